"""Writing output files atomically, and checking output folders before any work is done.

Every file localscale writes goes through :func:`atomic_path`: the data is written to a
hidden temporary file in the same folder (``.<name>.<token>.tmp-<pid><suffix>``: a random token
and the process id, so no two runs share one, even when a process id repeats; the same
extension, so encoders pick the same format) and renamed over the final name only when it is
complete. An interrupted or failed write leaves no partial file under the final name, and the
temporary file is removed (a killed process leaves it: :func:`stale_temporaries` finds them).
A folder is replaced in one step by :func:`replace_dir`.
"""

from __future__ import annotations

import ctypes
import os
import secrets
import shutil
import sys
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
    """A new hidden temporary name for ``path`` (same folder and suffix; unique to this call)."""
    return path.with_name(f".{path.stem[:200]}.{secrets.token_hex(4)}.tmp-{os.getpid()}{path.suffix}")


def stale_temporaries(path: Path) -> list:
    """The temporary files of ``path`` that :func:`atomic_path` left in its folder (a killed
    process's), with the ``-wal``, ``-shm`` and ``-journal`` files SQLite keeps beside a database."""
    import re

    path = Path(path)
    if not path.parent.is_dir():
        return []
    stem, suffix = re.escape(path.stem[:200]), re.escape(path.suffix)
    pattern = re.compile(rf"\.{stem}\.(?:[0-9a-f]+\.)?tmp-[0-9]+{suffix}(?:-wal|-shm|-journal)?")
    return sorted(p for p in path.parent.iterdir() if pattern.fullmatch(p.name))


@contextmanager
def atomic_path(path) -> Iterator[Path]:
    """Yield a temporary path to write ``path`` to; on success it is renamed to ``path``.

    On an exception (including ``KeyboardInterrupt``) the temporary file is removed and
    ``path`` is left as it was. An ``OSError`` of the write or the rename becomes a one-line
    :class:`~localscale.core.errors.OutputError` (a :class:`LocalScaleError`) naming ``path``.
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
    if out.is_symlink() and not out.exists():
        raise LocalScaleError(f"output {out} is a broken symbolic link or a link loop")
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

    from .quiet import quiet_decoder  # imports OpenCV

    with atomic_path(path) as tmp, quiet_decoder():  # OpenCV's own warnings stay off the terminal
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


def replace_dir(new, path) -> None:
    """Put the folder ``new`` in the place of ``path`` (a folder, or missing) and remove the old one.

    Where the system can swap two names in one step (Linux's ``renameat2`` with
    ``RENAME_EXCHANGE``) the swap is atomic: ``path`` is always the old folder or the new one.
    Elsewhere the old folder is renamed aside first (``path`` is missing for a moment).
    """
    new, path = Path(new), Path(path)
    if not path.exists() and not path.is_symlink():
        os.rename(new, path)
        return
    if _exchange(new, path):
        _remove_tree(new)  # now the old folder
        return
    old = path.with_name(f".{path.name}.old-{secrets.token_hex(4)}")
    os.rename(path, old)
    os.rename(new, path)
    _remove_tree(old)


def _exchange(a: Path, b: Path) -> bool:
    """Swap the names ``a`` and ``b`` atomically (Linux ``renameat2``); False where that is not possible."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        renameat2 = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    at_fdcwd, rename_exchange = -100, 2
    return renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0


def _remove_tree(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        _remove(path)


def resolved_path(p) -> Path:
    """Absolute path with symbolic links resolved as far as they go (never raises on a link loop)."""
    return Path(os.path.realpath(os.path.abspath(p)))
