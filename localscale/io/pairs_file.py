"""Pairs files: one pair of images per line (``predict --pairs``, ``reconstruct --pairs``).

:func:`read_pairs_lines` reads the fields as written; :func:`read_pairs_file` turns them into
image paths (relative to the file's folder). The format is :data:`PAIRS_FORMAT`.
"""

from __future__ import annotations

import errno
import shlex
import stat
from pathlib import Path

from ..core.errors import LocalScaleError

PAIRS_FORMAT = (
    "one pair per line: 'A<TAB>B' (each field taken as written: spaces, '#' and quotes are part "
    "of the name), or 'A B' with shell-like quoting (\"my photo.jpg\" 'b #2.png'); lines "
    "starting with '#' and blank lines are skipped; relative paths are relative to the file's folder"
)


class PairsFileError(LocalScaleError):
    """A pairs file cannot be used: missing, not a regular file, malformed lines, unknown images."""


def _split_line(line: str) -> list[str]:
    if "\t" in line:
        return [f for f in line.split("\t") if f != ""]
    return shlex.split(line, comments=False, posix=True)


def _special_file_kind(mode: int) -> str:
    if stat.S_ISFIFO(mode):
        return "a named pipe"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    return "a socket" if stat.S_ISSOCK(mode) else "a special file"


def _read_bytes(path: Path) -> bytes:
    """The file's bytes, or a :class:`PairsFileError` naming why not (a named pipe or a device would block)."""
    try:
        mode = path.stat().st_mode
        if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):  # a folder: the read below says so
            raise PairsFileError(f"pairs file is not a regular file ({_special_file_kind(mode)}): {path}")
        data = path.read_bytes()
    except OSError as e:
        what = {
            errno.ENOENT: "pairs file not found",
            errno.ELOOP: "pairs file is a symbolic link loop",
            errno.EISDIR: "pairs file is a folder",
            errno.EACCES: "pairs file is not readable (permission denied)",
            errno.ENAMETOOLONG: "pairs file name too long",
        }.get(e.errno, f"cannot read pairs file ({e.strerror})")
        if e.errno == errno.ENOENT and path.is_symlink():
            what = "pairs file is a broken symbolic link"
        raise PairsFileError(f"{what}: {path}") from None
    return data[3:] if data.startswith(b"\xef\xbb\xbf") else data  # UTF-8 byte order mark


def read_pairs_lines(path: str | Path) -> list[tuple[int, str, str]]:
    """``[(line_number, A, B), ...]``: the two fields of every pair line, as written.

    Bad lines (not two fields, unbalanced quotes, not UTF-8, a NUL character) are all reported, by
    number, in one :class:`PairsFileError`; so is a file that cannot be read, is not a regular
    file, or holds no pair.
    """
    path = Path(path)
    rows, bad = [], []
    for n, raw in enumerate(_read_bytes(path).split(b"\n"), 1):
        try:
            line = raw.decode("utf-8")
        except UnicodeDecodeError as e:
            bad.append((n, f"not UTF-8 text (byte 0x{raw[e.start]:02x} at column {e.start + 1})"))
            continue
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        try:
            parts = _split_line(line.rstrip("\r"))
        except ValueError as e:
            bad.append((n, f'{e} (quote paths with spaces: "a b.jpg", or separate the two paths by a TAB)'))
            continue
        if len(parts) != 2:
            bad.append((n, f"expected two images (names or paths), got {len(parts)} field(s)"))
        elif any("\0" in p for p in parts):
            bad.append((n, "a path contains a NUL character"))
        else:
            rows.append((n, parts[0], parts[1]))
    if bad:
        listed = ", ".join(str(n) for n, _ in bad[1:6]) + ("..." if len(bad) > 6 else "")
        more = f" (and {len(bad) - 1} more bad line(s): {listed})" if len(bad) > 1 else ""
        raise PairsFileError(f"{path}:{bad[0][0]}: {bad[0][1]}{more}")
    if not rows:
        raise PairsFileError(f"{path}: no pairs in the file ({PAIRS_FORMAT})")
    return rows


def read_pairs_file(path: str | Path, with_lines: bool = False) -> list[tuple]:
    """Read a pairs file (:data:`PAIRS_FORMAT`) into image paths, relative ones taken from the file's folder.

    Returns ``[(A, B), ...]`` of :class:`~pathlib.Path`, or ``[(line_number, A, B), ...]`` with ``with_lines``.

    Raises:
        PairsFileError: as :func:`read_pairs_lines`.
    """
    path = Path(path)
    out = []
    for n, *fields in read_pairs_lines(path):
        pair = tuple(Path(p) if Path(p).is_absolute() else path.parent / p for p in fields)
        out.append((n, *pair) if with_lines else pair)
    return out
