"""Geometric verification of a match set.

* :func:`verify_matches`: a robust homography (OpenCV ``USAC_MAGSAC``) of the matched points,
  and optionally, when no homography explains them, a fundamental matrix (``USAC_MAGSAC``)
  whose inliers are kept only where a local affine fit of their neighbouring inliers agrees
  (non-planar scenes). The ``verified`` decision checks the inlier count, the inlier ratio, the
  spread of the inliers over image A (convex-hull area share), the sanity of the geometry's
  scale and its agreement with the network's scale map at the inliers (``log2``). Every
  threshold is a field of :class:`VerificationConfig`; every failed check is a reason.
Conventions: points are ``(x, y)`` pixels (origin at the centre of the top-left pixel); scale
maps are ``S_{this->other}`` per pixel of their image (> 1: content bigger in the other image).

Example::

    v = verify_matches(pts_a, pts_b, a.shape[:2], b.shape[:2], scale_map=net_a)
    v.verified, v.model, v.H, v.num_inliers, v.reasons
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import cv2
import numpy as np

from ..core.errors import LocalScaleError
from ..geometry import homography_scale_at, orient_homography
from ..geometry.two_view import TwoViewConfig, TwoViewGeometry, estimate_two_view_geometry

#: what :attr:`VerificationConfig.model` can name
VERIFICATION_MODELS = ("homography", "fundamental", "auto", "two_view")


@dataclass
class VerificationConfig:
    """Thresholds of :func:`verify_matches` and :func:`refine_scale_map`.

    Estimation:
        model: ``"homography"`` (planar scenes), ``"fundamental"`` (non-planar), ``"auto"``
            (both; the fundamental matrix when it is verified and has ``auto_fundamental_gain`` times
            the homography's inliers or the homography is not verified, else the homography), or
            ``"two_view"``: the model chosen per pair as COLMAP's two-view geometry chooses it
            (homography for planes and pure rotation, fundamental matrix otherwise, essential
            matrix when both cameras are known; :func:`~localscale.geometry.two_view.estimate_two_view_geometry`
            with the thresholds of ``two_view``), with the relative pose when both cameras are known.
        two_view: thresholds of ``"two_view"`` (:class:`~localscale.geometry.two_view.TwoViewConfig`, COLMAP's defaults).
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
            or ``"hull"`` (the dilated inlier hull only); fundamental case: the dilated hull of the
            inliers with a local scale.
        hull_margin: dilation of the inlier hull, as a fraction of A's diagonal.
        decay: length (fraction of A's diagonal) over which the geometry's weight decays as
            ``exp(-d / (decay * diag))`` with the distance ``d`` to the support.
        interp_neighbours: inliers whose local scales are averaged (inverse distance, in log2) at
            each pixel (fundamental case).
        grid_stride: pixel stride of the interpolation grid (fundamental case), upsampled bilinearly.

    How the defaults of ``min_inliers``, ``min_inlier_ratio`` and ``support`` were chosen:
    ``docs/decisions/verification-thresholds.md``.
    """

    model: str = "homography"
    two_view: TwoViewConfig = field(default_factory=TwoViewConfig)
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
        if self.model not in VERIFICATION_MODELS:
            raise LocalScaleError(
                f"verification model must be one of {', '.join(VERIFICATION_MODELS)}, got {self.model!r}"
            )
        if not isinstance(self.two_view, TwoViewConfig):
            raise LocalScaleError(f"verification two_view must be a TwoViewConfig, got {type(self.two_view).__name__}")
        self.two_view.check()
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
        model: ``"homography"``, ``"fundamental"``, ``"essential"`` (``two_view`` with both cameras)
            or ``"none"`` (nothing could be estimated).
        H: ``3 x 3`` homography A -> B (``None`` unless ``model == "homography"``).
        F: ``3 x 3`` fundamental matrix (``x_B^T F x_A = 0``; ``None`` with a homography).
        two_view: the :class:`~localscale.geometry.two_view.TwoViewGeometry` of ``model="two_view"`` (configuration,
            relative pose ``R``, ``t`` when both cameras are known), else ``None``.
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
    two_view: Optional[TwoViewGeometry] = None

    def to_dict(self) -> dict:
        """JSON-ready summary (geometry, counts, decision; no per-match arrays)."""
        f = lambda x: None if x is None or not np.isfinite(x) else round(float(x), 6)  # noqa: E731
        return {
            "model": self.model,
            "verified": bool(self.verified),
            "reasons": list(self.reasons),
            "H": None if self.H is None else np.asarray(self.H).tolist(),
            "F": None if self.F is None else np.asarray(self.F).tolist(),
            "num_matches": int(len(self.inliers)),
            "num_inliers": int(self.num_inliers),
            "inlier_ratio": f(self.inlier_ratio),
            "coverage": f(self.coverage),
            "scale_disagreement_log2": f(self.scale_disagreement_log2),
            "shape_a": list(self.shape_a),
            "shape_b": list(self.shape_b),
            **({} if self.two_view is None else {"two_view": _two_view_summary(self.two_view)}),
        }

    def swapped(self) -> "VerificationResult":
        """The same verification seen from B (B -> A): inverse ``H``, transposed ``F``, inverse scales."""
        H = None if self.H is None else np.linalg.inv(self.H)
        F = None if self.F is None else self.F.T
        with np.errstate(divide="ignore", invalid="ignore"):
            ls = 1.0 / self.local_scales
        return VerificationResult(
            self.model,
            H,
            F,
            self.inliers,
            self.verified,
            list(self.reasons),
            self.points_b,
            self.points_a,
            ls,
            self.num_inliers,
            self.inlier_ratio,
            self.coverage,
            self.scale_disagreement_log2,
            self.shape_b,
            self.shape_a,
            None if self.two_view is None else self.two_view.swapped(),
        )


def _empty(points_a, points_b, shape_a, shape_b, reason) -> VerificationResult:
    k = len(points_a)
    return VerificationResult(
        "none",
        None,
        None,
        np.zeros(k, bool),
        False,
        [reason],
        points_a,
        points_b,
        np.full(k, np.nan),
        0,
        0.0,
        0.0,
        float("nan"),
        tuple(shape_a),
        tuple(shape_b),
    )


def estimate_homography(
    points_a: np.ndarray,
    points_b: np.ndarray,
    threshold: float = 3.0,
    confidence: float = 0.999,
    max_iters: int = 10000,
):
    """Robust homography A -> B of ``K x 2`` point sets with OpenCV ``USAC_MAGSAC``.

    Returns ``(H 3 x 3 or None, inlier mask K bool)``.
    """
    return _robust_fit(
        points_a,
        points_b,
        4,
        lambda pa, pb: cv2.findHomography(
            pa, pb, cv2.USAC_MAGSAC, threshold, maxIters=max_iters, confidence=confidence
        ),
        lambda H: abs(np.linalg.det(H)) >= 1e-12,
    )


def estimate_fundamental(
    points_a: np.ndarray,
    points_b: np.ndarray,
    threshold: float = 1.0,
    confidence: float = 0.999,
    max_iters: int = 10000,
):
    """Robust fundamental matrix (``x_B^T F x_A = 0``) with OpenCV ``USAC_MAGSAC``.

    Returns ``(F 3 x 3 or None, inlier mask K bool)``.
    """
    return _robust_fit(
        points_a,
        points_b,
        8,
        lambda pa, pb: cv2.findFundamentalMat(pa, pb, cv2.USAC_MAGSAC, threshold, confidence, max_iters),
        lambda F: F.shape == (3, 3),
    )


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


def local_affine_scales(
    points_a: np.ndarray, points_b: np.ndarray, neighbours: int = 8, threshold: float = 4.0
) -> tuple[np.ndarray, np.ndarray]:
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


def verify_matches(
    points_a: np.ndarray,
    points_b: np.ndarray,
    shape_a: tuple,
    shape_b: tuple,
    scale_map=None,
    config: VerificationConfig = VerificationConfig(),
    camera_a=None,
    camera_b=None,
    geometry: Optional[TwoViewGeometry] = None,
) -> VerificationResult:
    """Estimate the geometry of a match set and decide whether it is verified.

    Args:
        points_a, points_b: ``K x 2`` matched points in A and B (pixels).
        shape_a, shape_b: ``(height, width)`` of A and B.
        scale_map: the network's ``S_{A->B}`` (``H_A x W_A``, a float, or ``None`` to skip the
            agreement check).
        config: thresholds (:class:`VerificationConfig`).
        camera_a, camera_b: the cameras of A and B in the pixels of the points
            (:class:`~localscale.geometry.cameras.Camera` or what :func:`~localscale.geometry.cameras.as_camera`
            reads), used by ``model="two_view"`` (essential matrix and relative pose with both).
        geometry: ``model="two_view"``: the match set's geometry, already estimated (its
            ``inliers`` over these ``K`` matches, ``H`` and ``F`` in these pixels); only the decision is made.
    Returns:
        :class:`VerificationResult`.
    """
    config.check()
    pa = np.asarray(points_a, np.float64).reshape(-1, 2)
    pb = np.asarray(points_b, np.float64).reshape(-1, 2)
    shape_a, shape_b = tuple(int(v) for v in shape_a[:2]), tuple(int(v) for v in shape_b[:2])
    if len(pa) < 4:
        return _empty(pa, pb, shape_a, shape_b, f"{len(pa)} matches, at least 4 needed")
    if config.model == "two_view":
        return _verify_two_view(pa, pb, shape_a, shape_b, scale_map, config, camera_a, camera_b, geometry)
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
        reasons.append(
            f"inliers cover {result.coverage:.3f} of {'A' if config.coverage_of == 'a' else 'A or B'} "
            f"< {config.min_coverage}"
        )
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
                reasons.append(
                    f"geometry and network scales disagree by {result.scale_disagreement_log2:.2f} "
                    f"log2 > {config.max_scale_disagreement_log2}"
                )
    result.reasons = reasons
    result.verified = not reasons


def _verify_homography(pa, pb, shape_a, shape_b, scale_map, config, H=None, inl=None) -> VerificationResult:
    if H is None:
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


def _verify_two_view(pa, pb, shape_a, shape_b, scale_map, config, camera_a, camera_b, g=None) -> VerificationResult:
    """The model COLMAP's two-view geometry chooses (:func:`~localscale.geometry.two_view.estimate_two_view_geometry`),
    then the same decision as the other models: a homography's scales are its own, those of a
    fundamental or essential matrix come from the local affine fits of its inliers that are consistent."""
    if g is None:
        g = estimate_two_view_geometry(pa, pb, camera_a, camera_b, config.two_view)
    elif len(g.inliers) != len(pa):
        raise ValueError(f"the given geometry has {len(g.inliers)} inliers' mask for {len(pa)} matches")
    if g.model == "homography" and g.H is not None:
        res = _verify_homography(pa, pb, shape_a, shape_b, scale_map, config, g.H, g.inliers)
    elif g.model in ("fundamental", "essential"):
        # the model's inliers stay inliers (a 3D scene has no local affine map between sparse neighbours
        # at different depths); the scales come from the local affine fits that are consistent
        F = g.F if g.F is not None else _fundamental_from_essential(g.E, camera_a, camera_b)
        inl = np.asarray(g.inliers, bool).copy()
        idx = np.flatnonzero(inl)
        scales = np.full(len(pa), np.nan)
        s, ok = local_affine_scales(pa[idx], pb[idx], config.affine_neighbours, config.affine_threshold)
        scales[idx[ok]] = s[ok]
        res = VerificationResult(g.model, None, F, inl, False, [], pa, pb, scales, shape_a=shape_a, shape_b=shape_b)
        known = inl & np.isfinite(scales)
        _decide(res, scales[known], None if scale_map is None else sample_map(scale_map, pa[known]), config)
    else:
        res = _empty(pa, pb, shape_a, shape_b, "; ".join(g.reasons) or "no two-view geometry")
    res.two_view = g
    return res


def _fundamental_from_essential(E, camera_a, camera_b) -> np.ndarray:
    """``K_B^-T E K_A^-1``: the fundamental matrix (pixels) of an essential matrix and the cameras."""
    from ..geometry.cameras import as_camera

    Ka, Kb = as_camera(camera_a).K(), as_camera(camera_b).K()
    return np.linalg.inv(Kb).T @ E @ np.linalg.inv(Ka)


def _two_view_summary(g: TwoViewGeometry) -> dict:
    """The JSON fields of a two-view geometry that a verification record keeps (no per-match arrays)."""
    keep = (
        "configuration",
        "model",
        "R",
        "t",
        "pose_source",
        "num_inliers_H",
        "num_inliers_F",
        "num_inliers_E",
        "tri_angle",
        "reasons",
    )
    d = g.to_dict()
    return {k: d[k] for k in keep} | {"reliable": d["reliable"]}
