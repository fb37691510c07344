"""The seed matcher's part in ``correction="auto"``: its run on the images as they are, the
hypothesis its verified geometry gives (:func:`seed_hypothesis`), and otherwise the similarity its
matches' keypoints agree on (:func:`seed_similarity`), in the order tried (:func:`seed_choices`)."""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Optional

import numpy as np

from . import trial
from .config import AutoConfig
from .hypotheses import Hypothesis, geometry_hypothesis, mapping_hypothesis
from .localization import locate_similarity

#: inliers the seed matcher's geometry needs to be proposed, and the matcher's run at a verified
#: geometry's scale and turn needs to confirm it
GEOMETRY_MIN_INLIERS = 10


def seed_hypothesis(
    seed_matcher,
    a: np.ndarray,
    b: np.ndarray,
    keys: tuple,
    vconf,
    trials: list,
    window_share: float,
    cameras: tuple = (None, None),
    matched: Optional[list] = None,
    frames: Optional[list] = None,
) -> Optional[Hypothesis]:
    """The seed matcher's run on the images as they are (listed in ``trials``), and the hypothesis
    its verified geometry gives (``None`` if it did not verify). ``matched``: a list the run's
    matched points ``(N x 2 in A, N x 2 in B)`` are appended to; ``frames``: one their keypoints'
    ``(size, angle)`` (``N x 2`` each) are appended to, when the seed's detector has them."""
    name = seed_matcher.name
    seed = Hypothesis(1.0, 0, f"seed ({name})")
    t0 = time.perf_counter()
    # a proposal only (the matcher's own run at it is verified again): fewer inliers will do
    vconf = dataclasses.replace(vconf, min_inliers=min(vconf.min_inliers, GEOMETRY_MIN_INLIERS))
    found, v = trial.run_hypothesis(
        seed_matcher, a, b, seed, tuple(None if k is None else (k, "seed") for k in keys), vconf, cameras
    )
    trials.append(
        trial.Trial(seed, len(found.matches), v.num_inliers, v.inlier_ratio, bool(v.verified), time.perf_counter() - t0)
    )
    m = found.matches
    if matched is not None:
        matched.append((found.keypoints_a[m[:, 0]], found.keypoints_b[m[:, 1]]))
    if frames is not None and found.frames_a is not None and found.frames_b is not None:
        frames.append((found.frames_a[m[:, 0]], found.frames_b[m[:, 1]]))
    g = geometry_hypothesis(v, max_share=window_share)
    return None if g is None else dataclasses.replace(g, source=f"{name} geometry")


def seed_similarity(
    points_a, points_b, frames_a, frames_b, shape_a: tuple, shape_b: tuple, config: AutoConfig
) -> Optional[tuple[Hypothesis, int]]:
    """The scale, quarter turn and window (``config.similarity_margin``, ``config.window_share``)
    that the seed's matches (``N x 2`` points and ``(size, angle)`` frames in A and B) agree on by
    their keypoints' own sizes and orientations (:func:`~.localization.locate_similarity`, at least
    ``config.locate_votes``), and how many agree; ``None`` without such agreement."""
    found = locate_similarity(points_a, points_b, frames_a, frames_b, shape_a, shape_b, min_votes=config.locate_votes)
    if found is None:
        return None
    M, votes, inliers = found
    scale = float(np.sqrt(abs(np.linalg.det(M[:2, :2]))))
    h = mapping_hypothesis(
        M,
        scale,
        np.asarray(points_a)[inliers],
        shape_a,
        shape_b,
        "seed similarity",
        config.similarity_margin,
        config.window_share,
    )
    return h, votes


def seed_choices(
    g: Optional[Hypothesis],
    support: int,
    matched: list,
    frames: list,
    shape_a: tuple,
    shape_b: tuple,
    config: AutoConfig,
) -> list[tuple[Hypothesis, int]]:
    """The seed's hypotheses in the order they are tried, each with its support: ``g``, its verified
    geometry's (``support`` inliers), if any; before it, when it did not verify or gives a zoom of
    ``config.zoom_min_log2`` octaves or more no window, :func:`seed_similarity` of the seed's matched
    points and frames (as :func:`seed_hypothesis` lists them), if found and, after a verified
    geometry, if it has a window."""
    first = [] if g is None else [(g, support)]
    zoom_without_window = g is not None and g.window is None and abs(math.log2(g.scale)) >= config.zoom_min_log2
    if config.locate and matched and frames and (g is None or zoom_without_window):
        found = seed_similarity(*matched[0], *frames[0], shape_a, shape_b, config)
        if found is not None and (g is None or found[0].window is not None):
            first.insert(0, found)
    return first
