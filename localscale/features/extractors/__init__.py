"""Local feature extractors, one module each (hloc style); importing the package registers them
(:mod:`localscale.features.registry`), in this order (the order of the named matchers):

* :mod:`.patches` (:class:`PatchExtractor`): a single-scale detector (Hessian by default) and a patch
  descriptor (HardNet by default) on patches whose size each keypoint's scale map corrects (the paper's path);
* :mod:`.sift` (:class:`SIFT`): OpenCV's SIFT (DoG keypoints and descriptors);
* :mod:`.aliked`, :mod:`.disk`, :mod:`.xfeat` (:class:`ALIKED`, :class:`DISK`, :class:`XFeat`):
  kornia's models with pre-trained weights found on disk (:mod:`..pretrained`; nothing is downloaded).

A new extractor is one module here (its class, decorated with ``@register``) and its import below.
"""

# the order of registration is the order of the named matchers
# isort: off
from .base import Extractor, Features, resize_image, to_given_pixels
from .patches import PatchExtractor, extract
from .sift import SIFT
from .aliked import ALIKED, ALIKED_MODELS
from .disk import DISK
from .xfeat import XFeat
from ..registry import EXTRACTORS, get_extractor, named_matchers, register
# isort: on

__all__ = [
    "EXTRACTORS",
    "get_extractor",
    "named_matchers",
    "register",
    "Extractor",
    "Features",
    "resize_image",
    "to_given_pixels",
    "PatchExtractor",
    "extract",
    "SIFT",
    "ALIKED",
    "ALIKED_MODELS",
    "DISK",
    "XFeat",
]
