"""The matcher: extracts and matches the local features of two images with one :class:`~.config.MatchConfig`.

Scale maps reach the extractors in two ways. The patch extractor cuts each keypoint's patch
with the radius its map gives (:class:`~localscale.features.extractors.PatchExtractor`). Every
other extractor is scale-rectified: the pair's level ``S_{A->B}`` (:func:`~.rectification.pair_scale`,
the median of the maps) shrinks the image whose content is bigger by that factor before
extraction, or, for small images, shrinks it less and enlarges the other one
(:func:`~.rectification.rectify_factors`); the keypoints are mapped back to the given image's pixels.

Example::

    matcher = Matcher("aliked-lightglue")
    m = matcher.match(image_a, image_b)                       # H x W x 3 uint8 arrays
    m.keypoints_a[m.matches[:, 0]], m.keypoints_b[m.matches[:, 1]]
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable, Optional, Union

import cv2
import numpy as np
import torch

from ..core.devices import resolve_device
from ..core.errors import LocalScaleError
from ..features.extractors import Features
from .config import MatchConfig, match_config
from .nearest_neighbour import match_descriptors, ratio_mutual_matches
from .rectification import pair_scale, rectify_factors


@dataclass
class Matches:
    """What :meth:`Matcher.match` returns for one pair.

    Attributes:
        keypoints_a, keypoints_b: ``N_A x 2``, ``N_B x 2`` float32, pixels of the images given.
        matches: ``K x 2`` int64 indices (A, B).
        distances: ``K`` match costs, lower is better: descriptor distance (mutual NN) or
            ``1 - confidence`` (LightGlue).
        radii_a, radii_b: patch radii (patch extractor), else ``None``.
        frames_a, frames_b: the detector's own ``(size, angle)`` of each keypoint
            (:attr:`~localscale.features.Features.frames`; SIFT), else ``None``.
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
    frames_a: Optional[np.ndarray] = None
    frames_b: Optional[np.ndarray] = None
    factors: tuple = (1.0, 1.0)
    seconds: float = 0.0


class Matcher:
    """Extracts and matches local features with one :class:`~.config.MatchConfig`.

    Features of images given with a ``key`` (e.g. their path) are kept in a small cache:
    an image matched against several others (or with several maps) is extracted once per
    resize factor, and a patch keypoint whose corrected radius is unchanged reuses its descriptor.

    Args:
        config: a name of :data:`~.config.MATCHERS` or a :class:`~.config.MatchConfig`.
        device: torch device of the learned models.
        cache_size: images whose features are kept (0: none).
    """

    def __init__(self, config: Union[str, MatchConfig] = "hardnet", device: str = "cpu", cache_size: int = 8):
        self.config = config if isinstance(config, MatchConfig) else match_config(config)
        self.device = resolve_device(device)
        self.cache_size = cache_size
        self._cache: OrderedDict = OrderedDict()
        c = self.config
        self.extractor = c.extractor_class(self.device, weights=c.weights, **c.extractor_conf)
        self._lightglue = None
        if c.matching == "lightglue":
            from .lightglue import lightglue_runtime, load_lightglue

            net = load_lightglue(c.extractor, c.filter_threshold, c.depth_confidence, c.width_confidence, c.weights)
            self._lightglue = lightglue_runtime(net.to(self.device), c.lightglue_precision, self.device)

    @property
    def name(self) -> str:
        return self.config.name

    @property
    def described(self) -> int:
        """Patches described so far (patch keypoints whose radius is unchanged reuse theirs)."""
        return getattr(self.extractor, "described", 0)

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

        ``scale``: for the patch extractor the image's map ``S_{this->other}`` (or a float, or
        None); for the others the resize factor to extract at, keypoints returned in the given
        image's pixels. ``key``: identifies the image for the cache (None: no cache).
        """
        if not self.extractor.rectified:
            return self.extractor.extract(image, scale, self._cached((key, "patches"), dict))
        factor = 1.0 if scale is None else float(scale)
        return self._cached((key, "dense", round(factor, 6)), lambda: self.extractor.extract(image, factor))

    def extract_per_keypoint(self, image: np.ndarray, scale_map, key=None) -> Features:
        """Learned features of ``image`` on ``config.pyramid`` half-octave levels below its size, each
        keypoint taken from the level nearest (log2) to where its own local scale would shrink the
        image: ``min(1, S)`` of ``scale_map`` (``S_{this->other}``, a map of any resolution, or a
        float) at the keypoint. Keypoints in the given image's pixels; at most ``num_features``,
        the strongest."""
        c = self.config
        h, w = image.shape[:2]
        wanted = np.minimum(_log2_map(scale_map, h, w), 0.0)  # shrink where this image's content is bigger
        levels = np.asarray([-0.5 * k for k in range(c.pyramid + 1)])
        kps, descs, resps, seconds = [], [], [], 0.0
        for level in levels:
            f = self.extract(image, 2.0**level, key)
            seconds += f.seconds
            if not len(f.keypoints):
                continue
            x = np.clip(np.round(f.keypoints[:, 0]).astype(int), 0, w - 1)
            y = np.clip(np.round(f.keypoints[:, 1]).astype(int), 0, h - 1)
            keep = levels[np.argmin(np.abs(wanted[y, x][:, None] - levels[None]), 1)] == level
            kps.append(f.keypoints[keep])
            descs.append(f.descriptors[torch.from_numpy(keep)])
            resps.append(f.responses[keep])
        if not kps:
            return Features(
                np.zeros((0, 2), np.float32), torch.zeros(0, 1), np.zeros(0, np.float32), (h, w), seconds=seconds
            )
        kp, d, r = np.concatenate(kps), torch.cat(descs), np.concatenate(resps)
        order = np.argsort(-r, kind="stable")[: c.extractor_conf.get("num_features")]
        return Features(kp[order], d[torch.from_numpy(order)], r[order], (h, w), factor=1.0, seconds=seconds)

    # ---- matching

    def match_features(self, fa: Features, fb: Features) -> tuple[np.ndarray, np.ndarray]:
        """``(matches K x 2 int64, costs K)`` between two feature sets."""
        c = self.config
        if len(fa) == 0 or len(fb) == 0:
            return np.zeros((0, 2), np.int64), np.zeros(0, np.float32)
        if self._lightglue is not None:
            return self._match_lightglue(fa, fb)
        if c.ratio is not None and self.extractor.ratio_test == "a_to_b":  # Lowe's test A -> B, then the mutual check
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
            return {
                "keypoints": torch.from_numpy(kp)[None].to(self.device),
                "descriptors": f.descriptors[None].to(self.device),
                "image_size": torch.tensor([[fw, fh]], device=self.device),
            }

        with torch.inference_mode():
            out = self._lightglue({"image0": side(fa), "image1": side(fb)})
        m = out["matches"][0].cpu().numpy().astype(np.int64).reshape(-1, 2)
        scores = out["scores"][0].float().cpu().numpy().reshape(-1)
        return m, (1.0 - scores).astype(np.float32)

    def match(
        self,
        image_a: np.ndarray,
        image_b: np.ndarray,
        scale_a=None,
        scale_b=None,
        keys: tuple = (None, None),
        max_side: Optional[int] = None,
    ) -> Matches:
        """Extract and match two images (``H x W x 3`` uint8 RGB) with their scale maps.

        ``scale_a`` / ``scale_b``: ``S_{A->B}`` on A and ``S_{B->A}`` on B (maps, floats or None).
        The patch extractor corrects each patch's size by them; every other extractor
        shrinks the image whose content is bigger by the pair's level (:func:`~.rectification.pair_scale`)
        and enlarges the other up to a longer side of ``max_side`` (None: ``config.max_side``).
        ``keys``: cache keys of the two images (e.g. their paths).
        """
        c = self.config
        if not self.extractor.rectified:
            fa, fb = self.extract(image_a, scale_a, keys[0]), self.extract(image_b, scale_b, keys[1])
            factors = (1.0, 1.0)
        elif c.pyramid and any(isinstance(s, np.ndarray) and s.ndim == 2 for s in (scale_a, scale_b)):
            fa = self.extract_per_keypoint(image_a, scale_a, keys[0])
            fb = self.extract_per_keypoint(image_b, scale_b, keys[1])
            factors = (1.0, 1.0)
        else:
            factors = rectify_factors(
                pair_scale(scale_a, scale_b),
                shapes=(image_a.shape, image_b.shape),
                min_side=c.rectify_min_side,
                max_side=c.max_side if max_side is None else max_side,
            )
            fa, fb = self.extract(image_a, factors[0], keys[0]), self.extract(image_b, factors[1], keys[1])
        t0 = time.perf_counter()
        m, dist = self.match_features(fa, fb)
        seconds = fa.seconds + fb.seconds + time.perf_counter() - t0
        return Matches(
            fa.keypoints,
            fb.keypoints,
            m,
            dist,
            fa.radii,
            fb.radii,
            fa.frames,
            fb.frames,
            (fa.factor, fb.factor),
            seconds,
        )


def _log2_map(scale_map, h: int, w: int) -> np.ndarray:
    """``log2`` of a scale map (any resolution, resized to ``h x w``), a float or None (0)."""
    if isinstance(scale_map, np.ndarray) and scale_map.ndim == 2:
        log_map = np.log2(np.clip(np.nan_to_num(scale_map.astype(np.float32), nan=1.0), 1e-3, None))
        return cv2.resize(log_map, (w, h), interpolation=cv2.INTER_LINEAR) if log_map.shape != (h, w) else log_map
    value = 1.0 if scale_map is None else float(scale_map)
    return np.full((h, w), math.log2(value) if value > 0 and math.isfinite(value) else 0.0, np.float32)


def get_matcher(matcher: Union[str, MatchConfig, Matcher, None] = "hardnet", **options) -> Matcher:
    """A :class:`Matcher` from a name of :data:`~.config.MATCHERS`, a :class:`~.config.MatchConfig`
    (``options`` replace its fields) or a :class:`Matcher` (returned as it is; no options then)."""
    if isinstance(matcher, Matcher):
        if options:
            raise LocalScaleError(
                f"match options ({', '.join(sorted(options))}) cannot change a built Matcher; "
                "give a name or a MatchConfig instead"
            )
        return matcher
    return Matcher(match_config(matcher, **options))
