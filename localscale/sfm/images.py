"""The images of a reconstruction: found in a folder, checked once, named as COLMAP and hloc name them.

An image's **name** is its path relative to the images folder, with ``/`` separators and its
extension (``a.jpg``, ``left/b.png``): the name in ``features.h5``, ``matches.h5``, ``pairs.txt``
and the COLMAP database. So ``a.jpg`` and ``a.png`` are two images (a ``warning:`` says they share
a stem), and ``x/a.jpg`` and ``y/a.jpg`` are two images. Names that would give the same pair name
in ``matches.h5`` (hloc writes ``/`` inside a name as ``-``: ``x/a.jpg`` and a file ``x-a.jpg``) are an
error: rename one of them.

Files whose extension is not an image format's, and files whose name (path) is not valid UTF-8
(names in COLMAP's database and the h5 files are UTF-8), are listed in one ``warning:`` each and skipped;
image files that cannot be decoded, or that are too thin at the working resolution, each get a
``warning:`` and are skipped; of copies of one photo (the same pixels) only the first is kept, with a
``warning:``; hidden files and folders (``.name``) are ignored. Fewer than two usable images is an error.
"""

from __future__ import annotations

import hashlib
import os
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Optional

import numpy as np

from ..core.errors import ImageError, LocalScaleError
from ..core.outputs import resolved_path
from .report import warn

#: extensions read as images (any case)
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".ppm", ".pgm", ".pbm", ".bmp", ".tif", ".tiff", ".webp")


class ImageFolderError(LocalScaleError):
    """The images folder cannot be reconstructed: missing, empty, one image, clashing names."""


@dataclass(frozen=True)
class ImageInfo:
    """One usable image: its name (relative path), its file, and its upright size ``(H, W)``."""

    name: str
    path: Path
    shape: tuple


def pair_key(name: str) -> str:
    """How a name appears inside a pair name of ``matches.h5`` (hloc: ``/`` becomes ``-``)."""
    return name.replace("/", "-")


def names_to_pair(name_a: str, name_b: str) -> str:
    """hloc's pair name: ``<a>/<b>`` with ``/`` inside each name written as ``-``."""
    return f"{pair_key(name_a)}/{pair_key(name_b)}"


def find_images(folder, exclude: Iterable = (), check: bool = True, max_side: Optional[int] = 1024) -> list:
    """The usable images under ``folder`` (recursively), sorted by name (:class:`ImageInfo`).

    ``exclude``: folders not searched (e.g. the output folder when it lies inside ``folder``).
    ``check``: decode every image (at ``max_side``, cheap) so that a corrupt file is skipped
    here, with a ``warning:``, and not in the middle of the reconstruction; and so that of
    images with the same pixels (copies of one photo) only the first by name is kept (one
    ``warning:`` lists the others). An image that ``max_side`` would shrink to less than
    :data:`~localscale.io.MIN_SIDE` pixels on a side (a long thin strip) is skipped with a ``warning:``.

    Raises:
        ImageFolderError: ``folder`` missing or not a folder, no usable image, only one, or two
            names that clash in ``matches.h5``.
    """
    from ..io import image_shape, load_working_image

    root = Path(folder)
    if root.is_symlink() and not root.exists():
        raise ImageFolderError(f"images folder {root} is a broken symbolic link or a link loop")
    if not root.exists():
        raise ImageFolderError(f"images folder not found: {root}")
    if not root.is_dir():
        raise ImageFolderError(f"not a folder: {root} (give the folder that holds the images)")
    skip = {resolved_path(p) for p in exclude}
    others, images, unreadable, digests, not_utf8 = [], [], [], {}, []
    for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
        here = Path(dirpath)
        dirnames[:] = sorted(d for d in dirnames if not d.startswith(".") and resolved_path(here / d) not in skip)
        for fn in sorted(filenames):
            if fn.startswith("."):
                continue
            path = here / fn
            name = path.relative_to(root).as_posix()
            if not _is_utf8(name):
                not_utf8.append(name)
                continue
            if path.suffix.lower() not in IMAGE_SUFFIXES:
                others.append(name)
                continue
            try:
                if check:  # decodes: a corrupt file fails here
                    digests[name] = _pixel_digest(load_working_image(path, max_side, name)[0])
                shape = image_shape(path, name)
            except ImageError as e:
                unreadable.append((name, str(e)))
                continue
            thin = _too_thin(shape, max_side)
            if thin:
                unreadable.append((name, thin))
                continue
            images.append(ImageInfo(name, path, tuple(int(v) for v in shape)))
    if others:
        shown = ", ".join(others[:8]) + (f", ... ({len(others)} in all)" if len(others) > 8 else "")
        warn(f"skipped {len(others)} file(s) that are not images ({', '.join(IMAGE_SUFFIXES)}): {shown}")
    if not_utf8:
        shown = ", ".join(_printable(n) for n in not_utf8[:8]) + (", ..." if len(not_utf8) > 8 else "")
        warn(
            f"skipped {len(not_utf8)} file(s) whose name is not valid UTF-8 (image names in COLMAP's "
            f"database and the h5 files are UTF-8; rename them to use them): {shown}"
        )
    for name, why in unreadable:
        warn(f"skipped {name}: {why}")
    images = _without_duplicates(sorted(images, key=lambda im: im.name), digests)
    if not images:
        extra = f" ({len(unreadable)} unreadable)" if unreadable else ""
        raise ImageFolderError(
            f"no usable images in {root}{extra}; images are files ending in {', '.join(IMAGE_SUFFIXES)}"
        )
    if len(images) == 1:
        raise ImageFolderError(
            f"only one usable image in {root} ({images[0].name}): a reconstruction needs at least two views"
        )
    check_names(images)
    return images


def _pixel_digest(rgb) -> str:
    return hashlib.sha256(np.ascontiguousarray(rgb).tobytes()).hexdigest() + f"-{rgb.shape}"


def _too_thin(shape: tuple, max_side: Optional[int]) -> Optional[str]:
    """Why an image of ``shape`` (H, W) is too thin at the working resolution ``max_side``, or None."""
    from ..io import MIN_SIDE

    h, w = shape
    if not max_side or max(h, w) <= max_side:
        return None
    f = max_side / max(h, w)
    wh, ww = max(1, round(h * f)), max(1, round(w * f))
    if min(wh, ww) >= MIN_SIDE:
        return None
    return (
        f"the {w}x{h} image is {ww}x{wh} at the working resolution (longer side {max_side}), "
        f"less than {MIN_SIDE} pixels on a side: too thin to find features in"
    )


def _without_duplicates(images: list, digests: dict) -> list:
    """``images`` less those whose pixels are those of an earlier one (one ``warning:`` lists them)."""
    first, kept, dropped = {}, [], []
    for im in images:
        d = digests.get(im.name)
        if d is not None and d in first:
            dropped.append(f"{im.name} (= {first[d]})")
            continue
        if d is not None:
            first[d] = im.name
        kept.append(im)
    if dropped:
        shown = ", ".join(dropped[:8]) + (f", ... ({len(dropped)} in all)" if len(dropped) > 8 else "")
        warn(
            f"skipped {len(dropped)} duplicate image(s), the same pixels as an image kept (a copy would be "
            f"registered at the same pose and count its points twice): {shown}"
        )
    return kept


def _is_utf8(name: str) -> bool:
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:  # bytes the file system gave that are not UTF-8 (surrogate escapes)
        return False
    return True


def _printable(name: str) -> str:
    """``name`` with the bytes that are not UTF-8 written as ``\\xNN``."""
    return os.fsencode(name).decode("utf-8", "backslashreplace")


def check_names(images: list) -> None:
    """Raise :class:`ImageFolderError` for names that clash in ``matches.h5``; warn (``warning:``)
    for names that differ only in their extension (both are used, as separate images)."""
    by_key, by_stem = defaultdict(list), defaultdict(list)
    for im in images:
        by_key[pair_key(im.name)].append(im.name)
        by_stem[im.name.rsplit(".", 1)[0]].append(im.name)
    clash = [names for names in by_key.values() if len(names) > 1]
    if clash:
        raise ImageFolderError(
            f"image names {' and '.join(clash[0])} clash: hloc's pair names write '/' as '-', "
            "so their matches would mix; rename one of them"
        )
    for _stem, names in by_stem.items():
        if len(names) > 1:
            warn(
                f"{' and '.join(names)} differ only in their extension: both are used, as separate images "
                "(remove one if they are the same photo)"
            )
