"""Pairs files (``predict --pairs``, ``reconstruct --pairs``): one pair of images per line."""

from __future__ import annotations

import shlex
from pathlib import Path

from ..errors import LocalScaleError
from ..outputs import resolved_path
from .common import image_labels, short_name

PAIRS_FORMAT = (
    "one pair per line: 'A<TAB>B' (each field taken as written: spaces, '#' and quotes are part "
    "of the name), or 'A B' with shell-like quoting (\"my photo.jpg\" 'b #2.png'); lines "
    "starting with '#' and blank lines are skipped; relative paths are relative to the file's folder"
)


def _parse_pairs_line(line: str) -> list[str]:
    if "\t" in line:
        return [f for f in line.split("\t") if f != ""]
    return shlex.split(line, comments=False, posix=True)


def read_pairs_file(path: str | Path, with_lines: bool = False) -> list[tuple]:
    """Read a pairs file: :data:`PAIRS_FORMAT`.

    Returns ``[(A, B), ...]``, or ``[(line_number, A, B), ...]`` with ``with_lines``. Bad lines
    (not two fields, unbalanced quotes, not UTF-8) are all reported, by number, in one
    :class:`LocalScaleError`; so is a pairs file that cannot be read or is not a regular file
    (a named pipe or a device would block the read). A UTF-8 byte order mark at the start is dropped.
    """
    import stat

    path = Path(path)
    try:
        mode = path.stat().st_mode
        if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):  # a folder: the read below says so
            kind = (
                "a named pipe"
                if stat.S_ISFIFO(mode)
                else "a device"
                if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
                else "a socket"
                if stat.S_ISSOCK(mode)
                else "a special file"
            )
            raise LocalScaleError(f"pairs file is not a regular file ({kind}): {path}")
        data = path.read_bytes()
    except OSError as e:
        import errno

        what = {
            errno.ENOENT: "pairs file not found",
            errno.ELOOP: "pairs file is a symbolic link loop",
            errno.EISDIR: "pairs file is a folder",
            errno.EACCES: "pairs file is not readable (permission denied)",
            errno.ENAMETOOLONG: "pairs file name too long",
        }.get(e.errno, f"cannot read pairs file ({e.strerror})")
        if e.errno == errno.ENOENT and path.is_symlink():
            what = "pairs file is a broken symbolic link"
        raise LocalScaleError(f"{what}: {path}") from None
    if data.startswith(b"\xef\xbb\xbf"):  # UTF-8 byte order mark (some editors write one)
        data = data[3:]
    pairs, bad = [], []
    for n, raw in enumerate(data.split(b"\n"), 1):
        try:
            line = raw.decode("utf-8")
        except UnicodeDecodeError as e:
            bad.append((n, f"not UTF-8 text (byte 0x{raw[e.start]:02x} at column {e.start + 1})"))
            continue
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        try:
            parts = _parse_pairs_line(line.rstrip("\r"))
        except ValueError as e:
            bad.append((n, f'{e} (quote paths with spaces: "a b.jpg", or separate the two paths by a TAB)'))
            continue
        if len(parts) != 2:
            bad.append((n, f"expected two image paths, got {len(parts)} field(s)"))
            continue
        if any("\0" in p for p in parts):
            bad.append((n, "a path contains a NUL character"))
            continue
        pair = tuple((path.parent / p) if not Path(p).is_absolute() else Path(p) for p in parts)
        pairs.append((n, *pair) if with_lines else pair)
    if bad:
        more = (
            f" (and {len(bad) - 1} more bad line(s): {', '.join(str(n) for n, _ in bad[1:6])}"
            f"{'...' if len(bad) > 6 else ''})"
            if len(bad) > 1
            else ""
        )
        raise LocalScaleError(f"{path}:{bad[0][0]}: {bad[0][1]}{more}")
    if not pairs:
        raise LocalScaleError(f"{path}: no pairs in the file ({PAIRS_FORMAT})")
    return pairs


def pairs_output_names(pairs: list[tuple]) -> list[str]:
    """``<index:05d>_<A>_<B>`` per pair: the index is the pair's position in the list (so it does
    not depend on which pairs fail) and the names come from :func:`image_labels` over all images."""
    labels = image_labels([p for pair in pairs for p in pair])
    return [
        short_name(f"{i:05d}_{labels[resolved_path(a)]}_{labels[resolved_path(b)]}") for i, (a, b) in enumerate(pairs)
    ]
