"""Single-scale keypoint detectors (no learned weights).

The default, ``hessian``: determinant-of-Hessian blob response at one scale (``sigma``),
non-maximum suppression over a ``(2 * nms_radius + 1)`` window, a border margin, and the
top-``K`` responses. Positions are refined to sub-pixel accuracy by fitting a parabola to
the response along x and y.

:data:`DETECTORS` names the detectors that :func:`get_detector` / :func:`detect` can swap in
(all single-scale: the scale maps supply the scale change, so the detector must not adapt its
sizes to the zoom; the patch size of every keypoint comes from the base radius and the maps):

* ``hessian``: the detector above (sigma 2).
* ``harris``, ``gftt``, ``dog``: kornia responses (:func:`kornia.feature.harris_response`,
  :func:`~kornia.feature.gftt_response` on the image blurred with sigma 2,
  :func:`~kornia.feature.dog_response_single` with sigmas 1.6 and 1.6 x 2^(1/3)), each with the
  same NMS, border and sub-pixel refinement as ``hessian``.
* ``sift``: OpenCV SIFT keeping only the keypoints of its octave at the image's own
  resolution (OpenCV's octave 0; the up-sampled octave -1 and the coarser ones are dropped),
  i.e. blobs of sigma 1.6 to 3.2 px, with a low contrast threshold (0.01) so that a top-``K``
  can be taken; keypoints repeated with several orientations count once. One octave of a
  photo often has fewer than ``K`` keypoints.
* ``orb``: OpenCV ORB with one pyramid level (``nlevels=1``, FAST + Harris score).
* ``akaze``: OpenCV AKAZE with one octave (``nOctaves=1``, its finest) and a low threshold
  (1e-4) so that a top-``K`` can be taken; needs ``cv2.AKAZE_create`` (OpenCV 4.x; OpenCV 5
  moved AKAZE to opencv-contrib).

Every detector returns its ``K`` strongest keypoints by its own response, strongest first.
Coordinates follow :mod:`localscale.geometry`: ``(x, y)`` with pixel centres at integers
(OpenCV's keypoint convention too).

Example::

    kps, resp = detect_keypoints(rgb_uint8, num_features=1000)   # N x 2 float32, N
    kps, resp = detect(rgb_uint8, "orb", num_features=1000)      # same, with OpenCV ORB
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from kornia.feature import hessian_response
from kornia.filters import gaussian_blur2d

from ..core.errors import ImageError, LocalScaleError
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
    return hessian_response(blurred, grads_mode="sobel") * (sigma**4)


def local_max(r: torch.Tensor, radius: int) -> torch.Tensor:
    """Maximum over the ``(2 radius + 1)^2`` window of each pixel of an ``H x W`` map (outside
    the map counts as -inf): OpenCV's dilation on CPU, two 1-D max-pools elsewhere (the same
    values; a square max-pool is ~100x slower than ``cv2.dilate`` on CPU)."""
    k = 2 * radius + 1
    if r.device.type == "cpu" and r.dtype == torch.float32:
        out = cv2.dilate(
            np.ascontiguousarray(r.detach().numpy()),
            np.ones((k, k), np.uint8),
            borderType=cv2.BORDER_CONSTANT,
            borderValue=-np.inf,
        )
        return torch.from_numpy(out)
    x = F.max_pool2d(r[None, None], (1, k), stride=1, padding=(0, radius))
    return F.max_pool2d(x, (k, 1), stride=1, padding=(radius, 0))[0, 0]


def nms_topk(
    response: torch.Tensor, num_features: int, nms_radius: int = 3, border: int = 8, threshold: float = 0.0
) -> tuple[torch.Tensor, torch.Tensor]:
    """Local maxima of a ``1 x 1 x H x W`` response, strongest ``num_features`` first.

    Returns ``(xy N x 2 float32 with sub-pixel refinement, responses N)``.
    """
    r = response[0, 0]
    h, w = r.shape
    mx = local_max(r, nms_radius)
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


def detect_keypoints(
    image, num_features: int = 1000, sigma: float = 2.0, nms_radius: int = 3, border: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    """Detect up to ``num_features`` keypoints in one image.

    Args:
        image: ``H x W x 3`` uint8 array, path, or ``1 x H x W`` float tensor in [0, 1].

    Returns:
        ``(keypoints, responses)``: ``N x 2`` float32 ``(x, y)`` and ``N`` float32, strongest first.
    """
    gray = image_to_gray_tensor(image)
    xy, vals = HessianDetector(num_features, sigma, nms_radius, border)(gray)
    return xy.numpy().astype(np.float32), vals.numpy().astype(np.float32)


# ---------------------------------------------------------------- detector registry

DETECTORS = ("hessian", "harris", "gftt", "dog", "sift", "orb", "akaze")


def _border(gray: torch.Tensor, border: int) -> int:
    return min(border, max(0, min(gray.shape[-2:]) // 2 - 1))


class ResponseDetector(nn.Module):
    """Single-scale detector from a kornia corner / blob response, with NMS and top-K.

    Args:
        response: ``"harris"``, ``"gftt"`` or ``"dog"``.
        num_features: maximum number of keypoints K.
        sigma: Gaussian blur (``harris``, ``gftt``) or the smaller DoG sigma (``dog``), pixels.
        nms_radius, border: as :class:`HessianDetector`.

    Shape:
        input ``1 x 1 x H x W`` gray in [0, 1]; output ``(N x 2, N)`` with ``N <= K``.
    """

    def __init__(
        self, response: str, num_features: int = 1000, sigma: float = 2.0, nms_radius: int = 3, border: int = 8
    ):
        super().__init__()
        if response not in ("harris", "gftt", "dog"):
            raise LocalScaleError(f"unknown response {response!r}; choose from harris, gftt, dog")
        if num_features < 1:
            raise ValueError(f"num_features must be >= 1, got {num_features}")
        self.response, self.num_features, self.sigma = response, num_features, sigma
        self.nms_radius, self.border = nms_radius, border

    def response_map(self, gray: torch.Tensor) -> torch.Tensor:
        from kornia.feature import dog_response_single, gftt_response, harris_response

        if self.response == "dog":
            # |DoG|: bright and dark blobs; sigma**2 / (k - 1) normalises it like the Laplacian
            k = 2 ** (1 / 3)
            return dog_response_single(gray, self.sigma, self.sigma * k).abs() / (k - 1)
        ks = 2 * int(round(3 * self.sigma)) + 1
        blurred = gaussian_blur2d(gray, (ks, ks), (self.sigma, self.sigma))
        return harris_response(blurred) if self.response == "harris" else gftt_response(blurred)

    @torch.no_grad()
    def forward(self, gray: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        resp = self.response_map(gray)
        return nms_topk(resp, self.num_features, self.nms_radius, _border(gray, self.border), threshold=1e-12)


class OpenCVDetector(nn.Module):
    """An OpenCV detector restricted to one scale (``sift``, ``orb``, ``akaze``; module docstring).

    Args:
        name: ``"sift"``, ``"orb"`` or ``"akaze"``.
        num_features: maximum number of keypoints K (the strongest by OpenCV's ``response``).

    Shape:
        input ``1 x 1 x H x W`` gray in [0, 1] (quantised to uint8 for OpenCV);
        output ``(N x 2, N)`` float32 with ``N <= K``.
    """

    def __init__(self, name: str, num_features: int = 1000):
        super().__init__()
        if name not in ("sift", "orb", "akaze"):
            raise LocalScaleError(f"unknown OpenCV detector {name!r}; choose from sift, orb, akaze")
        if num_features < 1:
            raise ValueError(f"num_features must be >= 1, got {num_features}")
        if name == "akaze" and not hasattr(cv2, "AKAZE_create"):
            raise LocalScaleError(
                f"detector 'akaze' needs cv2.AKAZE_create, which OpenCV {cv2.__version__} lacks "
                "(it is in OpenCV 4.x and in opencv-contrib)"
            )
        self.name, self.num_features = name, num_features

    def keypoints(self, gray_u8: np.ndarray) -> list:
        """The ``cv2.KeyPoint`` list kept for an ``H x W`` uint8 image, strongest first."""
        if self.name == "orb":
            kps = cv2.ORB_create(self.num_features, nlevels=1, edgeThreshold=16).detect(gray_u8, None)
        elif self.name == "akaze":
            kps = cv2.AKAZE_create(threshold=1e-4, nOctaves=1).detect(gray_u8, None)
        else:
            kps = cv2.SIFT_create(contrastThreshold=0.01).detect(gray_u8, None)
            octave = [(k.octave & 255) - 256 * ((k.octave & 255) >= 128) for k in kps]  # -1 .. n
            seen, one = set(), []
            for k, o in zip(kps, octave):
                if o == 0 and k.pt not in seen:
                    seen.add(k.pt)
                    one.append(k)
            kps = one
        return sorted(kps, key=lambda k: -k.response)[: self.num_features]

    @torch.no_grad()
    def forward(self, gray: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        u8 = (gray[0, 0].detach().cpu().float() * 255).round().clamp(0, 255).to(torch.uint8).numpy()
        kps = self.keypoints(np.ascontiguousarray(u8))
        xy = torch.tensor([k.pt for k in kps], dtype=torch.float32).reshape(-1, 2)
        resp = torch.tensor([k.response for k in kps], dtype=torch.float32)
        return xy, resp


def get_detector(name: str = "hessian", num_features: int = 1000) -> nn.Module:
    """The single-scale detector called ``name`` (one of :data:`DETECTORS`).

    Args:
        name: ``"hessian"`` (default), ``"harris"``, ``"gftt"``, ``"dog"``, ``"sift"``, ``"orb"``, ``"akaze"``.
        num_features: maximum number of keypoints K.

    Returns:
        a module mapping a ``1 x 1 x H x W`` gray tensor in ``[0, 1]`` to ``(xy, responses)``:
        ``N x 2`` float32 ``(x, y)`` and ``N`` float32, strongest first, ``N <= K``.

    Raises:
        LocalScaleError: unknown name, or ``akaze`` with an OpenCV that lacks it.
    """
    if num_features < 1:
        raise LocalScaleError(f"num_features must be >= 1, got {num_features}")
    if name == "hessian":
        return HessianDetector(num_features)
    if name in ("harris", "gftt"):
        return ResponseDetector(name, num_features, sigma=2.0)
    if name == "dog":
        return ResponseDetector(name, num_features, sigma=1.6)
    if name in ("sift", "orb", "akaze"):
        return OpenCVDetector(name, num_features)
    raise LocalScaleError(f"unknown detector {name!r}; choose from {', '.join(DETECTORS)}")


def detect(image, name: str = "hessian", num_features: int = 1000):
    """Detect up to ``num_features`` keypoints in one image with the detector ``name``.

    Args:
        image: ``H x W x 3`` uint8 array, path, or ``1 x H x W`` / ``3 x H x W`` float tensor in [0, 1].
        name: one of :data:`DETECTORS`.

    Returns:
        ``(keypoints, responses)``: ``N x 2`` float32 ``(x, y)`` and ``N`` float32, strongest first;
        torch tensors for a tensor input, numpy arrays otherwise.
    """
    detector = get_detector(name, num_features)
    xy, resp = detector(image_to_gray_tensor(image))
    if isinstance(image, torch.Tensor):
        return xy.to(image.device), resp.to(image.device)
    return xy.numpy().astype(np.float32), resp.numpy().astype(np.float32)
