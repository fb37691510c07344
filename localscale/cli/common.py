"""What the commands share: loading a scale model from the options, the output folder check, output names."""

from __future__ import annotations

import hashlib
from collections import Counter, defaultdict
from pathlib import Path

from .. import loading
from ..core.errors import LocalScaleError
from ..core.outputs import resolved_path

ASSETS = Path(__file__).resolve().parent.parent / "assets"  #: the example pair (examples/ use it too)


def _model(args, kind: str):
    return loading.load_scale_model(kind, getattr(args, f"{kind}_weights", None), args.device)


def check_output_dir(path, names=()) -> Path:
    """``-o``: a folder (created later, when writing). Checked before any work: an existing file,
    a folder that cannot be written, or file ``names`` too long for the file system are errors."""
    from ..core.outputs import check_writable_dir

    if isinstance(path, (str, bytes)) and not path:  # Path("") would be the current folder
        raise LocalScaleError("-o: empty output folder name (give a folder, e.g. -o out, or -o . for this one)")
    return check_writable_dir(Path(path), names)


def image_labels(paths, always_parent: bool = False) -> dict:
    """Short, distinct names of image files for output names: the stem, or ``<parent>-<stem>``
    when another file among ``paths`` has the same stem (``v_churchill/1.ppm`` ->
    ``v_churchill-1``) or when ``always_parent``. Keyed by the resolved path."""
    uniq = list(dict.fromkeys(resolved_path(p) for p in paths))
    by_stem = defaultdict(list)
    for p in uniq:
        by_stem[p.stem].append(p)

    def with_parent(p: Path, name: str) -> str:
        return f"{p.parent.name}-{name}" if p.parent.name else name

    labels = {
        p: with_parent(p, p.stem) if (always_parent or len(ps) > 1) else p.stem for ps in by_stem.values() for p in ps
    }
    counts = Counter(labels.values())
    for p in uniq:  # same folder and stem, other extension
        if counts[labels[p]] > 1:
            labels[p] = with_parent(p, p.name.replace(".", "-"))
    return labels


def short_name(name: str, room: int = 200) -> str:
    """``name`` unchanged if it has at most ``room`` bytes, else its start and a hash of it
    (output file names stay within the file system's 255-byte limit)."""
    raw = name.encode("utf-8", "surrogateescape")
    if len(raw) <= room:
        return name
    digest = hashlib.sha1(raw).hexdigest()[:10]
    return raw[: room - 11].decode("utf-8", "ignore") + "~" + digest


def pair_name(image_a, image_b, always_parent: bool = False) -> str:
    """``<A>_<B>`` from :func:`image_labels` (``A_B`` for arrays); shortened by :func:`short_name`
    when too long for a file name."""
    if hasattr(image_a, "shape") or hasattr(image_b, "shape"):
        return "A_B"
    labels = image_labels([image_a, image_b], always_parent)
    return short_name(f"{labels[resolved_path(image_a)]}_{labels[resolved_path(image_b)]}")
