"""The images of a reconstruction: found in a folder, checked once, named as COLMAP and hloc name them.

An image's **name** is its path relative to the images folder, with ``/`` separators and its
extension (``a.jpg``, ``left/b.png``): the name in ``features.h5``, ``matches.h5``, ``pairs.txt``
and the COLMAP database. So ``a.jpg`` and ``a.png`` are two images (a ``warning:`` says they share
a stem), and ``x/a.jpg`` and ``y/a.jpg`` are two images. Names that would give the same pair name
in ``matches.h5`` (hloc writes ``/`` inside a name as ``-``: ``x/a.jpg`` and a file ``x-a.jpg``) are an
error: rename one of them.

Files whose extension is not an image format's, and files whose name (path) is not valid UTF-8
(names in COLMAP's database and the h5 files are UTF-8), are listed in one ``warning:`` each and skipped;
image files that cannot be decoded each get a ``warning:`` and are skipped; hidden files and
folders (``.name``) are ignored. Fewer than two usable images is an error.
"""

from __future__ import annotations

import os
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Optional

from ..errors import ImageError, LocalScaleError
from ..outputs import resolved_path
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
    here, with a ``warning:``, and not in the middle of the reconstruction.

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
    others, images, unreadable, not_utf8 = [], [], [], []
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
                if check:
                    load_working_image(path, max_side, name)  # decodes: a corrupt file fails here
                shape = image_shape(path, name)
            except ImageError as e:
                unreadable.append((name, str(e)))
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
    images.sort(key=lambda im: im.name)
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
