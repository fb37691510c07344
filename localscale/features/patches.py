"""Patch-size correction from scale maps, LAFs and patch extraction.

Convention
----------
Each image of a pair gets the scale map of *its own* direction: for image A,
``scale_map = S_{A->B}`` sampled on A's pixels (``H_A x W_A``), for image B,
``S_{B->A}`` on B's pixels. It may also be a float (one global scale for the whole
image) or ``None`` (no correction, i.e. ``S = 1``). ``S > 1`` means content looks bigger
in the *other* image.

The patch radius at keypoint ``x`` is::

    r(x) = base_radius * max(1, 1 / S(x))

with ``S(x)`` the bilinear sample of the map at ``x``. ``S < 1`` means the other image
shows this content *smaller*, i.e. this image shows it *bigger* (it is the zoomed-in
view there), so this image's patch is enlarged by ``1/S``: it then covers the same
physical region as the other image's base-radius patch. The other image (whose map
there is ``1/S > 1``) keeps ``base_radius``. Only enlarging, never shrinking, keeps the
smaller view's patch at the detector's native support. Example: B = A zoomed x3
(``S_{A->B} = 3``, ``S_{B->A} = 1/3``): A's patches keep ``r0``, B's get ``3 r0``.

Sanity limits: ``S`` is clamped to the bin range ``[0.125, 8]`` of the scale
networks (non-finite values, e.g. beyond a homography's horizon, count as ``1``),
so ``base_radius <= r <= 8 * base_radius``; additionally ``r <= max(H, W) / 2``
when the image shape is given (a patch never exceeds the image).

Optional gating (see :func:`gate_scale`): values with ``|log2 S| < deadzone`` are set
to 1, and, when a confidence map is given, so are values whose confidence is below
``min_confidence``.

Orientation: ``"upright"`` (default) or ``"gradient"`` (training-free dominant gradient,
:class:`kornia.feature.PatchDominantGradientOrientation` via ``LAFOrienter``). Upright
is the default because it matched better on our evaluation (rotations in HPatches-style
data are small; see ``eval/matching_accuracy.py``).

LAFs follow kornia: ``1 x N x 2 x 3`` with ``A = r * R(angle)``; the patch covers
``c + A [-1, 1]^2``, so the patch side is ``2 r`` pixels, resampled to ``32 x 32``
(from the appropriate pyramid level, i.e. anti-aliased).
"""

from __future__ import annotations

from typing import Optional, Union

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from kornia.feature import LAFOrienter, extract_patches_from_pyramid, laf_from_center_scale_ori

from ..core.errors import LocalScaleError

MIN_SCALE = 0.125
MAX_SCALE = 8.0
ScaleMapLike = Union[None, float, int, np.ndarray, torch.Tensor]


def _as_points(keypoints) -> torch.Tensor:
    kp = torch.as_tensor(
        np.asarray(keypoints, dtype=np.float32) if not isinstance(keypoints, torch.Tensor) else keypoints
    ).float()
    if kp.dim() != 2 or kp.shape[1] != 2:
        raise LocalScaleError(f"keypoints must be N x 2 (x, y), got shape {tuple(kp.shape)}")
    return kp


def sample_scale_map(scale_map: ScaleMapLike, keypoints, image_shape: Optional[tuple[int, int]] = None) -> torch.Tensor:
    """Bilinear sample of a scale map at keypoints.

    Args:
        scale_map: ``H x W`` map (numpy or torch), float, or ``None`` (-> 1).
        keypoints: ``N x 2`` ``(x, y)`` pixel coordinates of this image.
        image_shape: ``(H, W)`` of the image; if the map has another size it is assumed to
            cover the same image (coordinates rescaled). Defaults to the map's size.

    Returns:
        ``N`` float32 scales (non-finite samples become 1, not yet clamped).
    """
    kp = _as_points(keypoints)
    n = kp.shape[0]
    if scale_map is None:
        return torch.ones(n)
    if isinstance(scale_map, (float, int, np.floating, np.integer)):
        s = float(scale_map)
        if not np.isfinite(s) or s <= 0:
            raise LocalScaleError(f"global scale must be finite and > 0, got {s}")
        return torch.full((n,), s)
    m = torch.as_tensor(
        np.asarray(scale_map, dtype=np.float32) if not isinstance(scale_map, torch.Tensor) else scale_map
    ).float()
    if m.dim() == 3 and m.shape[0] == 1:
        m = m[0]
    if m.dim() != 2:
        raise LocalScaleError(f"scale_map must be an H x W array, a float or None, got shape {tuple(m.shape)}")
    if n == 0:
        return torch.ones(0)
    mh, mw = m.shape
    ih, iw = image_shape if image_shape is not None else (mh, mw)
    finite = torch.isfinite(m) & (m > 0)
    logm = torch.where(finite, torch.log(m.clamp_min(1e-12)), torch.zeros_like(m))
    # pixel centre x of the image -> normalised coordinate (align_corners=False)
    gx = (2 * (kp[:, 0] + 0.5) / iw) - 1
    gy = (2 * (kp[:, 1] + 0.5) / ih) - 1
    grid = torch.stack([gx, gy], -1)[None, None]
    v = F.grid_sample(logm[None, None], grid, mode="bilinear", padding_mode="border", align_corners=False)
    return torch.exp(v[0, 0, 0])


def gate_scale(
    scale: torch.Tensor,
    deadzone_log2: float = 0.0,
    confidence: Optional[torch.Tensor] = None,
    min_confidence: float = 0.0,
) -> torch.Tensor:
    """Set scales to 1 where ``|log2 S| < deadzone_log2`` or ``confidence < min_confidence``."""
    s = scale.clone()
    if deadzone_log2 > 0:
        s[torch.log2(s).abs() < deadzone_log2] = 1.0
    if confidence is not None and min_confidence > 0:
        s[torch.as_tensor(confidence).float() < min_confidence] = 1.0
    return s


def patch_radii(
    keypoints,
    scale_map: ScaleMapLike = None,
    base_radius: float = 16.0,
    image_shape: Optional[tuple[int, int]] = None,
    deadzone_log2: float = 0.0,
) -> torch.Tensor:
    """Corrected patch radius per keypoint: ``base_radius * max(1, 1 / clamp(S, 0.125, 8))``.

    Args:
        keypoints: ``N x 2``.
        scale_map: ``S_{this->other}`` (``H x W``), float, or ``None``.
        image_shape: ``(H, W)``; also caps the radius at ``max(H, W) / 2``.
        deadzone_log2: gating, see :func:`gate_scale`.

    Returns:
        ``N`` float32 radii in pixels.
    """
    if base_radius <= 0:
        raise LocalScaleError(f"base_radius must be > 0, got {base_radius}")
    s = sample_scale_map(scale_map, keypoints, image_shape)
    s = torch.where(torch.isfinite(s), s, torch.ones_like(s)).clamp(MIN_SCALE, MAX_SCALE)
    s = gate_scale(s, deadzone_log2)
    r = base_radius * torch.clamp(1.0 / s, min=1.0)
    if image_shape is not None:
        r = r.clamp(max=max(base_radius, max(image_shape) / 2.0))
    return r.float()


def make_lafs(keypoints, radii: torch.Tensor, angles_deg: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Isotropic LAFs ``1 x N x 2 x 3`` from centres ``N x 2``, radii ``N`` and angles ``N`` (degrees)."""
    kp = _as_points(keypoints)
    r = torch.as_tensor(radii).float().reshape(-1)
    if r.shape[0] != kp.shape[0]:
        raise LocalScaleError(f"{kp.shape[0]} keypoints but {r.shape[0]} radii")
    ang = torch.zeros_like(r) if angles_deg is None else torch.as_tensor(angles_deg).float().reshape(-1)
    return laf_from_center_scale_ori(kp[None], r[None, :, None, None], ang[None, :, None])


def extract_patches(gray: torch.Tensor, lafs: torch.Tensor, patch_size: int = 32) -> torch.Tensor:
    """Cut patches: ``gray`` ``1 x 1 x H x W``, ``lafs`` ``1 x N x 2 x 3`` -> ``N x 1 x PS x PS``."""
    if gray.dim() != 4 or gray.shape[:2] != (1, 1):
        raise LocalScaleError(f"gray image must be 1 x 1 x H x W, got {tuple(gray.shape)}")
    if lafs.shape[1] == 0:
        return torch.zeros(0, 1, patch_size, patch_size)
    return extract_patches_from_pyramid(gray, lafs.to(gray.dtype), PS=patch_size)[0]


class ScaleCorrectedPatches(nn.Module):
    """Keypoints + scale map -> scale-corrected (optionally oriented) patches.

    Args:
        base_radius: radius in pixels where no enlargement is needed (patch side = 2 r).
        patch_size: output patch side (32 for HardNet/SIFT here).
        orientation: ``"upright"`` or ``"gradient"``.
        deadzone_log2: gating of the correction (0 = off).

    Shape:
        ``forward(gray 1x1xHxW, keypoints Nx2, scale_map)`` ->
        ``(patches N x 1 x PS x PS, lafs 1 x N x 2 x 3, radii N)``.
    """

    def __init__(
        self, base_radius: float = 16.0, patch_size: int = 32, orientation: str = "upright", deadzone_log2: float = 0.0
    ):
        super().__init__()
        if orientation not in ("upright", "gradient"):
            raise LocalScaleError(f"orientation must be 'upright' or 'gradient', got {orientation!r}")
        self.base_radius, self.patch_size, self.orientation = base_radius, patch_size, orientation
        self.deadzone_log2 = deadzone_log2
        self.orienter = LAFOrienter(patch_size) if orientation == "gradient" else None

    @torch.no_grad()
    def forward(self, gray: torch.Tensor, keypoints, scale_map: ScaleMapLike = None):
        shape = tuple(gray.shape[-2:])
        radii = patch_radii(keypoints, scale_map, self.base_radius, shape, self.deadzone_log2)
        patches, lafs = self.patches_from_radii(gray, keypoints, radii)
        return patches, lafs, radii

    @torch.no_grad()
    def patches_from_radii(self, gray: torch.Tensor, keypoints, radii: torch.Tensor):
        """``(patches N x 1 x PS x PS, lafs 1 x N x 2 x 3)`` for given radii (e.g. of :func:`patch_radii`).

        A keypoint's patch depends only on the image, its centre and its radius (not on the
        other keypoints), so patches of a subset of keypoints equal the same rows of the full set."""
        lafs = make_lafs(keypoints, radii)
        if self.orienter is not None and lafs.shape[1] > 0:
            lafs = self.orienter(lafs, gray)
        return extract_patches(gray, lafs, self.patch_size), lafs
