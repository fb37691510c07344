"""Writing output files atomically, and checking output folders before any work is done.

Every file localscale writes goes through :func:`atomic_path`: the data is written to a
hidden temporary file in the same folder (``.<name>.tmp-<pid><suffix>``, same extension so
encoders pick the same format) and renamed over the final name only when it is complete.
An interrupted or failed write leaves no partial file under the final name, and the
temporary file is removed.
"""

from __future__ import annotations

import os
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

from .errors import LocalScaleError, OutputError

if TYPE_CHECKING:
    import numpy as np

#: longest file name (one path component) written; most file systems allow 255 bytes
NAME_MAX = 255


def _name_max(folder: Path) -> int:
    try:
        return int(os.pathconf(str(folder), "PC_NAME_MAX"))
    except (OSError, ValueError, AttributeError):
        return NAME_MAX


def temporary_name(path: Path) -> Path:
    """The hidden temporary name :func:`atomic_path` writes ``path`` under (same suffix)."""
    tmp = path.with_name(f".{path.stem[:200]}.tmp-{os.getpid()}{path.suffix}")
    return tmp


@contextmanager
def atomic_path(path) -> Iterator[Path]:
    """Yield a temporary path to write ``path`` to; on success it is renamed to ``path``.

    On an exception (including ``KeyboardInterrupt``) the temporary file is removed and
    ``path`` is left as it was. An ``OSError`` of the write or the rename becomes a one-line
    :class:`~localscale.errors.OutputError` (a :class:`LocalScaleError`) naming ``path``.
    """
    path = Path(path)
    tmp = temporary_name(path)
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as e:
        _remove(tmp)
        raise OutputError(f"cannot write {path}: {e.strerror or e}") from None
    except BaseException:
        _remove(tmp)
        raise


def _remove(tmp: Path) -> None:
    try:
        tmp.unlink()
    except OSError:
        pass


def write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
    return Path(path)


def write_text(path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return write_bytes(path, text.encode("utf-8"))


def check_writable_dir(out: Path, names=()) -> Path:
    """Refuse an output folder that cannot be written, before any work is done.

    ``out`` may not exist yet: then its nearest existing parent must be a writable folder.
    ``names`` (file names to be written into ``out``) must fit the file system's name length.
    Raises :class:`LocalScaleError` (one line).
    """
    out = Path(out)
    for part in out.parts:
        if len(os.fsencode(part)) > NAME_MAX:
            raise LocalScaleError(
                f"output folder name too long ({len(os.fsencode(part))} bytes, the limit is {NAME_MAX}): {part[:40]}..."
            )
    if out.exists():
        if not out.is_dir():
            raise LocalScaleError(f"output {out} exists and is not a folder (-o names a folder)")
        existing = out
    else:
        existing = next((p for p in out.parents if p.exists() or p.is_symlink()), Path("."))
        if existing.is_symlink() and not existing.exists():
            raise LocalScaleError(f"output {out}: {existing} is a broken symbolic link or a link loop")
        if not existing.is_dir():
            raise LocalScaleError(f"output {out}: {existing} is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise LocalScaleError(f"output folder {existing} is not writable (permission denied)")
    limit = _name_max(existing)
    for n in names:
        if len(os.fsencode(n)) > limit:
            raise LocalScaleError(
                f"output file name too long ({len(os.fsencode(n))} bytes, the limit is {limit}): {n[:40]}..."
            )
    return out


# ---------------------------------------------------------------- writers of arrays, images, maps


def ensure_not_input(path, inputs) -> Path:
    """Refuse to write ``path`` when it is one of the command's ``inputs``."""
    path = Path(path)
    for i in inputs:
        if i is not None and not hasattr(i, "shape") and resolved_path(i) == resolved_path(path):
            raise LocalScaleError(f"refusing to overwrite the input {i} with an output")
    return path


def make_dir(path: Path) -> Path:
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise LocalScaleError(f"cannot create output folder {path}: {e.strerror or e}") from None
    return path


def write_image(path, image_bgr: np.ndarray) -> Path:
    """``cv2.imwrite`` (atomic: temporary name, then rename) that raises :class:`LocalScaleError`
    when nothing was written."""
    import cv2

    from .io import _quiet_decoder

    with atomic_path(path) as tmp, _quiet_decoder():  # OpenCV's own warnings stay off the terminal
        try:
            ok = cv2.imwrite(str(tmp), image_bgr)
        except cv2.error as e:
            raise LocalScaleError(f"cannot write {path}: {str(e).strip().splitlines()[-1]}") from None
        if not ok:  # OpenCV says no more; a full disk is the common cause
            full = shutil.disk_usage(Path(tmp).parent).free < max(image_bgr.nbytes // 4, 1 << 16)
            raise LocalScaleError(f"cannot write {path}" + (": no space left on the device" if full else ""))
    return Path(path)


def write_npy(path, array: np.ndarray) -> Path:
    """``np.save`` to ``path`` (atomic: temporary name, then rename)."""
    import numpy as np

    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, array)
    return Path(path)


def write_npy_bands(path, shape: tuple[int, int], bands) -> Path:
    """A float32 ``.npy`` of ``shape`` written from ``(y0, rows)`` row bands in order, without the
    whole array in memory (atomic: temporary name, then rename)."""
    import numpy as np

    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.lib.format.write_array_header_1_0(
                f,
                {
                    "descr": np.lib.format.dtype_to_descr(np.dtype(np.float32)),
                    "fortran_order": False,
                    "shape": tuple(int(n) for n in shape),
                },
            )
            for _, rows in bands:
                # f.write, not ndarray.tofile: a SIGTERM raised inside tofile surfaces as a TypeError
                f.write(np.ascontiguousarray(rows, np.float32).data)
    return Path(path)


def resolved_path(p) -> Path:
    """Absolute path with symbolic links resolved as far as they go (never raises on a link loop)."""
    return Path(os.path.realpath(os.path.abspath(p)))
