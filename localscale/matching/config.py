"""Matcher configurations: :class:`MatchConfig` and the named ones users pick (:data:`MATCHERS`).

The named configurations are those the registered extractors declare
(:mod:`localscale.features.registry`); seven ship with localscale:

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
checked once, when it is made (:meth:`MatchConfig.check`), and used as it is below that. The
extractor's own options live in ``extractor_conf``; given by name, as the other fields are, they go there.

Example::

    cfg = match_config("aliked-lightglue", num_features=1024)
    cfg.extractor_conf                                   # {"model": "aliked-n16", "num_features": 1024, ...}
    MatchConfig(descriptor="sift", num_features=500)     # patches described by SIFT
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Optional

from ..core.checks import check_int, check_number
from ..core.errors import LocalScaleError
from ..features.extractors import get_extractor, named_matchers
from .auto.config import AutoConfig
from .correction import CorrectionGate
from .lightglue import LIGHTGLUE_PRECISIONS
from .verification import VerificationConfig

#: matching rules a :class:`MatchConfig` can name
MATCHINGS = ("mnn", "lightglue")


@dataclass
class _MatchFields:
    name: str = "hardnet"
    extractor: str = "patches"
    matching: str = "mnn"
    max_side: Optional[int] = 2048
    rectify_min_side: int = 640
    pyramid: int = 0
    ratio: Optional[float] = None
    min_similarity: float = -1.0
    weights: Optional[str] = None
    filter_threshold: float = 0.1
    depth_confidence: Optional[float] = None
    width_confidence: Optional[float] = None
    lightglue_precision: str = "fp32"
    gate: CorrectionGate = field(default_factory=CorrectionGate)
    bf16: bool = False
    refine: bool = False
    max_passes: int = 2
    sift_seed: bool = True
    verification: VerificationConfig = field(default_factory=VerificationConfig)
    auto: AutoConfig = field(default_factory=AutoConfig)
    extractor_conf: dict = field(default_factory=dict)

    def __post_init__(self):
        self.check()


_FIELD_NAMES = frozenset(f.name for f in dataclasses.fields(_MatchFields))


class MatchConfig(_MatchFields):
    """How two images are matched (one entry of :data:`MATCHERS`, or your own).

    Attributes:
        name: label in results and pictures.
        extractor: a registered extractor (:data:`~localscale.features.registry.EXTRACTORS`):
            ``patches`` (detector + scale-corrected patches + patch descriptor), ``sift``
            (OpenCV), ``aliked``, ``disk`` or ``xfeat`` (kornia, pre-trained weights).
        extractor_conf: the extractor's options (its ``default_conf``, e.g. ``num_features``,
            the ``patches`` extractor's ``descriptor``, ``detector``, ``descriptor_precision``,
            ``base_radius``, ``orientation``, ALIKED's ``model``, ``channels_last``, the learned
            ones' ``detection_threshold``), completed by its defaults. Given by name to
            :class:`MatchConfig` or :func:`match_config`, as a field is, an option goes here, and
            reads back by name (``cfg.num_features``).
        matching: ``mnn`` (mutual nearest neighbours) or ``lightglue`` (extractors with LightGlue weights).
        max_side: working resolution, longer side in pixels (None: full resolution); keypoints
            are returned in full-image pixels.
        pyramid: learned extractors given scale maps: extract on this many half-octave levels
            below the working size as well and give each keypoint the level its own local scale
            selects (:meth:`Matcher.extract_per_keypoint`; 0: one rectification by the maps' level).
        rectify_min_side: scale rectification of the learned extractors shrinks the image whose
            content is bigger down to this longer side at most, and enlarges the other one for
            the rest, up to ``max_side`` (:func:`rectify_factors`).
        ratio: Lowe's ratio on top of mutual NN (``None``: mutual NN only; ``patches``: kornia's
            symmetric test, ``sift``: from A to B, as OpenCV's ``knnMatch`` users do).
        min_similarity: ``mnn`` of learned descriptors: cosine similarity a match must exceed.
        weights: folder (or file) of the extractor's pre-trained weight files and its LightGlue's
            (None: the installed weight packages); an extractor without weight files refuses it.
        filter_threshold: LightGlue's match confidence threshold.
        depth_confidence, width_confidence: LightGlue's adaptive depth (early stop) and width (point
            pruning) confidences, -1 turns one off (None: kornia's value for the extractor:
            ALIKED / DISK 0.95 / 0.99, LighterGlue off / 0.95).
        lightglue_precision: LightGlue's run-time precision (:data:`~.lightglue.LIGHTGLUE_PRECISIONS`):
            ``fp32`` (the default of two-view matching), ``auto`` (bfloat16 autocast on a CPU that
            computes bfloat16 natively, else float32: the default of ``reconstruct``, which matches
            thousands of pairs), ``bf16`` (kornia's mixed precision), ``int8`` (dynamic int8 linear
            layers, CPU).
        gate: gating of predicted scale maps (:class:`~.correction.CorrectionGate`).
        bf16: run the scale networks under bfloat16 autocast.
        refine, max_passes, sift_seed, verification: verify the matches, refine the maps by the
            verified geometry and match again (:func:`~.refinement.refine_passes`).
        auto: the hypothesis loop of ``correction="auto"`` (:class:`~.auto.AutoConfig`: budget, acceptance).
    """

    def __init__(self, *args, **options):
        conf = {k: options.pop(k) for k in list(options) if k not in _FIELD_NAMES}
        if conf:
            options["extractor_conf"] = {**(options.get("extractor_conf") or {}), **conf}
        super().__init__(*args, **options)

    def __getattr__(self, name):
        conf = self.__dict__.get("extractor_conf")
        if conf is not None and name in conf:
            return conf[name]
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def __setattr__(self, name, value):
        conf = self.__dict__.get("extractor_conf")
        if name not in _FIELD_NAMES and conf is not None and name in conf:
            conf[name] = value
        else:
            object.__setattr__(self, name, value)

    @property
    def extractor_class(self) -> type:
        """The registered class of :attr:`extractor`."""
        return get_extractor(self.extractor)

    def check(self) -> "MatchConfig":
        """Raise :class:`LocalScaleError` naming the first value that cannot work; returns ``self``
        (with :attr:`extractor_conf` completed by the extractor's defaults)."""
        cls = self.extractor_class
        if not isinstance(self.extractor_conf, dict):
            raise LocalScaleError(f"extractor_conf must be a dict, got {type(self.extractor_conf).__name__}")
        unknown = sorted(set(self.extractor_conf) - set(cls.default_conf))
        if unknown:
            raise LocalScaleError(
                f"unknown match option(s) {', '.join(unknown)}: MatchConfig has {', '.join(sorted(_FIELD_NAMES))}, "
                f"the {self.extractor} extractor {', '.join(sorted(cls.default_conf)) or 'no options'}"
            )
        self.extractor_conf = cls.check_conf(self.extractor_conf)
        if self.matching not in MATCHINGS:
            raise LocalScaleError(f"matching must be one of {MATCHINGS}, got {self.matching!r}")
        if self.matching == "lightglue" and cls.lightglue_weights is None:
            raise LocalScaleError(f"the {self.extractor} extractor has no LightGlue weights (matching 'mnn')")
        if self.weights is not None and not cls.weights:
            raise LocalScaleError(
                f"weights: the {self.extractor} extractor loads no weight files (bundled weights or none)"
            )
        self._check_numbers()
        for name, kind in (("gate", CorrectionGate), ("verification", VerificationConfig), ("auto", AutoConfig)):
            if not isinstance(getattr(self, name), kind):
                raise LocalScaleError(f"{name} must be a {kind.__name__}, got {type(getattr(self, name)).__name__}")
        self.auto.check()
        if self.auto.seed is not None and self.auto.seed not in named_matchers():
            raise LocalScaleError(
                f"auto seed must be None or one of {', '.join(named_matchers())}, got {self.auto.seed!r}"
            )
        return self

    def _check_numbers(self) -> None:
        if self.max_side is not None:
            check_int(self.max_side, "max_side", 16)
        check_int(self.rectify_min_side, "rectify_min_side", 0)
        check_int(self.pyramid, "pyramid", 0)
        if self.ratio is not None:
            check_number(self.ratio, "ratio", low=0.0, high=1.0)
        check_number(self.min_similarity, "min_similarity", low=-1.0, high=1.0, inclusive=True)
        check_number(self.filter_threshold, "filter_threshold", low=0.0, high=1.0, inclusive=True)
        for name in ("depth_confidence", "width_confidence"):
            v = getattr(self, name)
            if v is not None and v != -1:
                try:
                    check_number(v, name, low=0.0, high=1.0)
                except LocalScaleError:
                    raise LocalScaleError(f"{name} must be in (0, 1] or -1 (off), got {v!r}") from None
        check_int(self.max_passes, "max_passes", 1)
        if self.lightglue_precision not in LIGHTGLUE_PRECISIONS:
            raise LocalScaleError(
                f"lightglue_precision must be one of {', '.join(LIGHTGLUE_PRECISIONS)}, got {self.lightglue_precision!r}"
            )


class _NamedMatchers(Mapping):
    """The named configurations of the registered extractors (name -> :class:`MatchConfig`), built
    from :func:`~localscale.features.registry.named_matchers` whenever the registry changes."""

    def __init__(self):
        self._key, self._table = None, {}

    def _current(self) -> dict:
        named = named_matchers()
        key = tuple((n, cls, repr(opts)) for n, (cls, opts) in named.items())
        if key != self._key:
            self._table = {
                n: MatchConfig(name=n, extractor=cls.name, max_side=cls.max_side, **opts)
                for n, (cls, opts) in named.items()
            }
            self._key = key
        return self._table

    def __getitem__(self, name: str) -> MatchConfig:
        return self._current()[name]

    def __iter__(self):
        return iter(self._current())

    def __len__(self) -> int:
        return len(self._current())

    def __repr__(self) -> str:
        return f"MATCHERS({', '.join(self)})"


#: the named configurations; ``Matcher(name)`` / ``localscale match --matcher NAME``
MATCHERS = _NamedMatchers()


def match_config(matcher=None, **options) -> MatchConfig:
    """The :class:`MatchConfig` of a name of :data:`MATCHERS` (or a config), with ``options``
    replacing its fields or its extractor's options: a new, checked config (every
    :class:`MatchConfig` is checked when it is made). Another ``extractor`` starts from its defaults."""
    if matcher is None:
        matcher = "hardnet"
    if isinstance(matcher, str):
        if matcher not in MATCHERS:
            raise LocalScaleError(f"unknown matcher {matcher!r}; choose from {', '.join(MATCHERS)}")
        matcher = MATCHERS[matcher]
    if not isinstance(matcher, MatchConfig):
        raise LocalScaleError(f"matcher must be a name of MATCHERS or a MatchConfig, got {type(matcher).__name__}")
    if options.get("extractor", matcher.extractor) != matcher.extractor:
        options.setdefault("extractor_conf", {})
    elif "extractor_conf" in options:
        options["extractor_conf"] = {**matcher.extractor_conf, **options["extractor_conf"]}
    return dataclasses.replace(matcher, **options)
