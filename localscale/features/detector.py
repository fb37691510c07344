"""Single-scale keypoint detector (no learned weights).

Determinant-of-Hessian blob response at one scale (``sigma``), 3x3-neighbourhood
non-maximum suppression over a ``(2 * nms_radius + 1)`` window, a border margin, and the
top-``K`` responses. Positions are refined to sub-pixel accuracy by fitting a parabola to
the response along x and y.

Coordinates follow :mod:`localscale.geometry`: ``(x, y)`` with pixel centres at integers.

Example::

    kps, resp = detect_keypoints(rgb_uint8, num_features=1000)   # N x 2 float32, N
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from kornia.feature import hessian_response
from kornia.filters import gaussian_blur2d

from ..errors import ImageError
from ..io import load_image


def image_to_gray_tensor(image, name: str = "image") -> torch.Tensor:
    """Any supported image to a ``1 x 1 x H x W`` float32 gray tensor in ``[0, 1]``.

    Accepts an ``H x W x 3`` uint8 array or a path (via :func:`localscale.io.load_image`),
    a ``1 x H x W`` / ``H x W`` / ``1 x 1 x H x W`` float tensor in ``[0, 1]``, or a
    ``3 x H x W`` float tensor (converted to gray).
    """
    if isinstance(image, torch.Tensor):
        t = image.detach().float().cpu()
        if t.dim() == 4 and t.shape[0] == 1:
            t = t[0]
        if t.dim() == 2:
            t = t[None]
        if t.dim() != 3 or t.shape[0] not in (1, 3):
            raise ImageError(f"{name}: expected a 1 x H x W (or 3 x H x W) tensor, got shape {tuple(image.shape)}")
        if not torch.isfinite(t).all():
            raise ImageError(f"{name}: tensor contains NaN or inf")
        if t.shape[-1] < 16 or t.shape[-2] < 16:
            raise ImageError(f"{name}: image is {t.shape[-1]}x{t.shape[-2]}, smaller than the minimum 16x16")
        if t.shape[0] == 3:
            t = (0.299 * t[0] + 0.587 * t[1] + 0.114 * t[2])[None]
        return t[None].contiguous()
    rgb = load_image(image, name).astype(np.float32) / 255.0
    gray = rgb @ np.array([0.299, 0.587, 0.114], np.float32)
    return torch.from_numpy(np.ascontiguousarray(gray))[None, None]


def hessian_blob_response(gray: torch.Tensor, sigma: float = 2.0) -> torch.Tensor:
    """Scale-normalised det-of-Hessian response at one scale.

    Args:
        gray: ``B x 1 x H x W`` in ``[0, 1]``.
    Returns:
        ``B x 1 x H x W`` response, positive on bright and dark blobs.
    """
    k = 2 * int(round(3 * sigma)) + 1
    blurred = gaussian_blur2d(gray, (k, k), (sigma, sigma))
    # sobel second derivatives carry a factor 8 each; sigma**4 normalises the scale
    return hessian_response(blurred, grads_mode="sobel") * (sigma ** 4)


def nms_topk(response: torch.Tensor, num_features: int, nms_radius: int = 3, border: int = 8,
             threshold: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Local maxima of a ``1 x 1 x H x W`` response, strongest ``num_features`` first.

    Returns ``(xy N x 2 float32 with sub-pixel refinement, responses N)``.
    """
    r = response[0, 0]
    h, w = r.shape
    mx = F.max_pool2d(response, 2 * nms_radius + 1, stride=1, padding=nms_radius)[0, 0]
    keep = (r == mx) & (r > threshold)
    if border > 0:
        keep[:border] = False
        keep[-border:] = False
        keep[:, :border] = False
        keep[:, -border:] = False
    ys, xs = torch.nonzero(keep, as_tuple=True)
    vals = r[ys, xs]
    order = torch.argsort(vals, descending=True)[:num_features]
    ys, xs, vals = ys[order], xs[order], vals[order]
    # parabola fit per axis (neighbours exist because border >= 1 or clamped)
    def _offset(c, m, p):
        den = m - 2 * c + p
        off = torch.where(den.abs() > 1e-12, 0.5 * (m - p) / den, torch.zeros_like(den))
        return off.clamp(-0.5, 0.5)
    xm, xp = (xs - 1).clamp(0, w - 1), (xs + 1).clamp(0, w - 1)
    ym, yp = (ys - 1).clamp(0, h - 1), (ys + 1).clamp(0, h - 1)
    dx = _offset(vals, r[ys, xm], r[ys, xp])
    dy = _offset(vals, r[ym, xs], r[yp, xs])
    xy = torch.stack([xs.float() + dx, ys.float() + dy], -1)
    return xy.float(), vals.float()


class HessianDetector(nn.Module):
    """Single-scale det-of-Hessian detector with NMS and top-K.

    Args:
        num_features: maximum number of keypoints K.
        sigma: detection scale in pixels.
        nms_radius: suppression window is ``2 * nms_radius + 1`` pixels.
        border: keypoints closer than this to the image border are dropped.

    Shape:
        input ``1 x 1 x H x W`` gray in [0, 1]; output ``(N x 2, N)`` with ``N <= K``.
    """

    def __init__(self, num_features: int = 1000, sigma: float = 2.0, nms_radius: int = 3, border: int = 8):
        super().__init__()
        if num_features < 1:
            raise ValueError(f"num_features must be >= 1, got {num_features}")
        self.num_features, self.sigma, self.nms_radius, self.border = num_features, sigma, nms_radius, border

    @torch.no_grad()
    def forward(self, gray: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        resp = hessian_blob_response(gray, self.sigma)
        border = min(self.border, max(0, min(gray.shape[-2:]) // 2 - 1))
        return nms_topk(resp, self.num_features, self.nms_radius, border, threshold=1e-8)


def detect_keypoints(image, num_features: int = 1000, sigma: float = 2.0, nms_radius: int = 3,
                     border: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Detect up to ``num_features`` keypoints in one image.

    Args:
        image: ``H x W x 3`` uint8 array, path, or ``1 x H x W`` float tensor in [0, 1].

    Returns:
        ``(keypoints, responses)``: ``N x 2`` float32 ``(x, y)`` and ``N`` float32, strongest first.
    """
    gray = image_to_gray_tensor(image)
    xy, vals = HessianDetector(num_features, sigma, nms_radius, border)(gray)
    return xy.numpy().astype(np.float32), vals.numpy().astype(np.float32)
