"""Geometric verification of a match set, refined scale maps, and homography accuracy.

* :func:`verify_matches`: a robust homography (OpenCV ``USAC_MAGSAC``) of the matched points,
  and optionally, when no homography explains them, a fundamental matrix (``USAC_MAGSAC``)
  whose inliers are kept only where a local affine fit of their neighbouring inliers agrees
  (non-planar scenes). The ``verified`` decision checks the inlier count, the inlier ratio, the
  spread of the inliers over image A (convex-hull area share), the sanity of the geometry's
  scale and its agreement with the network's scale map at the inliers (``log2``). Every
  threshold is a field of :class:`VerificationConfig`; every failed check is a reason.
* :func:`refine_scale_map`: the network map replaced, where a verified geometry explains the
  inliers, by the geometry's scale: the analytic map ``sqrt|det J_H(x)|`` of the homography
  over its support (co-visible region of A under ``H`` and the dilated inlier hull), or per-inlier
  scales of local affine fits interpolated between the inliers (fundamental-matrix case);
  blended with the network map in ``log2`` with a weight that decays with the distance to the
  support. Unverified: the network map unchanged, source all 0.
* :func:`refine_matching`: match, verify, refine the maps of both images, re-cut the patches
  with the refined maps and match again, until the inlier count stops growing; the pass with
  the most inliers is returned. When the first pass is not verified, an optional *seed* match
  set (e.g. OpenCV SIFT on a DoG scale space, :func:`sift_seed_points`, which finds matches under
  zoom where a single-scale detector does not) is verified with the same thresholds and, if it
  passes, gives the geometry of the refined maps for the second pass.
* :func:`corner_error`, :func:`homography_auc`: mean error of A's four corners under an
  estimated vs the true homography, and the area under its cumulative curve up to a threshold.

Conventions: points are ``(x, y)`` pixels (origin at the centre of the top-left pixel); scale
maps are ``S_{this->other}`` per pixel of their image (> 1: content bigger in the other image).

Example::

    v = verify_matches(pts_a, pts_b, a.shape[:2], b.shape[:2], scale_map=net_a)
    ref = refine_scale_map(net_a, v, a.shape[:2], b.shape[:2])
    ref.scale, ref.source, ref.verified
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import cv2
import numpy as np

from ..errors import LocalScaleError
from ..geometry import covisible_mask, homography_scale_at, homography_scale_map, orient_homography, project


@dataclass
class VerificationConfig:
    """Thresholds of :func:`verify_matches` and :func:`refine_scale_map`.

    Estimation:
        model: ``"homography"`` (planar scenes), ``"fundamental"`` (non-planar), or ``"auto"``
            (both; the fundamental matrix when it is verified and has ``auto_fundamental_gain`` times
            the homography's inliers or the homography is not verified, else the homography).
        auto_fundamental_gain: inlier ratio F / H above which ``"auto"`` prefers F.
        homography_threshold: MAGSAC reprojection threshold (pixels of B) of the homography.
        fundamental_threshold: MAGSAC threshold (pixels, distance to the epipolar line) of ``F``.
        confidence, max_iters: RANSAC confidence and iteration cap.
    Decision (each failing check adds a reason, any reason means not verified):
        min_inliers: inliers needed.
        min_inlier_ratio: inliers / matches needed.
        min_coverage: area of the inliers' convex hull / area of A needed.
        coverage_of: ``"a"``: that area in A; ``"either"``: the larger of the shares in A and in B
            (a strong zoom shows a small part of one image, but all of the other).
        max_scale_disagreement_log2: median ``|log2 S_geometry - log2 S_network|`` at the inliers
            allowed (a geometry that contradicts the network everywhere by more than this is rejected).
        scale_range_log2: the geometry's scale at every inlier must satisfy ``|log2 S| <=`` this
            (and ``w(x) > 0`` for a homography): degenerate fits are rejected.
    Local affine fits (fundamental case):
        affine_neighbours: inliers (the point itself included) in each local affine fit.
        affine_threshold: max residual (pixels of B) of a point and of its neighbours in their
            local affine fit; inliers of ``F`` without such a consistent fit are dropped.
    Refinement:
        support: ``"covisible"`` (the region of A that ``H`` maps into B, plus the dilated inlier hull)
            or ``"hull"`` (the dilated inlier hull only); fundamental case: the inliers themselves.
        hull_margin: dilation of the inlier hull, as a fraction of A's diagonal.
        decay: length (fraction of A's diagonal) over which the geometry's weight decays as
            ``exp(-d / (decay * diag))`` with the distance ``d`` to the support.
        interp_neighbours: inliers whose local scales are averaged (inverse distance, in log2) at
            each pixel (fundamental case).
        grid_stride: pixel stride of the interpolation grid (fundamental case), upsampled bilinearly.

    ``min_inliers``, ``min_inlier_ratio`` and ``support`` were chosen on held-out synthetic pairs
    (``eval/select_verification.py``; numbers in ``docs/RESULTS.md``): the smallest thresholds at
    which no verified homography made the map worse than the network's.
    """

    model: str = "homography"
    auto_fundamental_gain: float = 1.5
    homography_threshold: float = 3.0
    fundamental_threshold: float = 1.0
    confidence: float = 0.999
    max_iters: int = 10000
    min_inliers: int = 20
    min_inlier_ratio: float = 0.15
    min_coverage: float = 0.05
    coverage_of: str = "a"
    max_scale_disagreement_log2: float = 2.0
    scale_range_log2: float = 5.0
    affine_neighbours: int = 8
    affine_threshold: float = 4.0
    support: str = "covisible"
    hull_margin: float = 0.05
    decay: float = 0.1
    interp_neighbours: int = 8
    grid_stride: int = 8

    def check(self) -> "VerificationConfig":
        if self.model not in ("homography", "fundamental", "auto"):
            raise LocalScaleError(f"verification model must be homography, fundamental or auto, got {self.model!r}")
        if self.coverage_of not in ("a", "either"):
            raise LocalScaleError(f"verification coverage_of must be a or either, got {self.coverage_of!r}")
        if self.support not in ("covisible", "hull"):
            raise LocalScaleError(f"verification support must be covisible or hull, got {self.support!r}")
        if self.min_inliers < 4 or self.homography_threshold <= 0 or self.decay <= 0:
            raise LocalScaleError("verification config: min_inliers >= 4, thresholds and decay > 0 needed")
        return self


@dataclass
class VerificationResult:
    """Outcome of :func:`verify_matches` for ``K`` matches.

    Attributes:
        model: ``"homography"``, ``"fundamental"`` or ``"none"`` (nothing could be estimated).
        H: ``3 x 3`` homography A -> B (``None`` unless ``model == "homography"``).
        F: ``3 x 3`` fundamental matrix (``x_B^T F x_A = 0``; ``None`` unless ``model == "fundamental"``).
        inliers: ``K`` bool mask over the matches.
        verified: all checks passed; reasons: why not (empty when verified).
        points_a, points_b: ``K x 2`` matched points.
        local_scales: ``K`` geometry scale ``S_{A->B}`` at each match (nan where unknown).
        num_inliers, inlier_ratio, coverage, scale_disagreement_log2: the measured quantities.
        shape_a, shape_b: ``(height, width)`` of A and B.
    """

    model: str
    H: Optional[np.ndarray]
    F: Optional[np.ndarray]
    inliers: np.ndarray
    verified: bool
    reasons: list
    points_a: np.ndarray
    points_b: np.ndarray
    local_scales: np.ndarray
    num_inliers: int = 0
    inlier_ratio: float = 0.0
    coverage: float = 0.0
    scale_disagreement_log2: float = float("nan")
    shape_a: tuple = ()
    shape_b: tuple = ()

    def to_dict(self) -> dict:
        """JSON-ready summary (geometry, counts, decision; no per-match arrays)."""
        f = lambda x: None if x is None or not np.isfinite(x) else round(float(x), 6)  # noqa: E731
        return {"model": self.model, "verified": bool(self.verified), "reasons": list(self.reasons),
                "H": None if self.H is None else np.asarray(self.H).tolist(),
                "F": None if self.F is None else np.asarray(self.F).tolist(),
                "num_matches": int(len(self.inliers)), "num_inliers": int(self.num_inliers),
                "inlier_ratio": f(self.inlier_ratio), "coverage": f(self.coverage),
                "scale_disagreement_log2": f(self.scale_disagreement_log2),
                "shape_a": list(self.shape_a), "shape_b": list(self.shape_b)}

    def swapped(self) -> "VerificationResult":
        """The same verification seen from B (B -> A): inverse ``H``, transposed ``F``, inverse scales."""
        H = None if self.H is None else np.linalg.inv(self.H)
        F = None if self.F is None else self.F.T
        with np.errstate(divide="ignore", invalid="ignore"):
            ls = 1.0 / self.local_scales
        return VerificationResult(self.model, H, F, self.inliers, self.verified, list(self.reasons), self.points_b,
                                  self.points_a, ls, self.num_inliers, self.inlier_ratio, self.coverage,
                                  self.scale_disagreement_log2, self.shape_b, self.shape_a)


def _empty(points_a, points_b, shape_a, shape_b, reason) -> VerificationResult:
    k = len(points_a)
    return VerificationResult("none", None, None, np.zeros(k, bool), False, [reason], points_a, points_b,
                              np.full(k, np.nan), 0, 0.0, 0.0, float("nan"), tuple(shape_a), tuple(shape_b))


def estimate_homography(points_a: np.ndarray, points_b: np.ndarray, threshold: float = 3.0,
                        confidence: float = 0.999, max_iters: int = 10000):
    """Robust homography A -> B of ``K x 2`` point sets with OpenCV ``USAC_MAGSAC``.

    Returns ``(H 3 x 3 or None, inlier mask K bool)``.
    """
    return _robust_fit(points_a, points_b, 4,
                       lambda pa, pb: cv2.findHomography(pa, pb, cv2.USAC_MAGSAC, threshold, maxIters=max_iters,
                                                         confidence=confidence),
                       lambda H: abs(np.linalg.det(H)) >= 1e-12)


def estimate_fundamental(points_a: np.ndarray, points_b: np.ndarray, threshold: float = 1.0,
                         confidence: float = 0.999, max_iters: int = 10000):
    """Robust fundamental matrix (``x_B^T F x_A = 0``) with OpenCV ``USAC_MAGSAC``.

    Returns ``(F 3 x 3 or None, inlier mask K bool)``.
    """
    return _robust_fit(points_a, points_b, 8,
                       lambda pa, pb: cv2.findFundamentalMat(pa, pb, cv2.USAC_MAGSAC, threshold, confidence, max_iters),
                       lambda F: F.shape == (3, 3))


def _robust_fit(points_a, points_b, min_points: int, fit, valid):
    """``(M, inlier mask)`` of an OpenCV robust estimator ``fit(pa, pb) -> (M, mask)``; ``(None, all
    False)`` with fewer than ``min_points`` points, on an OpenCV error, or when ``M`` is missing,
    not finite or fails ``valid``."""
    pa = np.asarray(points_a, np.float64).reshape(-1, 2)
    pb = np.asarray(points_b, np.float64).reshape(-1, 2)
    none = None, np.zeros(len(pa), bool)
    if len(pa) < min_points:
        return none
    try:
        M, mask = fit(pa, pb)
    except cv2.error:
        return none
    if M is None or mask is None or not np.isfinite(M).all() or not valid(M):
        return none
    return M, mask.reshape(-1).astype(bool)


def local_affine_scales(points_a: np.ndarray, points_b: np.ndarray, neighbours: int = 8,
                        threshold: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """Scale ``sqrt|det A|`` of a least-squares affine map fitted to each point and its nearest
    neighbours (in A), and whether the fit is consistent (max residual <= ``threshold`` px of B).

    Args:
        points_a, points_b: ``K x 2`` corresponding points (inliers of a geometry).
    Returns:
        ``(scales K float64, consistent K bool)``; scales are nan where no fit exists.
    """
    pa = np.asarray(points_a, np.float64).reshape(-1, 2)
    pb = np.asarray(points_b, np.float64).reshape(-1, 2)
    k = len(pa)
    scales, ok = np.full(k, np.nan), np.zeros(k, bool)
    n = min(neighbours, k)
    if n < 4:
        return scales, ok
    d = np.linalg.norm(pa[:, None] - pa[None], axis=-1)
    nn = np.argsort(d, axis=1)[:, :n]
    for i in range(k):
        a, b = pa[nn[i]], pb[nn[i]]
        X = np.c_[a - a.mean(0), np.ones(n)]
        sol, *_ = np.linalg.lstsq(X, b - b.mean(0), rcond=None)
        A = sol[:2].T
        det = np.linalg.det(A)
        if not np.isfinite(det) or abs(det) < 1e-12:
            continue
        res = np.linalg.norm(X @ sol - (b - b.mean(0)), axis=1)
        scales[i] = math.sqrt(abs(det))
        ok[i] = bool(res.max() <= threshold)
    return scales, ok


def hull_coverage(points: np.ndarray, shape: tuple) -> float:
    """Area of the convex hull of ``K x 2`` points / area of an image of ``shape = (h, w)``."""
    pts = np.asarray(points, np.float32).reshape(-1, 2)
    if len(pts) < 3:
        return 0.0
    return float(cv2.contourArea(cv2.convexHull(pts)) / max(1.0, shape[0] * shape[1]))


def sample_map(scale_map, points: np.ndarray) -> np.ndarray:
    """Values of an ``H x W`` map (or a float; ``None`` = 1) at the nearest pixel of ``K x 2`` points."""
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    if scale_map is None:
        return np.ones(len(pts))
    if np.isscalar(scale_map):
        return np.full(len(pts), float(scale_map))
    m = np.asarray(scale_map)
    x = np.clip(np.round(pts[:, 0]).astype(int), 0, m.shape[1] - 1)
    y = np.clip(np.round(pts[:, 1]).astype(int), 0, m.shape[0] - 1)
    return m[y, x].astype(np.float64)


def verify_matches(points_a: np.ndarray, points_b: np.ndarray, shape_a: tuple, shape_b: tuple,
                   scale_map=None, config: VerificationConfig = VerificationConfig()) -> VerificationResult:
    """Estimate the geometry of a match set and decide whether it is verified.

    Args:
        points_a, points_b: ``K x 2`` matched points in A and B (pixels).
        shape_a, shape_b: ``(height, width)`` of A and B.
        scale_map: the network's ``S_{A->B}`` (``H_A x W_A``, a float, or ``None`` to skip the
            agreement check).
        config: thresholds (:class:`VerificationConfig`).
    Returns:
        :class:`VerificationResult`.
    """
    config.check()
    pa = np.asarray(points_a, np.float64).reshape(-1, 2)
    pb = np.asarray(points_b, np.float64).reshape(-1, 2)
    shape_a, shape_b = tuple(int(v) for v in shape_a[:2]), tuple(int(v) for v in shape_b[:2])
    if len(pa) < 4:
        return _empty(pa, pb, shape_a, shape_b, f"{len(pa)} matches, at least 4 needed")
    if config.model == "homography":
        return _verify_homography(pa, pb, shape_a, shape_b, scale_map, config)
    fres = _verify_fundamental(pa, pb, shape_a, shape_b, scale_map, config)
    if config.model == "fundamental":
        return fres
    hres = _verify_homography(pa, pb, shape_a, shape_b, scale_map, config)
    if fres.verified and (not hres.verified or fres.num_inliers >= config.auto_fundamental_gain * hres.num_inliers):
        return fres
    if hres.verified:
        return hres
    return fres if fres.num_inliers > hres.num_inliers else hres


def _decide(result: VerificationResult, scales_in: np.ndarray, net_in, config: VerificationConfig) -> None:
    k = len(result.inliers)
    n = int(result.inliers.sum())
    result.num_inliers = n
    result.inlier_ratio = n / k if k else 0.0
    result.coverage = hull_coverage(result.points_a[result.inliers], result.shape_a)
    if config.coverage_of == "either":
        result.coverage = max(result.coverage, hull_coverage(result.points_b[result.inliers], result.shape_b))
    reasons = []
    if n < config.min_inliers:
        reasons.append(f"{n} inliers < {config.min_inliers}")
    if result.inlier_ratio < config.min_inlier_ratio:
        reasons.append(f"inlier ratio {result.inlier_ratio:.3f} < {config.min_inlier_ratio}")
    if result.coverage < config.min_coverage:
        reasons.append(f"inliers cover {result.coverage:.3f} of {'A' if config.coverage_of == 'a' else 'A or B'} "
                       f"< {config.min_coverage}")
    ls = np.log2(scales_in) if len(scales_in) else np.zeros(0)
    if len(ls) and not (np.isfinite(ls).all() and np.abs(ls).max() <= config.scale_range_log2):
        reasons.append(f"degenerate geometry (scale beyond 2^+-{config.scale_range_log2} or behind the camera)")
    elif net_in is not None and len(ls):
        with np.errstate(divide="ignore", invalid="ignore"):
            dis = np.abs(ls - np.log2(net_in))
        dis = dis[np.isfinite(dis)]
        if dis.size:
            result.scale_disagreement_log2 = float(np.median(dis))
            if result.scale_disagreement_log2 > config.max_scale_disagreement_log2:
                reasons.append(f"geometry and network scales disagree by {result.scale_disagreement_log2:.2f} "
                               f"log2 > {config.max_scale_disagreement_log2}")
    result.reasons = reasons
    result.verified = not reasons


def _verify_homography(pa, pb, shape_a, shape_b, scale_map, config) -> VerificationResult:
    H, inl = estimate_homography(pa, pb, config.homography_threshold, config.confidence, config.max_iters)
    if H is None:
        return _empty(pa, pb, shape_a, shape_b, "no homography could be estimated")
    H = orient_homography(H / (H[2, 2] if abs(H[2, 2]) > 1e-9 * np.abs(H).max() else np.abs(H).max()), shape_a)
    w = pa @ H[2, :2] + H[2, 2]
    scales = np.where(w > 0, homography_scale_at(H, pa), np.nan)
    res = VerificationResult("homography", H, None, inl, False, [], pa, pb, scales, shape_a=shape_a, shape_b=shape_b)
    _decide(res, scales[inl], None if scale_map is None else sample_map(scale_map, pa[inl]), config)
    return res


def _verify_fundamental(pa, pb, shape_a, shape_b, scale_map, config) -> VerificationResult:
    F, inl = estimate_fundamental(pa, pb, config.fundamental_threshold, config.confidence, config.max_iters)
    if F is None:
        return _empty(pa, pb, shape_a, shape_b, "no fundamental matrix could be estimated")
    idx = np.flatnonzero(inl)
    scales = np.full(len(pa), np.nan)
    s, ok = local_affine_scales(pa[idx], pb[idx], config.affine_neighbours, config.affine_threshold)
    keep = idx[ok]
    inl = np.zeros(len(pa), bool)
    inl[keep] = True
    scales[keep] = s[ok]
    res = VerificationResult("fundamental", None, F, inl, False, [], pa, pb, scales, shape_a=shape_a, shape_b=shape_b)
    _decide(res, scales[inl], None if scale_map is None else sample_map(scale_map, pa[inl]), config)
    return res


# ---------------------------------------------------------------- refined maps

@dataclass
class RefinedScale:
    """A refined scale map of one image.

    Attributes:
        scale: ``H x W`` float32 refined ``S_{this->other}``.
        source: ``H x W`` float32 weight of the geometry in ``log2`` (0 = network map, 1 = geometry).
        verification: the :class:`VerificationResult` it came from (seen from this image).
        verified: whether a verified geometry was used.
    """

    scale: np.ndarray
    source: np.ndarray
    verification: VerificationResult
    verified: bool

    @property
    def H(self):
        return self.verification.H

    @property
    def F(self):
        return self.verification.F

    @property
    def inliers(self):
        return self.verification.inliers


def _network_log2(scale_map, shape) -> np.ndarray:
    if scale_map is None:
        return np.zeros(shape, np.float64)
    if np.isscalar(scale_map):
        return np.full(shape, math.log2(float(scale_map)))
    m = np.asarray(scale_map, np.float64)
    if m.shape != tuple(shape):
        raise LocalScaleError(f"scale map is {m.shape[1]}x{m.shape[0]}, image is {shape[1]}x{shape[0]}")
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.log2(m)


def _hull_mask(points: np.ndarray, shape, margin_px: float) -> np.ndarray:
    mask = np.zeros(shape, np.uint8)
    pts = np.round(np.asarray(points, np.float64)).astype(np.int32).reshape(-1, 2)
    if len(pts) >= 3:
        cv2.fillConvexPoly(mask, cv2.convexHull(pts), 1)
    else:
        for x, y in pts:
            mask[np.clip(y, 0, shape[0] - 1), np.clip(x, 0, shape[1] - 1)] = 1
    if margin_px >= 1 and mask.any():
        r = int(round(margin_px))
        mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    return mask.astype(bool)


def _distance_to(mask: np.ndarray) -> np.ndarray:
    """Euclidean distance (pixels) of every pixel to the nearest ``True`` pixel of ``mask``."""
    if not mask.any():
        return np.full(mask.shape, np.inf, np.float32)
    return cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 5)


def _interpolate_log_scales(points: np.ndarray, log_scales: np.ndarray, shape, neighbours: int, stride: int):
    """Inverse-distance interpolation of per-point ``log2`` scales over an image; returns
    ``(log2 map H x W, distance to the nearest point H x W)``."""
    h, w = shape
    gh, gw = math.ceil(h / stride), math.ceil(w / stride)
    gx, gy = np.meshgrid(np.arange(gw) * stride + (stride - 1) / 2, np.arange(gh) * stride + (stride - 1) / 2)
    g = np.stack([gx.ravel(), gy.ravel()], 1)
    d = np.linalg.norm(g[:, None] - points[None], axis=-1)
    n = min(neighbours, len(points))
    nn = np.argpartition(d, n - 1, axis=1)[:, :n] if n < len(points) else np.tile(np.arange(len(points)), (len(g), 1))
    dn = np.take_along_axis(d, nn, 1)
    wts = 1.0 / np.maximum(dn, 1.0) ** 2
    val = (wts * log_scales[nn]).sum(1) / wts.sum(1)
    grid = val.reshape(gh, gw).astype(np.float32)
    full = cv2.resize(grid, (gw * stride, gh * stride), interpolation=cv2.INTER_LINEAR)[:h, :w]
    mask = np.zeros((h, w), bool)
    pi = np.clip(np.round(points).astype(int), 0, [w - 1, h - 1])
    mask[pi[:, 1], pi[:, 0]] = True
    return full.astype(np.float64), _distance_to(mask)


def refine_scale_map(scale_map, verification: VerificationResult, shape: Optional[tuple] = None,
                     config: VerificationConfig = VerificationConfig()) -> RefinedScale:
    """The network's map refined by a verified geometry (module docstring).

    Args:
        scale_map: the network's ``S_{A->B}`` (``H_A x W_A``), a float, or ``None`` (= 1).
        verification: :class:`VerificationResult` of matches A -> B.
        shape: ``(height, width)`` of A (default: ``verification.shape_a``).
        config: support, decay and interpolation settings.
    Returns:
        :class:`RefinedScale` (``H_A x W_A`` scale and source weight).
    """
    config.check()
    shape = tuple(shape or verification.shape_a)[:2]
    net = _network_log2(scale_map, shape)
    if not verification.verified or verification.model == "none":
        base = np.exp2(net).astype(np.float32) if scale_map is not None else np.ones(shape, np.float32)
        return RefinedScale(base, np.zeros(shape, np.float32), verification, False)
    diag = math.hypot(*shape)
    inl_a = verification.points_a[verification.inliers]
    if verification.model == "homography":
        H = orient_homography(verification.H, shape)
        geo = np.log2(homography_scale_map(H, *shape))
        support = _hull_mask(inl_a, shape, config.hull_margin * diag)
        if config.support == "covisible" and verification.shape_b:
            support |= covisible_mask(H, shape, verification.shape_b)
        support &= np.isfinite(geo)
    else:
        ls = np.log2(verification.local_scales[verification.inliers])
        geo, _ = _interpolate_log_scales(inl_a, ls, shape, config.interp_neighbours, config.grid_stride)
        support = np.zeros(shape, bool)
        pi = np.clip(np.round(inl_a).astype(int), 0, [shape[1] - 1, shape[0] - 1])
        support[pi[:, 1], pi[:, 0]] = True
    dist = _distance_to(support)
    weight = np.exp(-dist / (config.decay * diag)).astype(np.float64)
    ok = np.isfinite(geo)
    weight[~ok] = 0.0
    net_ok = np.isfinite(net)
    out = np.where(net_ok, net, 0.0) * (1 - weight) + np.where(ok, geo, 0.0) * weight
    out = np.where(net_ok | (weight > 0), out, net)
    return RefinedScale(np.exp2(out).astype(np.float32), weight.astype(np.float32), verification, True)


def refine_pair_maps(scale_a, scale_b, verification: VerificationResult,
                     config: VerificationConfig = VerificationConfig()) -> tuple[RefinedScale, RefinedScale]:
    """Refined maps of both images: A's from ``verification``, B's from its swapped view."""
    return (refine_scale_map(scale_a, verification, verification.shape_a, config),
            refine_scale_map(scale_b, verification.swapped(), verification.shape_b, config))


# ---------------------------------------------------------------- second pass

@dataclass
class RefinedMatching:
    """Outcome of :func:`refine_matching`.

    Attributes:
        keypoints_a, keypoints_b: ``N_A x 2``, ``N_B x 2``; matches: ``K x 2`` int64; distances: ``K``.
        verification: :class:`VerificationResult` of these matches.
        refined_a, refined_b: :class:`RefinedScale` of A and B from the returned pass's geometry.
        passes: matching passes run; inlier_counts: inliers after each pass;
        best_pass: index of the returned pass (0 = the first, with the initial maps).
        seed: verification of the seed match set when it was tried, else ``None``.
    """

    keypoints_a: np.ndarray
    keypoints_b: np.ndarray
    matches: np.ndarray
    distances: np.ndarray
    verification: VerificationResult
    refined_a: RefinedScale
    refined_b: RefinedScale
    passes: int
    inlier_counts: list = field(default_factory=list)
    best_pass: int = 0
    seed: Optional[VerificationResult] = None


def refine_matching(match: Callable, shape_a: tuple, shape_b: tuple,
                    first_a=None, first_b=None, prior_a=None, prior_b=None,
                    config: VerificationConfig = VerificationConfig(), max_passes: int = 2,
                    seed: Optional[Callable] = None) -> RefinedMatching:
    """Match, verify, refine both maps and match again with them while the inlier count grows.

    Args:
        match: ``f(map_a, map_b) -> (keypoints_a N_A x 2, keypoints_b N_B x 2, matches K x 2, costs K)``,
            the pair matched with these scale maps (``None`` = no correction), e.g.
            :meth:`localscale.features.matchers.Matcher.match` or :func:`describe_and_match`.
        shape_a, shape_b: ``(height, width)``.
        first_a, first_b: maps of the first matching pass (e.g. the gated network maps).
        prior_a, prior_b: network maps the refined maps start from (default: ``first_*``).
        config: :class:`VerificationConfig`.
        max_passes: matching passes at most (1 = no second pass); passes stop early when the
            inlier count does not grow or verification fails.
        seed: ``f() -> (points_a K x 2, points_b K x 2)``, another match set of the pair, verified
            (same thresholds) when the first pass is not; its geometry then refines the maps.
    Returns:
        :class:`RefinedMatching`: the matches of the pass with the most inliers (the earliest on
        ties); the refined maps of the last verified geometry of a pass that grew the inlier count
        (or of the seed), else the priors unchanged.
    """
    if max_passes < 1:
        raise LocalScaleError(f"max_passes must be >= 1, got {max_passes}")
    prior_a = first_a if prior_a is None else prior_a
    prior_b = first_b if prior_b is None else prior_b
    maps = (first_a, first_b)
    best, counts, geometry, seeded = None, [], None, None
    for i in range(max_passes):
        ka, kb, m, dist = match(maps[0], maps[1])
        m = np.asarray(m, np.int64).reshape(-1, 2)
        ka, kb, dist = np.asarray(ka), np.asarray(kb), np.asarray(dist)
        v = verify_matches(ka[m[:, 0]], kb[m[:, 1]], shape_a, shape_b, prior_a, config)
        counts.append(v.num_inliers)
        grew = best is None or v.num_inliers > best.verification.num_inliers
        if grew:
            best = RefinedMatching(ka, kb, m, dist, v, None, None, i + 1, counts, i)
        if grew and v.verified:
            geometry = v
        elif i == 0 and seed is not None:
            pa, pb = seed()
            seeded = verify_matches(pa, pb, shape_a, shape_b, prior_a, config)
            geometry = seeded if seeded.verified else None
        else:
            break
        if geometry is None:
            break
        ra, rb = refine_pair_maps(prior_a, prior_b, geometry, config)
        maps = (ra.scale, rb.scale)
        best.refined_a, best.refined_b = ra, rb
    if best.refined_a is None:
        best.refined_a, best.refined_b = refine_pair_maps(prior_a, prior_b, best.verification, config) \
            if geometry is None else refine_pair_maps(prior_a, prior_b, geometry, config)
    best.passes, best.inlier_counts, best.seed = len(counts), counts, seeded
    return best


def describe_and_match(describe_a: Callable, describe_b: Callable, ratio: Optional[float] = None) -> Callable:
    """The ``match`` of :func:`refine_matching` from two describers ``f(scale_map) -> (keypoints
    N x 2, descriptors N x D)``: mutual nearest neighbours (with Lowe's ``ratio`` if given)."""
    from .matching import match_descriptors

    def match(map_a, map_b):
        ka, da = describe_a(map_a)
        kb, db = describe_b(map_b)
        dist, idx = match_descriptors(da, db, ratio)
        return ka, kb, idx.numpy(), dist.numpy()

    return match


def sift_seed_points(image_a, image_b, num_features: int = 1000, ratio: float = 0.8):
    """Matches of OpenCV SIFT (DoG keypoints, top ``num_features``, SIFT descriptors, mutual nearest
    neighbours passing Lowe's ``ratio``): ``(points_a K x 2, points_b K x 2)`` float64.

    ``image_a``, ``image_b``: ``H x W x 3`` RGB or ``H x W`` uint8 arrays.
    """
    pts, descs = [], []
    for img in (image_a, image_b):
        gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
        kps, desc = cv2.SIFT_create(nfeatures=num_features).detectAndCompute(np.ascontiguousarray(gray), None)
        pts.append(np.array([k.pt for k in kps], np.float64).reshape(-1, 2))
        descs.append(np.zeros((0, 128), np.float32) if desc is None else desc)
    m = ratio_mutual_matches(descs[0], descs[1], ratio)
    return pts[0][m[:, 0]], pts[1][m[:, 1]]


def ratio_mutual_matches(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float = 0.8) -> np.ndarray:
    """Mutual nearest neighbours (L2) that pass Lowe's ratio test, with OpenCV's brute-force matcher.
    ``desc_a``: ``N x D``, ``desc_b``: ``M x D`` float32; returns ``K x 2`` int64 indices (A, B)."""
    if len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros((0, 2), np.int64)
    bf = cv2.BFMatcher(cv2.NORM_L2)
    fwd = bf.knnMatch(desc_a, desc_b, k=2)
    back = {m.queryIdx: m.trainIdx for m in bf.match(desc_b, desc_a)}
    out = [(m.queryIdx, m.trainIdx) for m, n in (p for p in fwd if len(p) == 2)
           if m.distance < ratio * n.distance and back.get(m.trainIdx) == m.queryIdx]
    return np.array(out, np.int64).reshape(-1, 2)


# ---------------------------------------------------------------- homography accuracy

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
