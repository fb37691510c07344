"""Whether a model places its images right: camera centres against a reference.

Two references:

* a reference model (its camera centres by image name: :func:`read_reference_centres`, a COLMAP model
  or a ``name K R t`` table): the model's centres are aligned to it by a similarity transform
  (Umeyama's, made robust by trying every triple of common images, :func:`align_centres`); a photo is
  placed right when its aligned centre lies within :data:`PHOTO_TOLERANCE` of the *spread* of the
  reference (the median distance of its centres to their centroid) from its reference centre;
* close-ups (``{close-up: source photo}``): a window cut from a photo, or a zoom taken from where the
  photo was, has its photo's centre; it is placed right within :data:`CLOSEUP_TOLERANCE` of the
  spread from the source photo's centre (the reference's when there is one, else the model's own).

An image that is not registered, or registered but left out (:mod:`.registration_check`), is not
placed right. Example::

    p = placement(camera_centres, reference=read_reference_centres("ref/sparse/0"), closeups={"c.jpg": "a.jpg"})
    p["placed_right"], p["checked"], p["wrong"]
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Optional

import numpy as np

from ..core.errors import LocalScaleError

#: a photo's centre is right within this fraction of the reference's spread
PHOTO_TOLERANCE = 0.05
#: a close-up's centre is right within this fraction of the spread from its source photo's centre
CLOSEUP_TOLERANCE = 0.5
#: the most triples :func:`align_centres` tries (all of them when there are fewer)
MAX_TRIPLES = 2000


def spread(centres) -> float:
    """The median distance of ``centres`` (N x 3) to their centroid (0.0 for fewer than 2)."""
    c = np.asarray(centres, np.float64).reshape(-1, 3)
    if len(c) < 2:
        return 0.0
    return float(np.median(np.linalg.norm(c - c.mean(0), axis=1)))


def umeyama(src, dst) -> tuple:
    """``(s, R, t)`` minimising ``sum |s R src_i + t - dst_i|^2`` (Umeyama 1991; N x 3 each, N >= 3)."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    ms, md = src.mean(0), dst.mean(0)
    xs, xd = src - ms, dst - md
    u, d, vt = np.linalg.svd(xd.T @ xs / len(src))
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1
    R = u @ sign @ vt
    var = (xs**2).sum() / len(src)
    s = float(np.trace(np.diag(d) @ sign) / var) if var > 0 else 1.0
    return s, R, md - s * R @ ms


def apply(transform: tuple, points) -> np.ndarray:
    s, R, t = transform
    return s * (np.asarray(points, np.float64).reshape(-1, 3) @ R.T) + t


def align_centres(src, dst, tolerance: float) -> tuple:
    """``(transform, inliers)``: the similarity taking ``src`` to ``dst`` (N x 3, the same images in
    order) that puts the most images within ``tolerance`` (a distance in ``dst``) of their ``dst``
    centre, refit on those (robust: a few misplaced images do not pull it); tries every triple of
    images (at most :data:`MAX_TRIPLES`, chosen with a fixed seed). ``inliers``: a boolean mask."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    n = len(src)
    if n < 3:
        raise LocalScaleError(f"aligning camera centres needs at least 3 common images, got {n}")
    triples = list(itertools.combinations(range(n), 3))
    if len(triples) > MAX_TRIPLES:
        rng = np.random.default_rng(0)
        triples = [triples[i] for i in rng.choice(len(triples), MAX_TRIPLES, replace=False)]
    best, best_key, tf = None, (-1, np.inf), None
    for idx in [tuple(range(n))] + triples:
        sel = list(idx)
        if spread(src[sel]) <= 0 or spread(dst[sel]) <= 0:
            continue
        candidate = umeyama(src[sel], dst[sel])
        err = np.linalg.norm(apply(candidate, src) - dst, axis=1)
        inl = err <= tolerance
        key = (int(inl.sum()), float(np.sum(np.minimum(err, tolerance))))
        if key[0] > best_key[0] or (key[0] == best_key[0] and key[1] < best_key[1]):
            best, best_key, tf = inl, key, candidate
    if best is None:
        raise LocalScaleError("aligning camera centres: the common images are all at one place")
    for _ in range(2):  # refit on the images it places right
        if best.sum() < 3 or spread(src[best]) <= 0:
            break
        tf = umeyama(src[best], dst[best])
        best = np.linalg.norm(apply(tf, src) - dst, axis=1) <= tolerance
    return tf, best


def placement(centres: dict, images, reference: Optional[dict] = None, closeups: Optional[dict] = None) -> dict:
    """How many of ``images`` (names) the model places right (module docstring).

    ``centres``: ``{name: centre}`` of the model's registered images (those it keeps); ``reference``:
    ``{name: centre}`` of a reference model (None: close-ups only); ``closeups``: ``{close-up: source
    photo}``. Returns ``{"reference", "checked", "placed_right", "photos": {"checked", "right"},
    "closeups": {"checked", "right"}, "errors": {name: distance over the spread, None when not
    registered}, "wrong": [...], "not_checked": [...]}``; ``checked`` is 0 when nothing has a reference.
    """
    closeups = {k: v for k, v in (closeups or {}).items() if k in set(images)}
    centres = {k: np.asarray(v, np.float64).reshape(3) for k, v in centres.items()}
    errors, checked_photos, aligned = {}, [], None
    if reference is not None:
        reference = {k: np.asarray(v, np.float64).reshape(3) for k, v in reference.items()}
        checked_photos = [n for n in images if n in reference and n not in closeups]
        scale = spread([reference[n] for n in checked_photos])
        common = [n for n in checked_photos if n in centres]
        if len(common) >= 3 and scale > 0:
            tf, _ = align_centres([centres[n] for n in common], [reference[n] for n in common], PHOTO_TOLERANCE * scale)
            aligned = {n: apply(tf, c)[0] for n, c in centres.items()}
        for n in checked_photos:
            ok = aligned is not None and n in aligned
            errors[n] = float(np.linalg.norm(aligned[n] - reference[n]) / scale) if ok else None
        where, scale_c = (aligned, reference), scale
    else:
        photos = [c for n, c in centres.items() if n not in closeups]
        where, scale_c = (centres, centres), spread(photos)
    checked_close, not_checked = [], []
    for n, source in sorted(closeups.items()):
        model, ref = where
        if source not in ref or scale_c <= 0:
            not_checked.append(n)
            continue
        checked_close.append(n)
        ok = model is not None and n in model
        errors[n] = float(np.linalg.norm(model[n] - ref[source]) / scale_c) if ok else None
    right = {
        n: e is not None and e <= (CLOSEUP_TOLERANCE if n in closeups else PHOTO_TOLERANCE) for n, e in errors.items()
    }
    count = lambda names: sum(right[n] for n in names)  # noqa: E731
    return {
        "reference": "model" if reference is not None else "close-ups",
        "checked": len(errors),
        "placed_right": count(errors),
        "photos": {"checked": len(checked_photos), "right": count(checked_photos)},
        "closeups": {"checked": len(checked_close), "right": count(checked_close)},
        "errors": {n: (None if e is None else round(e, 4)) for n, e in sorted(errors.items())},
        "wrong": sorted(n for n, ok in right.items() if not ok),
        "not_checked": not_checked,
    }


def read_reference_centres(path) -> dict:
    """``{image name: camera centre}`` of a reference: a COLMAP model folder (binary or text;
    ``images.txt`` alone is enough) or a table file of lines ``name fx 0 cx 0 fy cy 0 0 1 R(9) t(3)``
    (Middlebury's ``*_par.txt``; a first line holding only a count is skipped). Raises
    :class:`LocalScaleError` when it cannot be read."""
    path = Path(path)
    try:
        if path.is_dir():
            return _colmap_centres(path)
        if path.is_file():
            return _table_centres(path)
    except (OSError, ValueError, RuntimeError) as e:
        raise LocalScaleError(f"reference model {path} cannot be read: {e}") from None
    raise LocalScaleError(f"reference model not found: {path}")


def _colmap_centres(path: Path) -> dict:
    text = path / "images.txt"
    if not text.is_file():
        import pycolmap

        if not (path / "images.bin").is_file():
            raise ValueError("no images.txt or images.bin in it")
        rec = pycolmap.Reconstruction(str(path))
        return {im.name: np.asarray(im.projection_center()) for im in rec.images.values() if im.has_pose}
    out = {}
    for ln in text.read_text().splitlines():  # each image: its pose line, then its 2D points (triples)
        f = ln.split()
        if ln.startswith("#") or len(f) != 10:
            continue
        qw, qx, qy, qz, tx, ty, tz = map(float, f[1:8])
        out[f[9]] = -_quat_matrix(qw, qx, qy, qz).T @ np.array([tx, ty, tz])
    return out


def _quat_matrix(w, x, y, z) -> np.ndarray:
    n = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _table_centres(path: Path) -> dict:
    out = {}
    for ln in path.read_text().splitlines():
        f = ln.split()
        if len(f) < 22:
            continue
        R = np.array(f[10:19], np.float64).reshape(3, 3)
        out[f[0]] = -R.T @ np.array(f[19:22], np.float64)
    if not out:
        raise ValueError("no line 'name K(9) R(9) t(3)' in it")
    return out
