"""Homography geometry: analytic scale maps, random homographies, warping with fill.

Pixel coordinates follow the HPatches/Oxford convention: ``(x, y)`` with the origin at
the centre of the top-left pixel; a homography ``H_{A->B}`` maps ``[x_A, y_A, 1]`` to
``[x_B, y_B, 1]`` up to scale.

The local scale of a homography at ``x`` is ``sqrt(|det J_H(x)|)``; for a homography
this is ``sqrt(|det H| / |w(x)|^3)`` with ``w(x) = h31 x + h32 y + h33`` (invariant to
the overall scale of ``H``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np


def grid_points(height: int, width: int, stride: int = 1) -> np.ndarray:
    """Pixel-centre coordinates of a stride-``stride`` grid over an ``height x width`` image.

    Cell ``(i, j)`` covers pixels ``[j*stride, (j+1)*stride)``; its centre is
    ``j*stride + (stride-1)/2``. Returns ``(h, w, 2)`` float64 ``(x, y)`` with
    ``h = ceil(height/stride)``, ``w = ceil(width/stride)``.
    """
    h, w = math.ceil(height / stride), math.ceil(width / stride)
    xs = np.arange(w) * stride + (stride - 1) / 2.0
    ys = np.arange(h) * stride + (stride - 1) / 2.0
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx, gy], -1)


def homography_scale_at(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Local scale ``sqrt(|det J_H|)`` of ``H`` at ``points`` (``(..., 2)`` in pixels)."""
    H = np.asarray(H, dtype=np.float64)
    w = H[2, 0] * points[..., 0] + H[2, 1] * points[..., 1] + H[2, 2]
    det = np.linalg.det(H)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sqrt(np.abs(det) / np.abs(w) ** 3)


def orient_homography(H: np.ndarray, shape_a: tuple[int, int]) -> np.ndarray:
    """Fix the overall sign of ``H`` so that ``w(x) = h31 x + h32 y + h33 > 0`` at A's centre.

    A homography is defined up to scale, sign included (Oxford ``leuven`` H_1_5 and the EVD
    pairs are stored with ``w < 0``); the scale maps and co-visibility here treat ``w <= 0``
    as beyond the horizon, so every function taking an image shape orients ``H`` first.
    """
    H = np.asarray(H, np.float64)
    cy, cx = (shape_a[0] - 1) / 2, (shape_a[1] - 1) / 2
    return -H if H[2, 0] * cx + H[2, 1] * cy + H[2, 2] < 0 else H


def homography_scale_map(H: np.ndarray, height: int, width: int, stride: int = 1) -> np.ndarray:
    """Analytic scale map ``S_{A->B}(x)`` of ``H`` over image A (``height x width``).

    Returns an ``(ceil(height/stride), ceil(width/stride))`` float64 array; values > 1
    mean content is bigger in B. Points on or beyond the horizon (``w <= 0``) are ``nan``.
    """
    H = orient_homography(H, (height, width))
    pts = grid_points(height, width, stride)
    s = homography_scale_at(H, pts)
    s[pts @ H[2, :2] + H[2, 2] <= 0] = np.nan
    return s


def project(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply ``H`` to ``(..., 2)`` points; returns ``(..., 2)``."""
    H = np.asarray(H, dtype=np.float64)
    p = points @ H[:, :2].T + H[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return p[..., :2] / p[..., 2:3]


def covisible_mask(H: np.ndarray, shape_a: tuple[int, int], shape_b: tuple[int, int], stride: int = 1) -> np.ndarray:
    """Which grid points of A land inside B (in front of the camera). ``shape_*`` = ``(height, width)``."""
    H = orient_homography(H, shape_a)
    pts = grid_points(shape_a[0], shape_a[1], stride)
    w = pts @ H[2, :2] + H[2, 2]
    q = project(H, pts)
    hb, wb = shape_b
    inside = (q[..., 0] >= -0.5) & (q[..., 0] <= wb - 0.5) & (q[..., 1] >= -0.5) & (q[..., 1] <= hb - 0.5)
    return inside & (w > 0) & np.isfinite(q).all(-1)


def global_scale(H: np.ndarray, shape_a: tuple[int, int], shape_b: tuple[int, int], stride: int = 4) -> float:
    """Global scale of a pair: exp of the mean log of the analytic map over the co-visible region."""
    s = homography_scale_map(H, shape_a[0], shape_a[1], stride)
    m = covisible_mask(H, shape_a, shape_b, stride) & np.isfinite(s)
    if not m.any():
        raise ValueError("global_scale: the homography leaves no co-visible region")
    return float(np.exp(np.log(s[m]).mean()))


@dataclass
class HomographyConfig:
    """Ranges of the random homography sampler (the paper's, plus perspective)."""

    scale_range: tuple[float, float] = (0.16, 6.0)
    rotation_deg: float = 30.0
    skew: float = 0.2
    #: max |(p1, p2)| of the perspective row, in coordinates normalised by the half-size of A
    perspective: float = 0.45
    #: max shift of A's centre in B, as a fraction of B's size
    translation: float = 0.2


def translation(dx: float, dy: float) -> np.ndarray:
    """3x3 homography of a pure shift by ``(dx, dy)`` pixels."""
    return np.array([[1.0, 0, dx], [0, 1, dy], [0, 0, 1]])


def central_crop(image: np.ndarray, fraction: float) -> tuple[np.ndarray, tuple[int, int]]:
    """The central part of ``image`` with sides ``fraction`` of its own, and its offset ``(x0, y0)``.

    A homography ``H`` on the crop's pixels is ``H @ translation(-x0, -y0)`` on the image's.
    """
    if not 0 < fraction <= 1:
        raise ValueError(f"crop fraction must be in (0, 1], got {fraction}")
    ch, cw = round(image.shape[0] * fraction), round(image.shape[1] * fraction)
    y0, x0 = (image.shape[0] - ch) // 2, (image.shape[1] - cw) // 2
    return np.ascontiguousarray(image[y0 : y0 + ch, x0 : x0 + cw]), (x0, y0)


def sample_homography(
    rng: np.random.Generator,
    shape_a: tuple[int, int],
    shape_b: tuple[int, int],
    cfg: HomographyConfig = HomographyConfig(),
) -> np.ndarray:
    """Random homography A->B: log-uniform scale, rotation, skew, perspective, shift.

    Built as ``T(c_B + t) · s R K · P · T(-c_A)`` where ``P`` has last row
    ``(p1/a, p2/a, 1)`` (``a`` = half the longer side of A), so the scale at A's centre is
    ``s`` and perspective makes it vary across the image.
    """
    ha, wa = shape_a
    hb, wb = shape_b
    s = math.exp(rng.uniform(math.log(cfg.scale_range[0]), math.log(cfg.scale_range[1])))
    th = math.radians(rng.uniform(-cfg.rotation_deg, cfg.rotation_deg))
    k = rng.uniform(-cfg.skew, cfg.skew)
    m = rng.uniform(0.0, cfg.perspective)
    phi = rng.uniform(0.0, 2 * math.pi)
    half = max(ha, wa) / 2.0
    P = np.array([[1, 0, 0], [0, 1, 0], [m * math.cos(phi) / half, m * math.sin(phi) / half, 1]])
    R = np.array([[math.cos(th), -math.sin(th), 0], [math.sin(th), math.cos(th), 0], [0, 0, 1]])
    K = np.array([[1, k, 0], [0, 1, 0], [0, 0, 1]])
    S = np.diag([s, s, 1.0])
    t = rng.uniform(-cfg.translation, cfg.translation, 2) * np.array([wb, hb])
    Tb = np.array([[1, 0, (wb - 1) / 2 + t[0]], [0, 1, (hb - 1) / 2 + t[1]], [0, 0, 1]])
    Ta = np.array([[1, 0, -(wa - 1) / 2], [0, 1, -(ha - 1) / 2], [0, 0, 1]])
    H = Tb @ S @ R @ K @ P @ Ta
    return H / H[2, 2]


def perspective_spread(H: np.ndarray, shape_a: tuple[int, int], shape_b: tuple[int, int], stride: int = 8) -> float:
    """Perspective strength of a pair: std of ``log2`` of the analytic scale over the co-visible region."""
    s = homography_scale_map(H, shape_a[0], shape_a[1], stride)
    m = covisible_mask(H, shape_a, shape_b, stride) & np.isfinite(s)
    if m.sum() < 2:
        return 0.0
    return float(np.log2(s[m]).std())


def warp_image(
    image: np.ndarray,
    H: np.ndarray,
    shape_out: tuple[int, int],
    fill: np.ndarray | None = None,
    interpolation: int = cv2.INTER_LINEAR,
    antialias: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Warp ``image`` by ``H`` into an ``shape_out`` canvas; empty regions are taken from ``fill``.

    Args:
        image: ``H x W x C`` uint8 (or float) image A.
        H: homography A -> output.
        shape_out: ``(height, width)`` of the output.
        fill: image used where A does not reach (resized to ``shape_out``); zeros if ``None``.
        antialias: blur A before a zoom-out so the warp does not alias.

    Returns:
        ``(warped, valid)``: the output image and a float32 ``height x width`` coverage mask in [0, 1].
    """
    h, w = shape_out
    H = np.asarray(H, dtype=np.float64)
    if antialias:
        # Warping a zoom-out straight from the full-resolution image aliases; pre-blur by
        # the minification at A's centre so B looks like a photo taken from further away.
        centre = np.array([(image.shape[1] - 1) / 2, (image.shape[0] - 1) / 2])
        s = float(homography_scale_at(H, centre))
        if np.isfinite(s) and s < 1:
            image = cv2.GaussianBlur(image, (0, 0), 0.5 * math.sqrt(1 / s**2 - 1))
    warped = cv2.warpPerspective(image, H, (w, h), flags=interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    ones = np.ones(image.shape[:2], np.float32)
    valid = cv2.warpPerspective(ones, H, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if fill is not None:
        f = cv2.resize(fill, (w, h), interpolation=cv2.INTER_AREA)
        if f.ndim == 2 and warped.ndim == 3:
            f = np.repeat(f[..., None], warped.shape[2], 2)
        elif f.ndim == 3 and warped.ndim == 2:
            f = f.mean(2).astype(f.dtype)
        v = valid[..., None] if warped.ndim == 3 else valid
        warped = warped.astype(np.float32) * v + f.astype(np.float32) * (1 - v)
        warped = (
            warped.round().clip(0, 255).astype(image.dtype) if image.dtype == np.uint8 else warped.astype(image.dtype)
        )
    return warped, valid


def turn_matrix(turn: int, shape: tuple) -> np.ndarray:
    """``3 x 3`` map from pixel coordinates of an image of ``shape`` ``(H, W)`` to those of
    ``np.rot90(image, turn)`` (counter-clockwise quarter turns)."""
    h, w = shape[:2]
    k = turn % 4
    if k == 0:
        return np.eye(3)
    if k == 1:
        return np.array([[0.0, 1, 0], [-1, 0, w - 1], [0, 0, 1]])
    if k == 2:
        return np.array([[-1.0, 0, w - 1], [0, -1, h - 1], [0, 0, 1]])
    return np.array([[0.0, -1, h - 1], [1, 0, 0], [0, 0, 1]])


def homography_rotation(H: np.ndarray, shape_a: tuple[int, int]) -> float:
    """In-plane rotation (degrees, -180..180) of ``H`` at the centre of image A
    (:func:`homography_rotation_at`)."""
    h, w = shape_a
    return homography_rotation_at(H, ((w - 1) / 2, (h - 1) / 2))


def homography_rotation_at(H: np.ndarray, point) -> float:
    """In-plane rotation (degrees, -180..180) of ``H`` at ``point`` ``(x, y)`` of A: the angle of the
    similarity closest to its Jacobian there (positive: counter-clockwise in the image frame)."""
    c = np.array([[float(point[0]), float(point[1])]])
    e = 1.0
    p0, px, py = project(H, c)[0], project(H, c + [[e, 0]])[0], project(H, c + [[0, e]])[0]
    J = np.stack([(px - p0) / e, (py - p0) / e], axis=1)  # columns: d/dx, d/dy
    return float(np.degrees(np.arctan2(J[1, 0] - J[0, 1], J[0, 0] + J[1, 1])))
