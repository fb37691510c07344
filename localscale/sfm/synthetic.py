"""A small multi-view scene with known cameras, rendered with NumPy and OpenCV (no data files).

Two textured rectangles meeting at a ridge (an open book seen from its spine), viewed by
cameras on an arc around the ridge: a non-planar scene, so the views need a real two-view
geometry (not one homography), and every view sees both planes. Each pixel's ray is intersected
with both planes and takes the texture of the nearest hit (:func:`render_view`), so occlusion and
perspective are exact. Used by the tests of :mod:`localscale.sfm` and as a smoke test::

    from localscale.sfm.synthetic import write_scene
    cameras = write_scene("scene/", num_views=6)      # scene/view_0.png .. view_5.png
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np


@dataclass
class SceneCamera:
    """A pinhole camera: ``x_cam = R @ x_world + t``, intrinsics ``K``, image ``(height, width)``."""

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    shape: tuple

    @property
    def center(self) -> np.ndarray:
        return -self.R.T @ self.t


def random_texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """``size x size x 3`` uint8 texture: noise at several scales plus random discs and boxes
    (corners and blobs at many sizes, so that every detector finds features)."""
    tex = np.zeros((size, size, 3), np.float32)
    for cells, weight in ((4, 0.8), (16, 0.6), (64, 0.5), (size // 2, 0.25)):
        noise = rng.random((cells, cells, 3)).astype(np.float32)
        tex += weight * cv2.resize(noise, (size, size), interpolation=cv2.INTER_CUBIC)
    tex = (tex - tex.min()) / (tex.max() - tex.min() + 1e-6) * 255
    img = tex.astype(np.uint8)
    for _ in range(120):
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        x, y = (int(v) for v in rng.integers(0, size, 2))
        r = int(rng.integers(3, size // 12))
        if rng.random() < 0.5:
            cv2.circle(img, (x, y), r, colour, -1)
        else:
            cv2.rectangle(img, (x - r, y - r), (x + r, y + int(r * rng.uniform(0.5, 1.5))), colour, -1)
    return img


def _planes(half_width: float, half_height: float, angle_deg: float):
    """Two rectangles meeting at the ridge line ``x = 0, z = 0`` (world y up the ridge), each
    turned ``angle_deg`` away from the image plane: ``(origin, u axis, v axis, u length, v length)``."""
    a = math.radians(angle_deg)
    v = np.array([0.0, 1.0, 0.0])
    left = np.array([-math.cos(a), 0.0, math.sin(a)])
    right = np.array([math.cos(a), 0.0, math.sin(a)])
    origin = np.array([0.0, -half_height, 0.0])
    return [(origin, left, v, half_width, 2 * half_height), (origin, right, v, half_width, 2 * half_height)]


def render_view(camera: SceneCamera, textures: list, planes=None) -> np.ndarray:
    """The ``H x W x 3`` uint8 RGB image ``camera`` sees of the textured planes (grey background)."""
    planes = planes or _planes(3.0, 2.5, 40.0)
    h, w = camera.shape
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pix = np.stack([xs, ys, np.ones_like(xs)], -1).reshape(-1, 3)
    rays = (pix @ np.linalg.inv(camera.K).T) @ camera.R  # world directions (R^T d, as row vectors)
    centre = camera.center
    best = np.full(len(rays), np.inf)
    out = np.full((len(rays), 3), 110, np.float32)
    for (origin, u, v, lu, lv), tex in zip(planes, textures):
        normal = np.cross(u, v)
        denom = rays @ normal
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = ((origin - centre) @ normal) / denom
        hit = centre + depth[:, None] * rays
        su, sv = (hit - origin) @ u / lu, (hit - origin) @ v / lv
        ok = np.isfinite(depth) & (depth > 0) & (su >= 0) & (su <= 1) & (sv >= 0) & (sv <= 1) & (depth < best)
        size = tex.shape[0]
        map_x = (su * (size - 1)).astype(np.float32).reshape(h, w)
        map_y = ((1 - sv) * (size - 1)).astype(np.float32).reshape(h, w)
        sampled = cv2.remap(tex, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT).reshape(-1, 3)
        out[ok] = sampled[ok]
        best[ok] = depth[ok]
    return np.clip(out, 0, 255).astype(np.uint8).reshape(h, w, 3)


def arc_cameras(
    num_views: int = 6, shape: tuple = (240, 320), focal: float = 300.0, distance: float = 6.0, spread_deg: float = 40.0
) -> list:
    """``num_views`` cameras on an arc (``spread_deg`` wide, heights alternating) around the ridge,
    each at ``distance`` and looking at the ridge's middle."""
    h, w = shape
    K = np.array([[focal, 0, (w - 1) / 2], [0, focal, (h - 1) / 2], [0, 0, 1]])
    target = np.array([0.0, 0.0, 0.0])
    cams = []
    for i in range(num_views):
        yaw = math.radians(-spread_deg / 2 + spread_deg * i / max(1, num_views - 1))
        height = 0.6 * (1 if i % 2 else -1)
        centre = target + np.array([distance * math.sin(yaw), height, -distance * math.cos(yaw)])
        z = target - centre
        z /= np.linalg.norm(z)
        x = np.cross(np.array([0.0, -1.0, 0.0]), z)  # image x to the right, image y down (world y up)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        cams.append(SceneCamera(K, R, -R @ centre, shape))
    return cams


def write_scene(folder, num_views: int = 6, shape: tuple = (240, 320), seed: int = 0, fmt: str = "png") -> list:
    """Render ``num_views`` views (:func:`arc_cameras`) into ``folder/view_<i>.<fmt>``; returns the cameras."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    textures = [random_texture(rng), random_texture(rng)]
    cams = arc_cameras(num_views, shape)
    for i, cam in enumerate(cams):
        cv2.imwrite(str(folder / f"view_{i}.{fmt}"), cv2.cvtColor(render_view(cam, textures), cv2.COLOR_RGB2BGR))
    return cams
