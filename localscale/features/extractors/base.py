"""The base of the local feature extractors (hloc style: a ``default_conf``, options that replace it)
and the :class:`Features` they return.

An extractor is one class that declares what the rest of localscale asks of it (:class:`Extractor`)
and is registered by name (:func:`~localscale.features.registry.register`); the ones that ship with
localscale are the modules of this package. The dense extractors take a resize factor
(:meth:`Extractor.extract`); keypoints always come back in pixels of the image given.

Example::

    aliked = ALIKED(num_features=1024)
    f = aliked.extract(image)                  # H x W x 3 uint8 RGB
    f.keypoints, f.descriptors                 # N x 2 float32, N x 128
    f = aliked.extract(image, factor=0.5)      # extracted at half size, keypoints in the given pixels
    d = aliked.describe(image, f.keypoints, factor=2.0)  # the same keypoints described at twice the size
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np
import torch

from ...core.checks import check_int
from ...core.devices import resolve_device
from ...core.errors import LocalScaleError
from ..pretrained import WeightFile


@dataclass
class Features:
    """Local features of one image.

    Attributes:
        keypoints: ``N x 2`` float32 ``(x, y)`` in pixels of the image given to the extractor.
        descriptors: ``N x D`` float32 (L2-normalised).
        responses: ``N`` detector scores.
        image_shape: ``(H, W)`` of that image.
        radii: ``N`` patch radii (:class:`PatchExtractor`), else ``None``.
        lafs: ``1 x N x 2 x 3`` kornia LAFs (:class:`PatchExtractor`), else ``None``.
        frames: ``N x 2`` float32 ``(size, angle)``: the detector's own support diameter in pixels
            of the image given and orientation in degrees, OpenCV's convention (:class:`SIFT`), else ``None``.
        factor: the resize factor the image was extracted at (1: as given).
        seconds: the time the extraction took (also when the features come from a cache).
    """

    keypoints: np.ndarray
    descriptors: torch.Tensor
    responses: np.ndarray
    image_shape: tuple
    radii: Optional[np.ndarray] = None
    lafs: Optional[torch.Tensor] = None
    frames: Optional[np.ndarray] = None
    factor: float = 1.0
    seconds: float = 0.0

    def __len__(self) -> int:
        return len(self.keypoints)


def resize_image(image: np.ndarray, factor: float, min_side: int = 32) -> tuple[np.ndarray, float, float]:
    """``image`` resized by ``factor`` (when shrunk, the shorter side kept >= ``min_side``);
    returns it and the per-axis factors actually applied."""
    h, w = image.shape[:2]
    if factor > 1.0:
        nw, nh = max(1, round(w * factor)), max(1, round(h * factor))
        return cv2.resize(image, (nw, nh), interpolation=cv2.INTER_LINEAR), nw / w, nh / h
    factor = max(factor, min(1.0, min_side / max(1, min(h, w))))
    if factor >= 1.0:
        return image, 1.0, 1.0
    nw, nh = max(1, round(w * factor)), max(1, round(h * factor))
    return cv2.resize(image, (nw, nh), interpolation=cv2.INTER_AREA), nw / w, nh / h


def to_given_pixels(points: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """Pixel coordinates of a resized image (pixel-centre convention) -> those of the given one."""
    if fx == 1.0 and fy == 1.0:
        return points
    return ((points + 0.5) / np.array([fx, fy], np.float32) - 0.5).astype(np.float32)


class Extractor:
    """Base of the extractors. A subclass declares what localscale asks of it:

    * ``name``: its name in the registry and in :attr:`~localscale.matching.MatchConfig.extractor`;
    * ``default_conf``: its options (a :class:`~localscale.matching.MatchConfig` holds them in
      ``extractor_conf``), their values checked by :meth:`check_conf`;
    * ``weights``: the :class:`~localscale.features.pretrained.WeightFile` s it loads (those of one
      conf: :meth:`weight_files`), found by :func:`~localscale.features.pretrained.find_weights`;
    * ``lightglue``, ``lightglue_weights``: the LightGlue configuration of kornia whose weights fit
      its descriptors, and their file (None: no LightGlue);
    * ``max_side``: the working resolution (longer side) of its named matchers (None: full);
    * ``requires``: pip packages it needs beyond localscale's dependencies and its weight packages
      (:meth:`needs`);
    * ``patch_based``: scale maps size each keypoint's patch (``extract(image, scale_map, cache)``)
      instead of resizing the image by the pair's scale (``extract(image, factor)``);
    * ``matchers``: its named matchers, name -> :class:`~localscale.matching.MatchConfig` options
      (None: one, under its ``name``).

    A dense subclass implements ``_extract(image) -> (xy N x 2, desc N x D, scores N)``, or
    ``(..., frames N x 2)`` for a detector with its own size and orientation (:attr:`Features.frames`).
    """

    name: str = ""
    default_conf: dict = {}
    weights: tuple = ()
    lightglue: Optional[str] = None
    lightglue_weights: Optional[WeightFile] = None
    max_side: Optional[int] = 1024
    requires: tuple = ()
    patch_based: bool = False
    matchers: Optional[dict] = None
    #: Lowe's ratio test of mutual NN matching: ``symmetric`` (kornia's) or ``a_to_b`` (as OpenCV users do)
    ratio_test: str = "symmetric"

    def __init__(self, device: str = "cpu", weights=None, **conf):
        """``weights``: a folder holding the weight files, or the file (None: the installed packages)."""
        self.conf = self.check_conf(conf)
        self.weights_dir = weights
        self.device = resolve_device(device)

    @classmethod
    def check_conf(cls, conf: dict) -> dict:
        """``conf`` completed by :attr:`default_conf`; raises :class:`LocalScaleError` naming an
        option the extractor does not have or a value that cannot work (subclasses check theirs)."""
        unknown = sorted(set(conf) - set(cls.default_conf))
        if unknown:
            raise LocalScaleError(
                f"the {cls.name or cls.__name__} extractor has no option(s) {', '.join(unknown)}; "
                f"it takes {', '.join(sorted(cls.default_conf)) or 'none'}"
            )
        full = {**cls.default_conf, **conf}
        if "num_features" in full:
            check_int(full["num_features"], "num_features", 1)
        return full

    @classmethod
    def weight_files(cls, conf: dict) -> tuple:
        """The weight files an extractor of ``conf`` (complete) loads: all of :attr:`weights`
        unless a subclass picks."""
        return tuple(cls.weights)

    @classmethod
    def needs(cls, conf: Optional[dict] = None, lightglue: bool = False) -> str:
        """What it needs installed with ``conf`` (and its LightGlue), as ``--help`` says it."""
        files = list(cls.weight_files({**cls.default_conf, **(conf or {})}))
        if lightglue and cls.lightglue_weights is not None:
            files.append(cls.lightglue_weights)
        packages = list(dict.fromkeys([*cls.requires, *(f.pip_name for f in files)]))
        if not packages:
            return "nothing to install"
        names = ", ".join(f.filename for f in files)
        return f"{names} ({', '.join(packages)})" if names else ", ".join(packages)

    @property
    def rectified(self) -> bool:
        """The image is resized by the pair's scale (not :attr:`patch_based`)."""
        return not self.patch_based

    def extract(self, image: np.ndarray, factor: float = 1.0) -> Features:
        """Features of ``image`` (``H x W x 3`` uint8 RGB) extracted at ``factor`` times its size,
        keypoints in pixels of ``image``."""
        t0 = time.perf_counter()
        img, fx, fy = resize_image(np.asarray(image), float(factor))
        xy, desc, scores, *rest = self._extract(img)
        factor = float(np.sqrt(fx * fy))
        # sizes in the given image's pixels; the orientation is unchanged by the resize
        frames = (rest[0] * np.array([1.0 / factor, 1.0], np.float32)).astype(np.float32) if rest else None
        return Features(
            to_given_pixels(xy, fx, fy),
            desc,
            scores,
            tuple(image.shape[:2]),
            frames=frames,
            factor=factor,
            seconds=time.perf_counter() - t0,
        )

    def describe(self, image: np.ndarray, keypoints: np.ndarray, factor: float = 1.0) -> Features:
        """Descriptors of given ``keypoints`` (``N x 2``, pixels of ``image``) on ``image`` resized by
        ``factor`` (what :meth:`extract` would have described there, had it detected them). ALIKED
        and DISK describe (:attr:`describes`); the others raise a :class:`LocalScaleError`."""
        if not self.describes:
            raise LocalScaleError(f"{type(self).__name__} cannot describe given keypoints")
        t0 = time.perf_counter()
        img, fx, fy = resize_image(np.asarray(image), float(factor))
        kp = np.asarray(keypoints, np.float32).reshape(-1, 2)
        xy = (kp + 0.5) * np.array([fx, fy], np.float32) - 0.5
        desc = self._describe(img, np.clip(xy, 0, [img.shape[1] - 1, img.shape[0] - 1]).astype(np.float32))
        return Features(
            kp, desc, np.zeros(len(kp), np.float32), tuple(image.shape[:2]),
            factor=float(np.sqrt(fx * fy)), seconds=time.perf_counter() - t0,
        )  # fmt: skip

    @property
    def describes(self) -> bool:
        """Whether :meth:`describe` works (the extractor implements ``_describe``)."""
        return type(self)._describe is not Extractor._describe

    def _extract(self, image: np.ndarray):
        raise NotImplementedError

    def _describe(self, image: np.ndarray, xy: np.ndarray) -> torch.Tensor:
        """``N x D`` descriptors at ``xy`` (``N x 2``, pixels of ``image``)."""
        raise NotImplementedError

    def _tensor(self, image: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float().div(255).to(self.device)


def outputs(xy: torch.Tensor, desc: torch.Tensor, scores: torch.Tensor):
    """What ``_extract`` returns, from a model's tensors."""
    return (
        xy.float().cpu().numpy().astype(np.float32),
        desc.float().cpu(),
        scores.float().cpu().numpy().reshape(-1).astype(np.float32),
    )
