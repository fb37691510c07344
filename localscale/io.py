"""Reading images and homographies with clear errors for bad input.

``load_image`` always returns an ``H x W x 3`` uint8 RGB array:

* grayscale is replicated to three channels;
* RGBA / gray+alpha: the alpha channel is dropped (a warning says so);
* 16-bit images are rescaled to 8 bit (``x / 257``, a warning says so);
* float arrays must be finite and in ``[0, 1]``;
* images smaller than :data:`MIN_SIDE` on a side or above :data:`MAX_PIXELS` pixels are
  refused; for files the size is read from the header before anything is decoded.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Union

import cv2
import numpy as np

from .errors import HomographyError, ImageError

MIN_SIDE = 16
MAX_PIXELS = 100_000_000
ImageLike = Union[str, os.PathLike, np.ndarray]


def _header_size(path: Path) -> tuple[int, int] | None:
    """``(width, height)`` from the file header without decoding pixels (None if unknown)."""
    try:
        from PIL import Image

        Image.MAX_IMAGE_PIXELS = None  # we apply our own limit below
        with Image.open(path) as im:
            return im.size
    except Exception:
        return None


def load_image(image: ImageLike, name: str = "image") -> np.ndarray:
    """Load an image file or validate an array; returns ``H x W x 3`` uint8 RGB.

    Raises:
        ImageError: missing/unreadable/corrupt file, bad dtype or shape, NaN/inf,
            image too small or too large.
    """
    if isinstance(image, (str, os.PathLike)):
        path = Path(image)
        if not path.exists():
            raise ImageError(f"{name}: file not found: {path}")
        if path.is_dir():
            raise ImageError(f"{name}: is a directory, not an image file: {path}")
        if path.stat().st_size == 0:
            raise ImageError(f"{name}: empty file (0 bytes): {path}")
        size = _header_size(path)
        if size is not None:
            _check_size(size[1], size[0], f"{name} ({path})")
        data = np.fromfile(str(path), dtype=np.uint8)
        arr = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        if arr is None:
            raise ImageError(f"{name}: cannot decode image (corrupt or unsupported format): {path}")
        if size is None:
            _check_size(arr.shape[0], arr.shape[1], f"{name} ({path})")
        if arr.ndim == 3:
            code = cv2.COLOR_BGRA2RGBA if arr.shape[2] == 4 else cv2.COLOR_BGR2RGB
            if arr.shape[2] in (3, 4):
                arr = cv2.cvtColor(arr, code)
        return to_rgb_uint8(arr, f"{name} ({path})")
    if isinstance(image, np.ndarray):
        return to_rgb_uint8(image, name)
    try:  # torch tensors: C x H x W float in [0, 1] or uint8
        import torch

        if isinstance(image, torch.Tensor):
            t = image.detach().cpu()
            if t.dim() == 3 and t.shape[0] in (1, 3, 4) and t.shape[-1] not in (1, 3, 4):
                t = t.permute(1, 2, 0)
            return to_rgb_uint8(t.numpy(), name)
    except ImportError:  # pragma: no cover
        pass
    raise ImageError(f"{name}: expected a file path or a numpy array, got {type(image).__name__}")


def to_rgb_uint8(arr: np.ndarray, name: str = "image") -> np.ndarray:
    """Validate and convert an ``H x W [x C]`` array to ``H x W x 3`` uint8 RGB."""
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] not in (2, 3, 4)):
        raise ImageError(f"{name}: expected H x W, H x W x 3 or H x W x 4, got shape {arr.shape}")
    _check_size(arr.shape[0], arr.shape[1], name)
    if arr.ndim == 3 and arr.shape[2] in (2, 4):
        warnings.warn(f"{name}: alpha channel dropped", stacklevel=3)
        arr = arr[..., :-1]
    if arr.dtype == np.uint8:
        out = arr
    elif arr.dtype == np.uint16:
        warnings.warn(f"{name}: 16-bit image rescaled to 8 bit", stacklevel=3)
        out = (arr.astype(np.float32) / 257.0).round().astype(np.uint8)
    elif arr.dtype == np.bool_:
        out = arr.astype(np.uint8) * 255
    elif np.issubdtype(arr.dtype, np.floating):
        if not np.isfinite(arr).all():
            raise ImageError(f"{name}: float image contains NaN or inf")
        if arr.min() < 0 or arr.max() > 1:
            raise ImageError(f"{name}: float image must be in [0, 1], got [{arr.min():.3g}, {arr.max():.3g}]")
        out = (arr * 255).round().astype(np.uint8)
    else:
        raise ImageError(f"{name}: unsupported dtype {arr.dtype} (use uint8, uint16 or float in [0, 1])")
    if out.ndim == 2:
        out = np.repeat(out[..., None], 3, axis=2)
    return np.ascontiguousarray(out)


def _check_size(height: int, width: int, name: str) -> None:
    if height < MIN_SIDE or width < MIN_SIDE:
        raise ImageError(f"{name}: image is {width}x{height}, smaller than the minimum {MIN_SIDE}x{MIN_SIDE}")
    if height * width > MAX_PIXELS:
        raise ImageError(f"{name}: image is {width}x{height} ({height * width / 1e6:.0f} MP), "
                         f"larger than the limit of {MAX_PIXELS / 1e6:.0f} MP")


def read_homography(path: Union[str, os.PathLike, np.ndarray]) -> np.ndarray:
    """Read a 3x3 homography (plain text, 3 lines of 3 numbers, HPatches layout) or validate an array."""
    if isinstance(path, np.ndarray):
        H, src = path.astype(np.float64), "homography"
    else:
        p = Path(path)
        if not p.is_file():
            raise HomographyError(f"homography file not found: {p}")
        try:
            H = np.loadtxt(p, dtype=np.float64, ndmin=2)
        except ValueError as e:
            raise HomographyError(f"{p}: not a text matrix of numbers ({str(e).splitlines()[0]})") from None
        src = str(p)
    if H.size == 9:
        H = H.reshape(3, 3)
    else:
        raise HomographyError(f"{src}: expected a 3x3 matrix, got shape {H.shape}")
    if not np.isfinite(H).all():
        raise HomographyError(f"{src}: contains NaN or inf")
    norm = np.abs(H).max()
    if norm == 0 or abs(np.linalg.det(H / norm)) < 1e-12:
        raise HomographyError(f"{src}: singular homography (det = 0)")
    return H
