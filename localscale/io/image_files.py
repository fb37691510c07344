"""Image files read without decoding them: sizes and orientation from the headers (PIL, TIFF tags,
the text headers of PFM / PAM / Radiance HDR), and the samples of float TIFFs (16, 32 or 64 bit),
which OpenCV does not read in every case."""

from __future__ import annotations

import re
import struct
import warnings
import zlib
from pathlib import Path

import numpy as np

from ..core.errors import ImageError

_HEAD_BYTES = 65536
TIFF_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")  # classic and BigTIFF, both byte orders


def _text_header_size(head: bytes) -> tuple[int, int] | None:
    """``(width, height)`` of the formats OpenCV decodes and PIL cannot identify: PFM, PAM and
    Radiance HDR, parsed from their text headers (None if the header is not one of them or is bad)."""
    if head[:2] in (b"PF", b"Pf"):  # PFM: "PF" / "Pf", width, height, scale
        tokens = head[2:256].split()
        if len(tokens) >= 2 and tokens[0].isdigit() and tokens[1].isdigit():
            return int(tokens[0]), int(tokens[1])
        return None
    if head[:3] in (b"P7\n", b"P7\r", b"P7 "):  # PAM: "WIDTH w", "HEIGHT h" lines up to ENDHDR
        fields = {}
        for line in head[3:].splitlines():
            line = line.split(b"#")[0].strip()
            if line == b"ENDHDR":
                break
            parts = line.split()
            if len(parts) == 2 and parts[1].isdigit():
                fields[parts[0].upper()] = int(parts[1])
        else:
            return None
        if b"WIDTH" not in fields or b"HEIGHT" not in fields:
            return None
        return fields[b"WIDTH"], fields[b"HEIGHT"]
    if head.startswith((b"#?RADIANCE", b"#?RGBE")):  # Radiance: header lines, blank line, "-Y h +X w"
        _, sep, rest = head.partition(b"\n\n")
        m = re.match(rb"\s*([-+][XY])\s+(\d+)\s+([-+][XY])\s+(\d+)\s*\n", rest) if sep else None
        if m is None or m.group(1)[1:] == m.group(3)[1:]:
            return None
        dims = {m.group(1)[1:]: int(m.group(2)), m.group(3)[1:]: int(m.group(4))}
        return dims[b"X"], dims[b"Y"]
    return None


#: TIFF field types of integers: type -> (struct code, bytes)
_TIFF_INTS = {
    1: ("B", 1),
    3: ("H", 2),
    4: ("I", 4),
    6: ("b", 1),
    8: ("h", 2),
    9: ("i", 4),
    16: ("Q", 8),
    17: ("q", 8),
    18: ("Q", 8),
}
#: the tags read: size, bits and format of the samples, compression, strips, orientation, layout
_TIFF_TAGS = {256, 257, 258, 259, 273, 274, 277, 278, 279, 284, 317, 322, 339}


def _tiff_tags(path: Path) -> tuple[str, dict[int, tuple]] | None:
    """``(byte order, {tag: values})`` of the first image of a TIFF or BigTIFF file, integer tags
    of :data:`_TIFF_TAGS` only, read without decoding pixels (None if the file is not a readable TIFF)."""
    with open(path, "rb") as f:
        head = f.read(16)
        if head[:4] not in TIFF_MAGIC:
            return None
        bo = "<" if head[:2] == b"II" else ">"
        big = head[2:4] in (b"+\x00", b"\x00+")
        offset = struct.unpack(bo + ("Q" if big else "I"), head[8:16] if big else head[4:8])[0]
        f.seek(offset)
        raw_count = f.read(8 if big else 2)
        if len(raw_count) < (8 if big else 2):
            return None
        count = struct.unpack(bo + ("Q" if big else "H"), raw_count)[0]
        size = 20 if big else 12
        entries = f.read(min(count, 4096) * size)
        tags = {}
        for k in range(len(entries) // size):
            e = entries[k * size : (k + 1) * size]
            tag, typ = struct.unpack(bo + "HH", e[:4])
            if tag not in _TIFF_TAGS or typ not in _TIFF_INTS:
                continue
            n = struct.unpack(bo + ("Q" if big else "I"), e[4:12] if big else e[4:8])[0]
            code, width = _TIFF_INTS[typ]
            inline = e[12:20] if big else e[8:12]
            if n * width > len(inline):
                if n > 1 << 24:
                    return None
                f.seek(struct.unpack(bo + ("Q" if big else "I"), inline)[0])
                data = f.read(n * width)
            else:
                data = inline[: n * width]
            if len(data) < n * width or n == 0:
                return None
            tags[tag] = struct.unpack(f"{bo}{n}{code}", data)
    if 256 not in tags or 257 not in tags:
        return None
    return bo, tags


def _pil_header(path: Path) -> tuple[tuple[int, int], int] | None:
    """``((width, height), exif_orientation)`` read by PIL without decoding pixels (None if unknown);
    the size is that of the stored pixels, before the orientation is applied."""
    try:
        from PIL import Image
    except ImportError:  # pragma: no cover
        return None
    limit = Image.MAX_IMAGE_PIXELS
    try:
        Image.MAX_IMAGE_PIXELS = None  # the size is checked against MAX_PIXELS by the caller
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(path) as im:
                size = im.size
                if im.format == "TIFF" and 256 in im.tag_v2 and 257 in im.tag_v2:
                    size = (int(im.tag_v2[256]), int(im.tag_v2[257]))  # as stored (PIL: upright)
                orientation = 1
                try:  # PNG keeps EXIF after the pixels at times: reading it there would decode them
                    if im.format != "PNG" or "exif" in im.info:
                        orientation = int(im.getexif().get(0x0112, 1))
                except Exception:
                    orientation = 1
                return size, orientation
    except Exception:
        return None
    finally:
        Image.MAX_IMAGE_PIXELS = limit


def read_header(path: Path) -> tuple[tuple[int, int], int] | None:
    """``((width, height), exif_orientation)`` from the file header, None if the size is unknown."""
    with open(path, "rb") as f:
        head = f.read(_HEAD_BYTES)
    size = _text_header_size(head)
    if size is not None:
        return size, 1
    header = _pil_header(path)
    if header is None and head[:4] in TIFF_MAGIC:  # float TIFFs: PIL does not read their samples
        found = _tiff_tags(path)
        if found is not None:
            tags = found[1]
            header = (tags[256][0], tags[257][0]), int(tags.get(274, (1,))[0])
    return header


def read_float_tiff(path: Path, name: str) -> np.ndarray | None:
    """The samples of a float (16, 32 or 64 bit) TIFF stored in strips, uncompressed or deflated,
    as ``H x W [x C]`` float32 in stored order (as OpenCV returns TIFFs before it turns them);
    None if the file is not a float TIFF. Raises :class:`ImageError` for a layout not read here."""
    try:
        found = _tiff_tags(path)
    except OSError as e:
        raise ImageError(f"{name}: cannot read {path} ({e.strerror})") from None
    if found is None or found[1].get(339, (1,))[0] != 3:  # SampleFormat 3: IEEE float
        return None
    bo, tags = found
    width, height = tags[256][0], tags[257][0]
    channels, bits = tags.get(277, (1,))[0], tags.get(258, (32,))[0]
    compression, predictor, planar = tags.get(259, (1,))[0], tags.get(317, (1,))[0], tags.get(284, (1,))[0]
    if (
        322 in tags
        or 273 not in tags
        or 279 not in tags
        or compression not in (1, 8, 32946)
        or predictor != 1
        or bits not in (16, 32, 64)
        or len(tags[273]) != len(tags[279])
    ):
        raise ImageError(
            f"{name}: float TIFF stored in a layout not read here ({bits}-bit samples, compression "
            f"{compression}, predictor {predictor}{', tiles' if 322 in tags else ''}; uncompressed or "
            f"deflated strips without predictor are read): {path}"
        )
    dtype = np.dtype(f"{bo}f{bits // 8}")
    need = width * height * channels * dtype.itemsize
    parts, got = [], 0
    try:
        with open(path, "rb") as f:
            for offset, count in zip(tags[273], tags[279]):
                f.seek(offset)
                part = f.read(count)
                parts.append(part if compression == 1 else zlib.decompress(part))
                got += len(parts[-1])
                if got >= need:
                    break
    except OSError as e:
        raise ImageError(f"{name}: cannot read {path} ({e.strerror})") from None
    except zlib.error:
        raise ImageError(f"{name}: cannot decode image (corrupt deflated data): {path}") from None
    if got < need:
        raise ImageError(f"{name}: cannot decode image (truncated: {got} of {need} bytes of samples): {path}")
    arr = np.frombuffer(b"".join(parts)[:need], dtype)
    if planar == 2:
        arr = arr.reshape(channels, height, width).transpose(1, 2, 0)
    else:
        arr = arr.reshape(height, width, channels)
    return np.ascontiguousarray(arr[..., 0] if channels == 1 else arr, dtype=np.float32)


#: values of a float image file this far outside its range are rounding, clipped; further out, refused
_FLOAT_SLACK = 0.5 / 255
#: a float image whose largest value is above 1 but below this (or whose median is at most 1) is a
#: ``[0, 1]`` image with highlights (HDR), not a ``[0, 255]`` one: as the latter it would be nearly black
_HDR_BELOW = 16.0
#: the percentile of an HDR image's samples that is mapped to 1 (the brighter ones are clipped)
_HDR_PERCENTILE = 99.5


def float_file_to_unit(arr: np.ndarray, label: str) -> np.ndarray:
    """A float image file's samples as float32 in ``[0, 1]``: a ``[0, 1]`` image as it is, a
    ``[0, 255]`` one divided by 255, an HDR one (values above 1, the largest below
    :data:`_HDR_BELOW` or the median at most 1) divided by its :data:`_HDR_PERCENTILE` th percentile
    and clipped, with a warning. NaN, inf, negative values and values above 255 are refused; an
    alpha channel is scaled with the colour channels."""
    arr = arr.astype(np.float32, copy=False)
    if not np.isfinite(arr).all():
        raise ImageError(f"{label}: float image contains NaN or inf")
    lo, hi = float(arr.min()), float(arr.max())
    top = 1.0 if hi <= 1 + _FLOAT_SLACK else 255.0
    if lo < -_FLOAT_SLACK * top or hi > top * (1 + _FLOAT_SLACK):
        raise ImageError(f"{label}: float image values are in [{lo:.4g}, {hi:.4g}]; expected [0, 1] or [0, 255]")
    if top == 255 and (hi < _HDR_BELOW or float(np.median(arr)) <= 1):
        scale = max(1.0, float(np.percentile(arr, _HDR_PERCENTILE)))
        warnings.warn(
            f"{label}: float image with values up to {hi:.3g}, {100 * float(np.mean(arr > 1)):.1f}% of them "
            f"above 1: read as a high dynamic range image, divided by {scale:.3g} (its "
            f"{_HDR_PERCENTILE:g}th percentile) and clipped to [0, 1]",
            stacklevel=4,
        )
        return np.clip(arr / scale, 0, 1)
    return np.clip(arr / top if top != 1 else arr, 0, 1)
