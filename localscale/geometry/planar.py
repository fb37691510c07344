"""Planar prior: fit the scale field a homography can produce to a predicted scale map.

For a homography A->B the local scale is ``S(x) = sqrt|det H| / |w(x)|^1.5`` with
``w(x) = h31 x + h32 y + h33``. In coordinates normalised to A's frame this is a
3-parameter family, ``ln S(x) = c - 1.5 ln(1 + p . x)``. For planar scenes (HPatches-like
data, facades, documents, aerial views) fitting it to the network's noisy per-cell
prediction, weighted by confidence and robust to outliers (IRLS, Cauchy weights), removes most of
the noise. It is wrong for non-planar scenes, so it is an option, never the default.
"""

from __future__ import annotations

import numpy as np


def fit_planar_log_scale(
    log_scale: np.ndarray,
    weights: np.ndarray,
    points: np.ndarray,
    iterations: int = 20,
    cauchy_scale: float = 0.3,
    ridge: float = 0.0,
) -> np.ndarray:
    """Fit ``ln S = c - 1.5 ln(1 + p . x)`` to samples; returns ``(c, p1, p2)``.

    Args:
        log_scale: ``N`` observed ``ln S``.
        weights: ``N`` non-negative weights (e.g. confidence).
        points: ``N x 2`` normalised coordinates (roughly in [-1, 1]).
        ridge: pull of the perspective terms ``p`` towards 0, relative to the total weight.
    """
    w0 = np.clip(weights, 0, None).astype(np.float64)
    if w0.sum() <= 0:
        raise ValueError("fit_planar_log_scale: all weights are zero")
    theta = np.array([np.average(log_scale, weights=w0), 0.0, 0.0])
    for _ in range(iterations):
        d = 1 + points @ theta[1:]
        d = np.clip(d, 1e-3, None)
        model = theta[0] - 1.5 * np.log(d)
        r = log_scale - model
        robust = 1.0 / (1.0 + (r / cauchy_scale) ** 2)  # Cauchy: gross errors get ~no weight
        w = w0 * robust
        J = np.column_stack([np.ones_like(d), -1.5 * points[:, 0] / d, -1.5 * points[:, 1] / d])
        reg = np.diag([1e-6, 1e-6 + ridge * w.sum(), 1e-6 + ridge * w.sum()])
        A = J.T @ (J * w[:, None]) + reg
        step = np.linalg.solve(A, J.T @ (w * r) - reg @ np.r_[0.0, theta[1:]])
        new = theta + step
        # keep 1 + p.x > 0 over the samples (no horizon inside the image): halve the step if needed
        for _ in range(20):
            if (1 + points @ new[1:]).min() > 0.05:
                break
            step *= 0.5
            new = theta + step
        theta = new
        if np.abs(step).max() < 1e-6:
            break
    return theta


def planar_scale_map(theta: np.ndarray, height: int, width: int) -> np.ndarray:
    """Evaluate a fitted planar scale field at every pixel of an ``height x width`` image."""
    x, y = normalised_grid(height, width)
    return np.exp(theta[0] - 1.5 * np.log(np.clip(1 + theta[1] * x + theta[2] * y, 1e-3, None))).astype(np.float32)


def normalised_grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates mapped so the longer side spans [-1, 1] (centred)."""
    half = max(height, width) / 2
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    return (xs - (width - 1) / 2) / half, (ys - (height - 1) / 2) / half


def planarize(scale: np.ndarray, confidence: np.ndarray, stride: int = 8, ridge: float = 0.0) -> np.ndarray:
    """Replace a predicted ``H x W`` scale map by its best planar fit (confidence-weighted)."""
    h, w = scale.shape
    x, y = normalised_grid(h, w)
    sl = (slice(stride // 2, None, stride), slice(stride // 2, None, stride))
    pts = np.column_stack([x[sl].ravel(), y[sl].ravel()])
    theta = fit_planar_log_scale(np.log(scale[sl].ravel()), confidence[sl].ravel() ** 2, pts, ridge=ridge)
    return planar_scale_map(theta, h, w)
