"""Accuracy of matches and of estimated homographies against the truth.

* :func:`reprojection_errors`: ``|| H x_A - x_B ||`` in pixels of B for each match (the HPatches
  MMA protocol of D2-Net); :func:`matching_accuracy`: the fraction below thresholds.
* :func:`corner_error`, :func:`homography_auc`: mean error of A's four corners under an
  estimated vs the true homography, and the area under its cumulative curve up to a threshold.
"""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from ..geometry import project


def reprojection_errors(
    keypoints_a: np.ndarray, keypoints_b: np.ndarray, matches: np.ndarray, H: np.ndarray
) -> np.ndarray:
    """``|| H x_A - x_B ||`` (pixels of B) for each match; ``inf`` where ``H x_A`` is undefined."""
    matches = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
    if len(matches) == 0:
        return np.zeros(0, np.float64)
    pa = np.asarray(keypoints_a, np.float64)[matches[:, 0]]
    pb = np.asarray(keypoints_b, np.float64)[matches[:, 1]]
    err = np.linalg.norm(project(H, pa) - pb, axis=1)
    return np.where(np.isfinite(err), err, np.inf)


def matching_accuracy(errors: np.ndarray, thresholds: Sequence[float] = (5.0,)) -> np.ndarray:
    """Fraction of matches with error ``< t`` for each threshold (0 when there are no matches)."""
    errors = np.asarray(errors, np.float64)
    if errors.size == 0:
        return np.zeros(len(thresholds))
    return np.array([(errors < t).mean() for t in thresholds])


def corner_error(H_est: Optional[np.ndarray], H_true: np.ndarray, shape_a: tuple) -> float:
    """Mean distance (pixels of B) between A's four corners mapped by ``H_est`` and by ``H_true``;
    ``inf`` when ``H_est`` is ``None`` or maps a corner to infinity."""
    if H_est is None:
        return float("inf")
    h, w = shape_a[:2]
    c = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float64)
    e = np.linalg.norm(project(H_est, c) - project(H_true, c), axis=1)
    return float(e.mean()) if np.isfinite(e).all() else float("inf")


def homography_auc(errors: Sequence[float], thresholds: Sequence[float] = (3.0, 5.0, 10.0)) -> list:
    """Area under the cumulative corner-error curve up to each threshold, normalised to [0, 1]:
    the recall curve of the sorted errors, linearly interpolated from ``(0, 0)`` (the AUC of
    SuperGlue's evaluation). Failed estimates count as infinite errors."""
    e = np.sort(np.asarray(errors, np.float64))
    if e.size == 0:
        return [0.0 for _ in thresholds]
    recall = np.arange(1, len(e) + 1) / len(e)
    e, recall = np.r_[0.0, e], np.r_[0.0, recall]
    out = []
    for t in thresholds:
        i = int(np.searchsorted(e, t))
        x = np.r_[e[:i], t]
        y = np.r_[recall[:i], recall[i - 1]]
        out.append(float(np.trapezoid(y, x) / t) if hasattr(np, "trapezoid") else float(np.trapz(y, x) / t))
    return out
