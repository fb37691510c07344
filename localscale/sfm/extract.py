"""The extract step: the local features of every image, extracted once (``features.h5``, hloc layout).

:func:`extract_features` runs a matcher's extractor (a name of
:data:`~localscale.matching.MATCHERS`, the same names ``--matcher`` takes) on each image at its
working resolution (longer side ``max_side``) and stores the keypoints in full-image pixels.
An image already in ``features.h5`` is skipped (a rerun resumes).

For corrections that match a pair at another scale or quarter turn (``auto``, ``global``, ...),
:class:`LevelMatcher` is the matcher the pairs share: the resize factors are snapped to a grid of
levels (``2^(k / levels_per_octave)``, half octaves by default) and kept per image, so the features of one image at one
level (and turn) are computed once and reused by every pair that needs them; the base level (1)
comes from ``features.h5``.

Example::

    from localscale.sfm import find_images, extract_features
    images = find_images("photos/")
    extract_features(images, "out/features.h5", matcher="aliked-lightglue", num_keypoints=2048)
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from ..matching.matcher import Matcher
from .config import ReconstructConfig
from .h5io import H5Writer, groups_with, read_group
from .progress import progress
from .steps import config_of, parser, run_step, step_images


@dataclass(frozen=True)
class FeatureConf:
    """What the features are: a matcher name of :data:`~localscale.matching.MATCHERS` and its
    keypoint count and working resolution (None: the matcher's own), and LightGlue's run-time
    precision (``MatchConfig.lightglue_precision``; no effect on the extracted features)."""

    matcher: str = "aliked-lightglue"
    num_keypoints: Optional[int] = 2048
    max_side: Optional[int] = 1024
    lightglue_precision: str = "auto"

    def options(self) -> dict:
        out = {}
        if self.num_keypoints is not None:
            out["num_features"] = int(self.num_keypoints)
        if self.max_side is not None:
            out["max_side"] = int(self.max_side)
        out["lightglue_precision"] = self.lightglue_precision
        return out

    def match_config(self):
        from ..matching import match_config

        return match_config(self.matcher, **self.options())


class _FeatureConfs(Mapping):
    """A :class:`FeatureConf` per name of :data:`~localscale.matching.MATCHERS`: its own keypoint
    count at the working resolution of ``reconstruct`` (1024)."""

    def __getitem__(self, name: str) -> FeatureConf:
        if name not in self._names():
            raise KeyError(name)
        return FeatureConf(name, None, 1024)

    def __iter__(self):
        return iter(self._names())

    def __len__(self) -> int:
        return len(self._names())

    @staticmethod
    def _names():
        from ..matching import MATCHERS

        return MATCHERS


#: named feature configurations (hloc style); ``--matcher NAME`` with the CLI's ``--num-keypoints`` / ``--max-side``
CONFS = _FeatureConfs()


def load_working(image, max_side: Optional[int]):
    """``(rgb at the working resolution, S)``: S maps full-image pixels to working pixels."""
    from ..io import load_working_image

    return load_working_image(image.path, max_side, image.name)


def to_full(points: np.ndarray, S: np.ndarray) -> np.ndarray:
    """Working-resolution pixels -> full-image pixels (the inverse of ``S``, a scale and shift)."""
    p = np.asarray(points, np.float64).reshape(-1, 2)
    return ((p - S[:2, 2]) / np.diag(S)[:2]).astype(np.float32)


def to_working(points: np.ndarray, S: np.ndarray) -> np.ndarray:
    p = np.asarray(points, np.float64).reshape(-1, 2)
    return (p * np.diag(S)[:2] + S[:2, 2]).astype(np.float32)


def build_matcher(conf: FeatureConf, device: str = "cpu", num_images: int = 8, levels_per_octave: int = 2):
    """The :class:`LevelMatcher` of ``conf``, with room in its cache for every image's levels."""
    return LevelMatcher(
        conf.match_config(), device, cache_size=max(8, 2 * num_images), levels_per_octave=levels_per_octave
    )


def extract_features(
    images: list,
    features_path,
    conf: FeatureConf = FeatureConf(),
    device: str = "cpu",
    matcher=None,
    overwrite: bool = False,
    show_progress: bool = True,
    executor=None,
) -> Path:
    """Extract every image of ``images`` (:class:`~.images.ImageInfo`) not yet in ``features_path``
    (all of them with ``overwrite``) and write the file (hloc layout, :mod:`.h5io`).

    ``matcher``: a :class:`~localscale.matching.Matcher` to extract with (default: built from
    ``conf``); when it is a :class:`LevelMatcher`, the features also seed its level-1 cache.
    ``executor``: an :class:`~localscale.engine.Executor` other than the local one extracts on its
    workers (each builds its own matcher from ``conf``); the driver writes the file.
    """
    features_path = Path(features_path)
    done = set() if overwrite else set(groups_with(features_path, "keypoints"))
    todo = [im for im in images if im.name not in done]
    writer = H5Writer(features_path, fresh=overwrite)
    if todo and executor is not None and executor.name != "local":
        factory = MatcherFactory(conf, device, len(images))
        label = "extract" if show_progress else None
        for i, result in executor.map(ExtractImage(conf), todo, state=factory, progress=label, unit="image"):
            if isinstance(result, Exception):
                raise result
            writer.add(todo[i].name, *result)
            writer.maybe_flush()
    elif todo:
        matcher = matcher or build_matcher(conf, device, len(images))
        extract_one = ExtractImage(conf)
        for im in progress(todo, "extract", unit="image", disable=not show_progress):
            writer.add(im.name, *extract_one(matcher, im))
            writer.maybe_flush()
    if writer.pending or not features_path.exists():
        writer.flush()
    return features_path


@dataclass(frozen=True)
class MatcherFactory:
    """Worker state of the extraction and matching steps on an executor: the :class:`LevelMatcher` of ``conf``."""

    conf: FeatureConf
    device: str = "cpu"
    num_images: int = 8

    def __call__(self):
        return build_matcher(self.conf, self.device, self.num_images)


@dataclass(frozen=True)
class ExtractImage:
    """Work of one image (:class:`~.images.ImageInfo`): ``(datasets, attributes)`` of its ``features.h5`` group."""

    conf: FeatureConf

    def __call__(self, matcher, im) -> tuple[dict, dict]:
        rgb, S = load_working(im, self.conf.max_side)
        f = matcher.extract(rgb, None if not matcher.extractor.rectified else 1.0, im.name)
        desc = f.descriptors.detach().float().cpu().numpy()
        data = {
            "keypoints": to_full(f.keypoints, S),
            "scores": np.asarray(f.responses, np.float32).reshape(-1),
            "descriptors": np.ascontiguousarray(desc.T.astype(np.float32)),
            "image_size": np.array([im.shape[1], im.shape[0]], np.int64),
        }
        attrs = {
            "matcher": self.conf.matcher,
            "to_working": np.asarray(S, np.float64),
            "working_size": np.array([rgb.shape[1], rgb.shape[0]], np.int64),
        }
        return data, attrs


def read_features(features_path, name: str) -> dict:
    """``keypoints`` (N x 2 float32, full-image pixels), ``scores``, ``descriptors`` (D x N), ``image_size``."""
    return read_group(features_path, name, ("keypoints", "scores", "descriptors", "image_size"))


def features_for_matcher(features_path, name: str):
    """The stored features of image ``name`` as the matcher's :class:`~localscale.features.Features`
    at the working resolution (keypoints in working pixels, as the matcher extracted them), and
    the ``3 x 3`` map from full-image to working pixels."""
    import torch

    from ..features.extractors import Features

    d = read_group(features_path, name, ("keypoints", "scores", "descriptors", "image_size"))
    S = np.asarray(d["attrs"]["to_working"], np.float64)
    w, h = (int(v) for v in d["attrs"]["working_size"])
    desc = torch.from_numpy(np.ascontiguousarray(d["descriptors"].T.astype(np.float32)))
    return Features(to_working(d["keypoints"], S), desc, d["scores"].astype(np.float32), (h, w), factor=1.0), S


class LevelMatcher(Matcher):
    """A :class:`~localscale.matching.Matcher` whose resize factors snap to levels
    ``2^(k / levels_per_octave)``, so that an image's features at a level are extracted once and
    reused by every pair that needs that level (the cache key is ``(image, turn or window, level)``).

    ``extractions`` counts the extractor runs per cache key (each is 1 while the cache holds them all).
    """

    def __init__(self, config, device: str = "cpu", cache_size: int = 8, levels_per_octave: int = 2):
        super().__init__(config, device, cache_size)
        self.levels_per_octave = levels_per_octave
        self.extractions: Counter = Counter()

    def extract(self, image, scale=None, key=None):
        if self.extractor.rectified and scale is not None and key is not None:
            scale = snap_factor(float(scale), self.levels_per_octave)
        return super().extract(image, scale, key)

    def _cached(self, key, fn):
        def counted():
            self.extractions[key] += 1
            return fn()

        return super()._cached(key, counted)

    def seed(self, name: str, features) -> None:
        """Use ``features`` (working pixels, factor 1) as image ``name``'s level 1."""
        self._cache[(name, "dense", 1.0)] = features

    @property
    def level_count(self) -> int:
        """Feature sets computed (all images, levels, turns, windows)."""
        return sum(self.extractions.values())


def snap_factor(factor: float, levels_per_octave: int = 2) -> float:
    """The level nearest to ``factor`` (log2): ``2^(round(log2 f * n) / n)``; 1 stays 1."""
    if not (factor > 0 and math.isfinite(factor)) or levels_per_octave <= 0:
        return factor
    return float(2.0 ** (round(math.log2(factor) * levels_per_octave) / levels_per_octave))


def extract_folder(images_dir, features_path, conf: Optional[ReconstructConfig] = None, device="cpu", **kw):
    """The extract step from paths: every image of ``images_dir`` into ``features_path``."""
    conf = conf or ReconstructConfig()
    images = step_images(images_dir, Path(features_path).parent, conf)
    Path(features_path).parent.mkdir(parents=True, exist_ok=True)
    f = conf.features
    return extract_features(images, features_path, FeatureConf(f.matcher, f.num_keypoints, f.max_side), device, **kw)


def main(argv=None) -> int:
    """``python -m localscale.sfm.extract``: this step alone, from files (:func:`extract_folder`)."""
    p = parser("extract", __doc__, ("matcher", "max_side", "num_keypoints"))
    p.add_argument("images", help="folder of images (searched recursively)")
    p.add_argument("features", help="features.h5 to write (images already in it are skipped)")
    p.add_argument("--device", default="cpu", help="torch device")
    args = p.parse_args(argv)
    return run_step(lambda: extract_folder(args.images, args.features, config_of(args), args.device))


if __name__ == "__main__":
    raise SystemExit(main())
