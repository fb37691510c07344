"""Relative pose of two calibrated views: from an essential matrix, a homography or a pure
rotation, its refinement on Sampson errors, triangulation angles, and the pose error and its AUC
(the relative-pose protocol of SuperGlue / LightGlue). Convention: ``x_B = R x_A + t``, ``|t| = 1``."""

from __future__ import annotations

from typing import List, Optional, Sequence, Tuple

import cv2
import numpy as np

from .cameras import Camera


def pose_from_essential(E, na, nb):
    """``(R, t, n_front)`` from ``E`` by ``cv2.recoverPose`` on normalised inliers (``K = I``);
    ``(None, None, 0)`` when no point passes the cheirality test."""
    if len(na) < 5:
        return None, None, 0
    try:
        n_front, R, t, _ = cv2.recoverPose(E, na, nb, np.eye(3))
    except cv2.error:
        return None, None, 0
    if n_front == 0:
        return None, None, 0
    t = t.ravel()
    return R, t / max(np.linalg.norm(t), 1e-12), int(n_front)


def _rodrigues(w):
    return cv2.Rodrigues(np.asarray(w, np.float64).reshape(3, 1))[0]


def refine_relative_pose(R, t, na, nb, threshold: float, iterations: int = 20):
    """Levenberg-Marquardt refinement of a relative pose on the Sampson errors of normalised
    matches (``N x 2`` each), with Huber weights of scale ``threshold`` (normalised units).

    ``R`` is updated as ``R exp([w]x)``, ``t`` on the unit sphere (two tangent directions).

    Returns:
        ``(R, t)``, ``|t| = 1``; the input when the cost does not decrease.
    """
    if len(na) < 6:
        return R, t

    def residuals(R_, t_):
        return np.sqrt(_sampson(skew(t_) @ R_, na, nb))

    def apply(R_, t_, p):
        R2 = R_ @ _rodrigues(p[:3])
        _, _, Vt = np.linalg.svd(t_.reshape(1, 3))
        t2 = t_ + Vt[1] * p[3] + Vt[2] * p[4]
        return R2, t2 / np.linalg.norm(t2)

    def cost(r):
        a = np.abs(r)
        return float(np.sum(np.where(a <= threshold, 0.5 * a**2, threshold * (a - 0.5 * threshold))))

    t = np.asarray(t, np.float64).ravel() / np.linalg.norm(t)
    r = residuals(R, t)
    c = cost(r)
    lam = 1e-3
    eps = 1e-7
    for _ in range(iterations):
        w = np.where(np.abs(r) <= threshold, 1.0, threshold / np.maximum(np.abs(r), 1e-30))
        J = np.empty((len(r), 5))
        for k in range(5):
            d = np.zeros(5)
            d[k] = eps
            J[:, k] = (residuals(*apply(R, t, d)) - r) / eps
        JW = J * w[:, None]
        A = JW.T @ J
        g = JW.T @ r
        improved = False
        for _ in range(8):
            try:
                step = -np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), g)
            except np.linalg.LinAlgError:
                break
            R2, t2 = apply(R, t, step)
            r2 = residuals(R2, t2)
            c2 = cost(r2)
            if c2 < c:
                R, t, r, lam = R2, t2, r2, max(lam / 10, 1e-9)
                improved = c - c2 > 1e-12 * max(c, 1e-30)
                c = c2
                break
            lam *= 10
        if not improved:
            break
    return R, t


def rotation_fit(ua, ub, cam_a: Camera, cam_b: Camera, max_error: float):
    """Best rotation between the bearings of undistorted pixels ``ua``/``ub`` (Kabsch) and the share
    of the points it maps within ``max_error`` pixels of B."""
    if len(ua) < 3:
        return np.eye(3), 0.0
    Ka, Kb = cam_a.K(), cam_b.K()
    ba = _bearings(ua, Ka)
    bb = _bearings(ub, Kb)
    U, _, Vt = np.linalg.svd(bb.T @ ba)
    D = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    proj = (Kb @ R @ np.linalg.inv(Ka) @ np.c_[ua, np.ones(len(ua))].T).T
    err = np.linalg.norm(proj[:, :2] / proj[:, 2:3] - ub, axis=1)
    return R, float(np.mean(err <= max_error))


def _bearings(pix, K):
    x = (np.linalg.inv(K) @ np.c_[pix, np.ones(len(pix))].T).T
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def pose_from_homography(H, cam_a, cam_b, na, nb, mask_H, cfg):
    """The decomposition of ``H`` (``cv2.decomposeHomographyMat`` of ``K_B^-1 H K_A``) that puts the
    most inliers in front of both cameras; ties broken by the Sampson support of its essential
    matrix over all matches (points off the plane decide between the two mirror solutions)."""
    Hn = np.linalg.inv(cam_b.K()) @ H @ cam_a.K()
    try:
        _, Rs, ts, normals = cv2.decomposeHomographyMat(Hn, np.eye(3))
    except cv2.error:
        return None
    thr = 0.5 * (
        cam_a.pixel_threshold_to_normalized(cfg.max_error) + cam_b.pixel_threshold_to_normalized(cfg.max_error)
    )
    ia, ib = na[mask_H], nb[mask_H]
    best, best_key = None, None
    for R, t in zip(Rs, ts):
        t = t.ravel()
        if np.linalg.norm(t) < 1e-12:
            continue
        tn = t / np.linalg.norm(t)
        front = _count_in_front(R, tn, ia, ib)
        support = int(np.sum(_sampson(skew(tn) @ R, na, nb) <= thr**2))
        key = (front, support)
        if best_key is None or key > best_key:
            best, best_key = (R, tn), key
    if best is None or best_key[0] == 0:
        return None
    return best


def skew(t):
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]], np.float64)


def _sampson(E, na, nb):
    """Squared Sampson errors of normalised matches under ``E`` (``x_B^T E x_A = 0``)."""
    xa = np.c_[na, np.ones(len(na))]
    xb = np.c_[nb, np.ones(len(nb))]
    Ex = xa @ E.T
    Etx = xb @ E
    num = np.sum(xb * Ex, axis=1) ** 2
    den = Ex[:, 0] ** 2 + Ex[:, 1] ** 2 + Etx[:, 0] ** 2 + Etx[:, 1] ** 2
    return num / np.maximum(den, 1e-30)


def _triangulate(R, t, na, nb):
    P1 = np.eye(3, 4)
    P2 = np.c_[R, t]
    X = cv2.triangulatePoints(P1, P2, na.T.astype(np.float64), nb.T.astype(np.float64))
    w = X[3]
    ok = np.abs(w) > 1e-12
    Xe = np.full((3, len(na)), np.nan)
    Xe[:, ok] = X[:3, ok] / w[ok]
    return Xe.T


def _count_in_front(R, t, na, nb) -> int:
    if len(na) == 0:
        return 0
    X = _triangulate(R, t, na, nb)
    za = X[:, 2]
    zb = (X @ R.T + t)[:, 2]
    return int(np.sum((za > 0) & (zb > 0)))


def median_triangulation_angle(R, t, na, nb) -> Optional[float]:
    """Median angle (degrees) between the two viewing rays of the triangulated inliers."""
    if len(na) == 0 or np.linalg.norm(t) < 1e-12:
        return None
    X = _triangulate(R, t, na, nb)
    c_b = -R.T @ t  # B's centre in A's frame
    X = X[np.all(np.isfinite(X), axis=1)]
    if len(X) == 0:
        return None
    ra = X / np.linalg.norm(X, axis=1, keepdims=True)
    rb = (X - c_b) / np.linalg.norm(X - c_b, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(np.sum(ra * rb, axis=1), -1, 1)))
    return float(np.median(ang))


# ---------------------------------------------------------------------- evaluation
def relative_pose_error(R_est, t_est, R_gt, t_gt) -> Tuple[float, float]:
    """Rotation and translation-direction errors in degrees (SuperGlue/LightGlue protocol).

    Rotation: the angle of ``R_est^T R_gt``. Translation: the angle between ``t_est`` and ``t_gt``,
    folded to ``min(e, 180 - e)`` (an essential matrix fixes the direction only up to sign).
    A missing estimate (``None``) or a zero translation gives 180 for that part.
    """
    if R_est is None:
        return 180.0, 180.0
    R_est, R_gt = np.asarray(R_est, np.float64), np.asarray(R_gt, np.float64)
    cos = (np.trace(R_est.T @ R_gt) - 1) / 2
    rot = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    if t_est is None:
        return rot, 180.0
    te, tg = np.asarray(t_est, np.float64).ravel(), np.asarray(t_gt, np.float64).ravel()
    ne, ng = np.linalg.norm(te), np.linalg.norm(tg)
    if ne < 1e-12 or ng < 1e-12:
        return rot, 180.0
    e = float(np.degrees(np.arccos(np.clip(te @ tg / (ne * ng), -1.0, 1.0))))
    return rot, min(e, 180.0 - e)


def epipolar_errors(points_a, points_b, camera_a, camera_b, R, t) -> np.ndarray:
    """Symmetric epipolar distances (``N``, normalised coordinates) of matches under a known
    relative pose ``x_B = R x_A + t`` (SuperGlue/LightGlue's match precision counts those below
    ``5e-4`` as correct). ``points_a`` / ``points_b``: ``N x 2`` pixels; the cameras undistort them
    (:meth:`localscale.geometry.cameras.Camera.normalize`)."""
    if len(points_a) != len(points_b):
        raise ValueError(f"points_a and points_b differ in length: {len(points_a)} and {len(points_b)}")
    if len(points_a) == 0:
        return np.zeros(0)
    xa = np.c_[camera_a.normalize(points_a), np.ones(len(points_a))]
    xb = np.c_[camera_b.normalize(points_b), np.ones(len(points_b))]
    E = skew(np.asarray(t, np.float64).ravel()) @ np.asarray(R, np.float64)
    Ex, Etx = xa @ E.T, xb @ E
    residual = np.sum(xb * Ex, axis=1) ** 2
    inverse = 1 / np.maximum(Ex[:, 0] ** 2 + Ex[:, 1] ** 2, 1e-30) + 1 / np.maximum(
        Etx[:, 0] ** 2 + Etx[:, 1] ** 2, 1e-30
    )
    return np.sqrt(residual * inverse)


def pose_auc(errors: Sequence[float], thresholds: Sequence[float] = (5, 10, 20)) -> List[float]:
    """Area under the recall-vs-error curve up to each threshold, normalised to [0, 1]
    (SuperGlue/LightGlue ``pose_auc``): errors are ``max(rot, trans)`` degrees per pair,
    failures counted as 180 (or inf)."""
    err = np.sort(np.asarray(errors, np.float64).ravel())
    if err.size == 0:
        return [0.0 for _ in thresholds]
    err = np.where(np.isnan(err), np.inf, err)
    recall = np.arange(1, len(err) + 1) / len(err)
    err = np.r_[0.0, err]
    recall = np.r_[0.0, recall]
    out = []
    for thr in thresholds:
        last = int(np.searchsorted(err, thr))
        e = np.r_[err[:last], thr]
        r = np.r_[recall[:last], recall[last - 1]]
        out.append(float(np.trapezoid(r, x=e) / thr) if hasattr(np, "trapezoid") else float(np.trapz(r, x=e) / thr))
    return out
