"""Step 6: pycolmap's incremental mapping into ``OUT/sparse/0, 1, ...`` (binary COLMAP models).

The models are numbered by size (``0``: the most registered images). The mapper writes into a
temporary folder; ``sparse/`` is replaced only when it has finished.

Example::

    result = run_mapping("out/database.db", "photos/", "out/sparse")
    result.stats[0]     # images registered, points, observations, mean track length, reprojection error
"""

from __future__ import annotations

import contextlib
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import LocalScaleError


@dataclass
class MappingResult:
    """The models (largest first), their statistics (:func:`model_stats`) and the seconds mapping took."""

    models: list = field(default_factory=list)
    stats: list = field(default_factory=list)
    seconds: float = 0.0


def model_stats(rec) -> dict:
    """Images registered (their names), 3D points, observations, mean track length, mean
    reprojection error (pixels) of a ``pycolmap.Reconstruction``."""
    names = sorted(im.name for im in rec.images.values() if im.has_pose)
    points = rec.num_points3D()
    return {
        "registered": len(names),
        "points": int(points),
        "observations": int(rec.compute_num_observations()),
        "mean_track_length": float(rec.compute_mean_track_length()) if points else 0.0,
        "mean_reprojection_error": float(rec.compute_mean_reprojection_error()) if points else None,
        "registered_images": names,
    }


def mapping_options(num_threads: int = -1, min_model_size: int = 3):
    import pycolmap

    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = num_threads
    opts.min_model_size = min_model_size
    opts.random_seed = 0  # the same run gives the same model
    return opts


@contextlib.contextmanager
def colmap_log(verbose: bool = False):
    """COLMAP's INFO log lines only when ``verbose`` (its warnings and errors always)."""
    import pycolmap

    before = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = before if verbose else max(before, 1)
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = before


def run_mapping(
    database_path, image_dir, sparse_dir, options=None, num_threads: int = -1, verbose: bool = False
) -> MappingResult:
    """Incremental mapping of ``database_path``; writes ``sparse_dir/<i>`` (largest model first).
    ``image_dir`` gives the points their colours (COLMAP reads the images)."""
    import pycolmap

    database_path, sparse_dir = Path(database_path), Path(sparse_dir)
    if not database_path.is_file():
        raise LocalScaleError(f"database not found: {database_path}")
    t0 = time.perf_counter()
    tmp = sparse_dir.with_name(f".{sparse_dir.name}.tmp")
    final_tmp = sparse_dir.with_name(f".{sparse_dir.name}.new")
    for d in (tmp, final_tmp):
        shutil.rmtree(d, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        opts = options or mapping_options(num_threads)
        with colmap_log(verbose):
            models = pycolmap.incremental_mapping(database_path, image_dir, tmp, opts)
        ordered = sorted(models.values(), key=lambda r: (-r.num_reg_images(), -r.num_points3D()))
        final_tmp.mkdir()
        for i, rec in enumerate(ordered):
            d = final_tmp / str(i)
            d.mkdir()
            rec.write(d)
        if sparse_dir.exists():
            shutil.rmtree(sparse_dir)
        final_tmp.rename(sparse_dir)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(final_tmp, ignore_errors=True)
    return MappingResult(ordered, [model_stats(r) for r in ordered], time.perf_counter() - t0)


def read_models(sparse_dir) -> list:
    """The ``pycolmap.Reconstruction`` of each ``sparse_dir/<i>``, in order."""
    import pycolmap

    d = Path(sparse_dir)
    subs = (
        sorted((p for p in d.iterdir() if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name))
        if d.is_dir()
        else []
    )
    return [pycolmap.Reconstruction(p) for p in subs]


def camera_centers(rec) -> tuple:
    """``(names, N x 3 centres)`` of the registered images of a reconstruction."""
    items = sorted((im.name, np.asarray(im.projection_center())) for im in rec.images.values() if im.has_pose)
    return [n for n, _ in items], np.array([c for _, c in items]).reshape(-1, 3)
