"""The h5 files between the steps, in hloc's layout, written atomically.

* ``features.h5`` (:mod:`.extract`): a group per image name (``/`` in a name makes nested groups,
  as in hloc) with ``keypoints`` (``N x 2`` float32, full-image pixels, pixel centres at integers),
  ``scores`` (``N`` float32), ``descriptors`` (``D x N`` float32) and ``image_size`` (``[W, H]``).
* ``keypoints.h5`` (:mod:`.match`): the same groups with ``keypoints`` and ``image_size`` only:
  every image's one keypoint set that the matches index. Its first ``N`` keypoints are
  ``features.h5``'s; a correction that matches at other scales or turns appends the keypoints of
  those levels that found matches.
* ``matches.h5`` (:mod:`.match`): a group per pair ``<a>/<b>`` (hloc's :func:`~.images.names_to_pair`)
  with ``matches0`` (int32: for each keypoint of A, its match in B or -1; one entry per keypoint A
  had when the pair was matched, later keypoints count as -1) and ``matching_scores0`` (float32).
* ``geometries.h5`` (:mod:`.geometry`): a group per pair with ``inlier_matches`` (``K x 2`` int32,
  indices into ``keypoints.h5``), ``F``, ``E``, ``H``, the relative pose ``R``, ``t`` when there is
  one (``x_B = R x_A + t``) and the attribute ``config`` (COLMAP's two-view configuration).

:class:`H5Writer` adds groups to such a file in memory and :meth:`~H5Writer.flush` writes the file
anew under a temporary name and renames it: the file on disk is always complete (an interrupted
run keeps what was flushed, and a rerun resumes from there).
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path
from typing import Iterator, Optional

import numpy as np

from ..core.errors import LocalScaleError
from ..core.outputs import atomic_path


class H5FileError(LocalScaleError):
    """An h5 file of a step is missing, unreadable or lacks what the next step needs."""


def _h5py():
    try:
        import h5py
    except ImportError:
        raise LocalScaleError("the sfm steps need h5py: pip install h5py") from None
    return h5py


def open_h5(path, mode="r"):
    h5py = _h5py()
    path = Path(path)
    if mode == "r" and not path.is_file():
        raise H5FileError(f"h5 file not found: {path}")
    try:
        return h5py.File(str(path), mode)
    except OSError as e:
        raise H5FileError(f"cannot read {path} as an h5 file ({e})") from None


def groups_with(path, dataset: str) -> list:
    """The paths of the groups of ``path`` that hold ``dataset`` (e.g. image names that have
    ``keypoints``, pair names that have ``matches0``); ``[]`` when the file does not exist."""
    if not Path(path).exists():
        return []
    found = []
    with open_h5(path) as f:

        def visit(name, obj):
            if hasattr(obj, "keys") and dataset in obj:
                found.append(name)

        f.visititems(visit)
    return found


def read_group(path, name: str, keys: Optional[tuple] = None) -> dict:
    """``{dataset: array}`` of group ``name`` of ``path`` (all datasets, or ``keys``), plus its attributes
    under ``"attrs"``."""
    with open_h5(path) as f:
        if name not in f:
            raise H5FileError(f"{path}: no group {name!r}")
        g = f[name]
        out = {k: g[k][()] for k in (keys or [k for k in g.keys() if not hasattr(g[k], "keys")])}
        out["attrs"] = dict(g.attrs)
    return out


class H5Writer:
    """Groups added to an h5 file in memory, written with the file's existing groups by :meth:`flush`
    (atomically); :meth:`maybe_flush` flushes at most every ``every_s`` seconds."""

    def __init__(self, path, every_s: float = 30.0, fresh: bool = False):
        self.path = Path(path)
        self.every_s = every_s
        self.pending: dict = {}
        self.fresh = fresh  # ignore (and replace) an existing file
        self._last = time.monotonic()

    def add(self, name: str, datasets: dict, attrs: Optional[dict] = None) -> None:
        self.pending[name] = (datasets, attrs or {})

    def extend(self, name: str, datasets: dict, attrs: Optional[dict] = None) -> None:
        """Add datasets and attributes to the group ``name`` added and not yet flushed."""
        have, have_attrs = self.pending[name]
        self.pending[name] = ({**have, **datasets}, {**have_attrs, **(attrs or {})})

    def maybe_flush(self) -> bool:
        if self.pending and time.monotonic() - self._last >= self.every_s:
            self.flush()
            return True
        return False

    def flush(self) -> Path:
        h5py = _h5py()
        with atomic_path(self.path) as tmp:
            if self.path.exists() and not self.fresh:
                shutil.copyfile(self.path, tmp)
            with h5py.File(str(tmp), "a") as f:
                for name, (datasets, attrs) in self.pending.items():
                    if name in f:
                        del f[name]
                    g = f.create_group(name)
                    for k, v in datasets.items():
                        g.create_dataset(k, data=np.asarray(v))
                    for k, v in attrs.items():
                        g.attrs[k] = v
        self.pending.clear()
        self.fresh = False
        self._last = time.monotonic()
        return self.path


def matches_from_matches0(matches0: np.ndarray, scores0: Optional[np.ndarray] = None):
    """``(K x 2 int64 (index in A, index in B), K scores)`` of hloc's ``matches0``."""
    m0 = np.asarray(matches0).reshape(-1)
    idx = np.flatnonzero(m0 >= 0)
    m = np.stack([idx, m0[idx]], 1).astype(np.int64)
    s = None if scores0 is None else np.asarray(scores0, np.float32).reshape(-1)[idx]
    return m, s


def matches0_from_matches(matches: np.ndarray, scores: np.ndarray, num_a: int):
    """hloc's ``(matches0, matching_scores0)`` (length ``num_a``) of ``K x 2`` matches."""
    m0 = np.full(num_a, -1, np.int32)
    s0 = np.zeros(num_a, np.float32)
    if len(matches):
        m0[matches[:, 0]] = matches[:, 1]
        s0[matches[:, 0]] = scores
    return m0, s0


def iter_pairs(path) -> Iterator[str]:
    """The pair names of ``matches.h5``."""
    yield from groups_with(path, "matches0")


def read_all_matches(matches_path) -> dict:
    """``{(name_a, name_b): (K x 2 matches, K scores)}`` of ``matches.h5`` (indices into
    ``keypoints.h5``; the names as matched, from the groups' ``name0`` / ``name1``)."""
    out = {}
    keys = groups_with(matches_path, "matches0")
    with open_h5(matches_path) as f:
        for key in keys:
            g = f[key]
            a, b = str(g.attrs.get("name0", "")), str(g.attrs.get("name1", ""))
            if not a or not b:
                a, b = key.split("/", 1)  # written by another tool: names without '/'
            out[(a, b)] = matches_from_matches0(g["matches0"][()], g["matching_scores0"][()])
    return out
