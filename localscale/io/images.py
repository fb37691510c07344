"""Reading images and homographies with clear errors for bad input.

``load_image`` returns an ``H x W x 3`` RGB array, uint8 by default (what detectors and
descriptors take); with ``precise=True`` an image of more than 8 bits (16-bit PNG/TIFF, float
TIFF, uint16 or float array) comes back as float32 in ``[0, 1]`` at its full precision (what the
scale networks take: :meth:`localscale.models.base.ScaleModel.load`), an 8-bit one as uint8:

* grayscale is replicated to three channels;
* RGBA / gray+alpha: the alpha channel is dropped (a warning says so unless it is fully opaque);
* 16-bit images: uint8 output rescales them (``x / 257``, a warning says so);
* float TIFF files (16, 32 or 64 bit, gray or RGB): ``[0, 1]`` or ``[0, 255]``, told apart by
  their largest value (up to ``1`` is ``[0, 1]``); NaN, inf or values outside both ranges are
  refused; float arrays must be finite and in ``[0, 1]``;
* images smaller than :data:`MIN_SIDE` on a side or above :data:`MAX_PIXELS` pixels are
  refused, however thin otherwise (a 16 x 4000 strip is an image); for files the size is
  read from the header before anything is decoded and checked there (a file decoded at a
  reduced size is not checked again), and a file whose size cannot be read from its header
  is refused undecoded;
* a damaged file whose data ends before the image its header declares (libjpeg's "premature
  end" warning: the rest would be filler) is refused, unless ``accept_damaged=True`` or
  :func:`accepting_damaged` (the CLI's ``--accept-damaged``), where it is decoded with a warning;
* the orientation tag of a file (EXIF, TIFF) is applied exactly once (a portrait photo stays
  portrait): OpenCV's TIFF decoder turns TIFF files itself (OpenCV 5, whatever the flags), the
  other formats are decoded as stored and turned here.

:func:`load_image_reduced` decodes a file much larger than needed at ``1/2``, ``1/4`` or ``1/8``
(JPEG through libjpeg's DCT scaling, other formats reduced right after decoding) and returns the
full size beside it; :func:`load_working_image` brings an image to a working resolution and
returns the matrix from full-image to working pixels; :func:`image_shape` reads the size alone.

Decoder messages (OpenCV's log, libjpeg/libpng warnings on stderr) are kept off the
terminal while a file is decoded; a decoder warning on a file that still decodes is
reported as one Python warning.
"""

from __future__ import annotations

import contextvars
import errno
import functools
import os
import stat
import warnings
from contextlib import contextmanager
from io import BytesIO
from pathlib import Path
from typing import Iterator, Union

import cv2
import numpy as np

from ..core.errors import HomographyError, ImageError
from ..core.quiet import quiet_decoder
from .image_files import TIFF_MAGIC, float_file_to_unit, read_float_tiff, read_header

MIN_SIDE = 16
MAX_PIXELS = 100_000_000
ImageLike = Union[str, os.PathLike, np.ndarray]

_ACCEPT_DAMAGED: contextvars.ContextVar[bool] = contextvars.ContextVar("localscale_accept_damaged", default=False)


@contextmanager
def accepting_damaged(accept: bool = True) -> Iterator[None]:
    """Within the block (in this thread), image files the decoder reports as damaged are decoded as
    they are, with a warning, instead of refused; for calls that do not pass ``accept_damaged``
    themselves (a model's ``predict`` on paths, ``match_pair``). The CLI's ``--accept-damaged``."""
    token = _ACCEPT_DAMAGED.set(bool(accept))
    try:
        yield
    finally:
        _ACCEPT_DAMAGED.reset(token)


#: decoder messages that mean image data is missing (libjpeg's JWRN_JPEG_EOF and JWRN_HIT_MARKER:
#: the rest of the image is filled in grey); other messages (extraneous bytes) stay warnings
_DAMAGED_MESSAGES = ("premature end",)


def _apply_orientation(arr: np.ndarray, orientation: int) -> np.ndarray:
    """Turn an image stored with EXIF orientation ``1..8`` upright (as PIL's ``exif_transpose``)."""
    if orientation == 2:
        return arr[:, ::-1]
    if orientation == 3:
        return arr[::-1, ::-1]
    if orientation == 4:
        return arr[::-1]
    if orientation == 5:
        return arr.swapaxes(0, 1)
    if orientation == 6:
        return np.rot90(arr, -1)
    if orientation == 7:
        return arr[::-1, ::-1].swapaxes(0, 1)
    if orientation == 8:
        return np.rot90(arr, 1)
    return arr


@functools.lru_cache(maxsize=None)
def _tiff_decoder_orients() -> bool:
    """Whether OpenCV's TIFF decoder applies the Orientation tag itself; probed once on a 2 x 4
    TIFF tagged "rotate 90" (OpenCV 5 does; the answer decides whether :func:`_load_file` turns)."""
    try:
        from PIL import Image

        buf = BytesIO()
        Image.fromarray(np.zeros((2, 4), np.uint8)).save(buf, "TIFF", tiffinfo={0x0112: 6})
        with quiet_decoder():
            arr = cv2.imdecode(np.frombuffer(buf.getvalue(), np.uint8), cv2.IMREAD_UNCHANGED)
    except Exception:  # pragma: no cover - no PIL TIFF writer: OpenCV >= 5 behaviour
        return True
    return arr is not None and arr.shape[:2] == (4, 2)


def _stat_file(path: Path, name: str) -> os.stat_result:
    try:
        return path.stat()
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise ImageError(f"{name}: symbolic link loop: {path}") from None
        if e.errno == errno.ENOENT:
            if path.is_symlink():
                raise ImageError(f"{name}: broken symbolic link (its target does not exist): {path}") from None
            raise ImageError(f"{name}: file not found: {path}") from None
        shown = str(path) if len(str(path)) <= 300 else f"{str(path)[:120]}... ({len(str(path))} characters)"
        raise ImageError(f"{name}: cannot access {shown} ({e.strerror})") from None


def load_image(
    image: ImageLike, name: str = "image", *, precise: bool = False, accept_damaged: bool | None = None
) -> np.ndarray:
    """Load an image file or validate an array; returns ``H x W x 3`` uint8 RGB (with ``precise``,
    an image of more than 8 bits as float32 RGB in ``[0, 1]``).

    ``accept_damaged``: decode a file whose data ends early (with a warning) instead of refusing
    it; None: as :func:`accepting_damaged` says (default: refuse).

    Raises:
        ImageError: missing/unreadable/corrupt/damaged file, bad dtype or shape, NaN/inf,
            image too small or too large, size not readable from the file header.
    """
    return load_image_reduced(image, name, precise=precise, accept_damaged=accept_damaged)[0]


def reduction_factor(height: int, width: int, min_long_side: int | None) -> int:
    """The largest of 1, 2, 4, 8 that keeps the longer side at least ``min_long_side``."""
    k = 1
    while min_long_side and k < 8 and max(height, width) / (2 * k) >= min_long_side:
        k *= 2
    return k


def load_image_reduced(
    image: ImageLike,
    name: str = "image",
    min_long_side: int | None = None,
    *,
    precise: bool = False,
    accept_damaged: bool | None = None,
) -> tuple[np.ndarray, tuple[int, int]]:
    """Like :func:`load_image`, but a file much larger than needed is decoded at a reduced size.

    A file whose longer side is at least twice ``min_long_side`` is reduced by the largest
    ``k`` of 2, 4, 8 that keeps its longer side at least ``min_long_side``: JPEG files are
    decoded at ``1/k`` (libjpeg's DCT scaling, which never holds the full image), other formats
    are decoded and at once reduced (area average), before any conversion. Arrays are not reduced.

    Returns:
        ``(rgb, (H, W))``: the ``h x w x 3`` RGB image (uint8; with ``precise``, float32 in
        ``[0, 1]`` for an image of more than 8 bits) and the size of the full image (upright, as
        :func:`load_image` would return it). ``precise``, ``accept_damaged``: as in :func:`load_image`.
    """
    if isinstance(image, (str, os.PathLike)):
        accept = _ACCEPT_DAMAGED.get() if accept_damaged is None else accept_damaged
        return _load_file(Path(image), name, min_long_side, precise, accept)
    rgb = load_image_array(image, name, precise=precise)
    return rgb, rgb.shape[:2]


def load_working_image(
    image: ImageLike, max_side: int | None, name: str = "image", *, accept_damaged: bool | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """An image at a working resolution: its longer side at most ``max_side`` (None: full size).

    Returns ``(rgb, S)``: the uint8 image, and the ``3 x 3`` matrix from pixel coordinates of the
    full image to those of the returned one (the identity when it was not resized)."""
    rgb, (h, w) = load_image_reduced(image, name, max_side, accept_damaged=accept_damaged)
    if not max_side or max(h, w) <= max_side:
        return rgb, np.eye(3)
    f = max_side / max(h, w)
    nw, nh = max(1, round(w * f)), max(1, round(h * f))
    rgb = cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_AREA)
    fx, fy = nw / w, nh / h
    return rgb, np.array([[fx, 0, 0.5 * fx - 0.5], [0, fy, 0.5 * fy - 0.5], [0, 0, 1]])


def image_shape(image: ImageLike, name: str = "image") -> tuple[int, int]:
    """``(H, W)`` of an image (upright) without decoding a file: from its header, checked as
    :func:`load_image` checks it."""
    if isinstance(image, (str, os.PathLike)):
        (width, height), orientation = _checked_header(Path(image), name)
        return (width, height) if orientation in (5, 6, 7, 8) else (height, width)
    return load_image_array(image, name).shape[:2]


def header_shape(path: Union[str, os.PathLike]) -> tuple[int, int]:
    """``(height, width)`` from the file header (upright, EXIF orientation applied); raises
    :class:`~localscale.core.errors.ImageError` for a file that cannot be used (missing, unreadable header,
    smaller than :data:`MIN_SIDE` or above :data:`MAX_PIXELS`). Unlike :func:`image_shape`, the file is
    not checked further (its kind, its decodability)."""
    _stat_file(Path(path), "image")
    try:
        header = read_header(Path(path))
    except OSError as e:
        raise ImageError(f"cannot read {path} ({e.strerror})") from None
    if header is None:
        raise ImageError(f"cannot read the image size of {path} (corrupt, truncated or unsupported format)")
    (w, h), orientation = header
    _check_size(h, w, str(path))
    return (w, h) if orientation in (5, 6, 7, 8) else (h, w)


_FILE_KINDS = (
    (stat.S_ISFIFO, "a named pipe"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def check_image_file(path: str | os.PathLike, name: str = "image") -> None:
    """The checks of an image file that need no read (one ``stat``): it exists, is a regular file
    (a named pipe would block the read) and is not empty. Raises :class:`ImageError` (one line)."""
    path = Path(path)
    st = _stat_file(path, name)
    if stat.S_ISDIR(st.st_mode):
        raise ImageError(f"{name}: is a directory, not an image file: {path}")
    if not stat.S_ISREG(st.st_mode):
        kind = next((k for test, k in _FILE_KINDS if test(st.st_mode)), "a special file")
        raise ImageError(f"{name}: not a regular file ({kind}): {path}")
    if st.st_size == 0:
        raise ImageError(f"{name}: empty file (0 bytes): {path}")


def _checked_header(path: Path, name: str) -> tuple[tuple[int, int], int]:
    check_image_file(path, name)
    try:
        header = read_header(path)
    except OSError as e:
        raise ImageError(f"{name}: cannot read {path} ({e.strerror})") from None
    if header is None:
        raise ImageError(
            f"{name}: cannot decode image, its size cannot be read from the header "
            f"(corrupt, truncated or unsupported format): {path}"
        )
    (width, height), _ = header
    _check_size(height, width, f"{name} ({path})")
    return header


def _load_file(
    path: Path, name: str, min_long_side: int | None, precise: bool = False, accept_damaged: bool = False
) -> tuple[np.ndarray, tuple[int, int]]:
    label = f"{name} ({path})"
    (width, height), orientation = _checked_header(path, name)  # the size limits, on the file's own size
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError as e:
        raise ImageError(f"{name}: cannot read {path} ({e.strerror})") from None
    k = reduction_factor(height, width, min_long_side)
    jpeg_reduced = k > 1 and bytes(data[:3]) == b"\xff\xd8\xff"
    tiff = bytes(data[:4]) in TIFF_MAGIC
    flags = cv2.IMREAD_UNCHANGED
    if jpeg_reduced:
        flags = _REDUCED_COLOR[k] | cv2.IMREAD_IGNORE_ORIENTATION
    with quiet_decoder() as messages:
        arr = cv2.imdecode(data, flags)
    del data
    bgr, oriented = True, tiff and _tiff_decoder_orients()  # as OpenCV's decoders return them
    if arr is None and tiff:
        arr = read_float_tiff(path, name)  # OpenCV reads no float16 TIFF: None if the file is not a float TIFF
        bgr, oriented = False, False
    if arr is None:
        raise ImageError(f"{name}: cannot decode image (corrupt or unsupported format): {path}")
    expected = (-(-height // k), -(-width // k)) if jpeg_reduced else (height, width)
    if sorted(arr.shape[:2]) != sorted(expected):
        raise ImageError(
            f"{name}: decoded image is {arr.shape[1] * (k if jpeg_reduced else 1)}x"
            f"{arr.shape[0] * (k if jpeg_reduced else 1)}, but its header says "
            f"{width}x{height} (corrupt file): {path}"
        )
    damaged = next((m for m in messages if any(w in m.lower() for w in _DAMAGED_MESSAGES)), None)
    if damaged is not None and not accept_damaged:
        raise ImageError(
            f"{name}: damaged file: the decoder reports '{damaged.strip()[:200]}', the image "
            f"data ends before the {width}x{height} image its header declares (the rest would "
            f"be filler; --accept-damaged / accept_damaged=True decodes it anyway): {path}"
        )
    if messages:
        warnings.warn(
            f"{label}: the decoder reported a problem: {(damaged or messages[0]).strip()[:200]}"
            + (" (decoded anyway, part of the image is filler)" if damaged else ""),
            stacklevel=3,
        )
    if np.issubdtype(arr.dtype, np.floating):
        arr = float_file_to_unit(arr, label)
    elif arr.dtype not in (np.uint8, np.uint16):
        raise ImageError(
            f"{name}: its samples are {arr.dtype} (signed or 32-bit integers), whose range is not known: "
            f"give 8- or 16-bit unsigned integer or float samples: {path}"
        )
    if k > 1 and not jpeg_reduced:
        arr = cv2.resize(arr, (-(-arr.shape[1] // k), -(-arr.shape[0] // k)), interpolation=cv2.INTER_AREA)
    if arr.ndim == 3 and bgr:
        code = cv2.COLOR_BGRA2RGBA if arr.shape[2] == 4 else cv2.COLOR_BGR2RGB
        if arr.shape[2] in (3, 4):
            arr = cv2.cvtColor(arr, code)
    full = (width, height) if orientation in (5, 6, 7, 8) else (height, width)
    if not oriented:  # a TIFF comes out of OpenCV's decoder upright
        arr = _apply_orientation(arr, orientation)
    return to_rgb(arr, label, precise=precise, full_shape=full), full


_REDUCED_COLOR = {2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4, 8: cv2.IMREAD_REDUCED_COLOR_8}


def load_image_array(
    image, name: str = "image", *, precise: bool = False, full_shape: tuple[int, int] | None = None
) -> np.ndarray:
    """Validate an array (or a ``C x H x W`` / ``H x W x C`` torch tensor) as :func:`load_image` does.

    ``full_shape``: ``(H, W)`` of the full image when ``image`` is a reduced copy of it; the size
    limits are checked on that size, not on the copy's."""
    if isinstance(image, np.ndarray):
        return to_rgb(image, name, precise=precise, full_shape=full_shape)
    try:  # torch tensors: C x H x W float in [0, 1] or uint8
        import torch

        if isinstance(image, torch.Tensor):
            if image.is_meta:
                raise ImageError(f"{name}: tensor on the meta device (shape only, no data)")
            t = image.detach().cpu()
            if t.dim() == 3 and t.shape[0] in (1, 3, 4) and t.shape[-1] not in (1, 3, 4):
                t = t.permute(1, 2, 0)
            return to_rgb(t.numpy(), name, precise=precise, full_shape=full_shape)
    except ImportError:  # pragma: no cover
        pass
    raise ImageError(f"{name}: expected a file path or a numpy array, got {type(image).__name__}")


def to_rgb_uint8(arr: np.ndarray, name: str = "image", check_size: bool = True) -> np.ndarray:
    """Validate and convert an ``H x W [x C]`` array to ``H x W x 3`` uint8 RGB."""
    return to_rgb(arr, name, check_size=check_size)


def to_rgb(
    arr: np.ndarray,
    name: str = "image",
    check_size: bool = True,
    precise: bool = False,
    full_shape: tuple[int, int] | None = None,
) -> np.ndarray:
    """Validate and convert an ``H x W [x C]`` array to ``H x W x 3`` RGB: uint8, or with ``precise``
    float32 in ``[0, 1]`` for uint16 and float input (no 8-bit rounding). ``full_shape``: the size
    checked instead of the array's (the full image of a reduced copy)."""
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] not in (2, 3, 4)):
        raise ImageError(
            f"{name}: expected H x W, H x W x 2 (gray + alpha), H x W x 3 or H x W x 4, got shape {arr.shape}"
        )
    if check_size:
        _check_size(*(full_shape or arr.shape[:2]), name)
    if arr.ndim == 3 and arr.shape[2] in (2, 4):
        if not _is_opaque(arr[..., -1]):
            warnings.warn(f"{name}: alpha channel dropped", stacklevel=3)
        arr = arr[..., :-1]
        if arr.shape[2] == 1:  # gray + alpha -> gray
            arr = arr[..., 0]
    if arr.dtype == np.uint8:
        out = arr
    elif arr.dtype == np.uint16 and precise:
        out = arr.astype(np.float32) / 65535.0
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
        out = arr.astype(np.float32) if precise else (arr * 255).round().astype(np.uint8)
    else:
        raise ImageError(f"{name}: unsupported dtype {arr.dtype} (use uint8, uint16 or float in [0, 1])")
    if out.ndim == 2:
        out = np.repeat(out[..., None], 3, axis=2)
    return np.ascontiguousarray(out)


def _is_opaque(alpha: np.ndarray) -> bool:
    """True if every alpha value is the dtype's full opacity (255, 65535, 1.0, True)."""
    if alpha.dtype == np.bool_:
        return bool(alpha.all())
    if np.issubdtype(alpha.dtype, np.integer):
        return bool((alpha == np.iinfo(alpha.dtype).max).all())
    return bool((alpha == 1).all())


def _check_size(height: int, width: int, name: str) -> None:
    if height < MIN_SIDE or width < MIN_SIDE:
        raise ImageError(f"{name}: image is {width}x{height}, smaller than the minimum {MIN_SIDE}x{MIN_SIDE}")
    if height * width > MAX_PIXELS:
        raise ImageError(
            f"{name}: image is {width}x{height} ({height * width / 1e6:.0f} MP), "
            f"larger than the limit of {MAX_PIXELS / 1e6:.0f} MP"
        )


def read_homography(path: Union[str, os.PathLike, np.ndarray, list]) -> np.ndarray:
    """Read a 3x3 homography (plain text, 3 lines of 3 numbers, HPatches layout) or validate an array
    (or a nested list of numbers)."""
    if isinstance(path, (list, tuple)):
        try:
            path = np.asarray(path, dtype=np.float64)
        except (TypeError, ValueError):
            raise HomographyError("homography: a nested list must hold 3 x 3 numbers") from None
    if isinstance(path, np.ndarray):
        if not np.issubdtype(path.dtype, np.number):
            raise HomographyError(f"homography: an array of numbers is needed, got dtype {path.dtype}")
        H, src = path.astype(np.float64), "homography"
    else:
        p = Path(path)
        try:
            st = p.stat()
        except OSError as e:
            what = {
                errno.ELOOP: "is a symbolic link loop",
                errno.ENAMETOOLONG: "name is too long",
                errno.EACCES: "is not accessible (permission denied)",
            }.get(e.errno, "not found")
            if e.errno == errno.ENOENT and p.is_symlink():
                what = "is a broken symbolic link"
            raise HomographyError(f"homography file {what}: {p}") from None
        if not stat.S_ISREG(st.st_mode):
            raise HomographyError(f"homography file not found (not a regular file): {p}")
        try:
            H = np.loadtxt(p, dtype=np.float64, ndmin=2)
        except OSError as e:
            raise HomographyError(f"cannot read homography file {p} ({e.strerror or e})") from None
        except (ValueError, UnicodeDecodeError) as e:
            raise HomographyError(f"{p}: not a text matrix of numbers ({str(e).splitlines()[0]})") from None
        src = str(p)
    if H.size == 9:
        H = H.reshape(3, 3)
    else:
        raise HomographyError(f"{src}: expected a 3x3 matrix, got shape {H.shape}")
    if not np.isfinite(H).all():
        raise HomographyError(f"{src}: contains NaN or inf")
    # Rank test on the singular values, relative to the largest one (the matrix_rank tolerance):
    # invariant to the overall scale of H, so large translations and strong zooms pass.
    sv = np.linalg.svd(H, compute_uv=False)
    if not sv[0] > 0 or sv[-1] <= sv[0] * 3 * np.finfo(np.float64).eps:
        raise HomographyError(
            f"{src}: singular homography (rank < 3: smallest singular value {sv[-1]:.3g}, largest {sv[0]:.3g})"
        )
    return H
