"""The mapping step: pycolmap's mapping into ``OUT/sparse/0, 1, ...`` (binary COLMAP models).

Two mappers (:data:`MAPPERS`): COLMAP's ``incremental`` one (registers one image after the other,
bundle adjustment along the way: hloc's and COLMAP's default), and its ``global`` one (GLOMAP:
rotations and positions of every camera at once from the verified pairs, then one bundle
adjustment; COLMAP 4's ``global_mapper``). The global mapper needs focal lengths: when fewer than
half of the cameras have a known one, COLMAP's view-graph calibration runs first
(``colmap view_graph_calibrator``: focal lengths from the fundamental matrices; it updates the
database's cameras and two-view geometries). The models are numbered by size (``0``: the most
registered images). The mapper writes into temporary folders (``.sparse.tmp-*``, ``.sparse.new-*``,
unique to the run); ``sparse/`` is replaced by the new one in one step
(:func:`~localscale.core.outputs.replace_dir`) only when it has finished. A database of two images, or one
where the mapper makes no model (its images connected by single pairs only), gets the best pair's
two-view model (:mod:`.two_views`).

Example::

    result = run_mapping("out/database.db", "photos/", "out/sparse")
    result = run_mapping("out/database.db", "photos/", "out/sparse", mapper="global")
    result.stats[0]     # images registered, points, observations, mean track length, reprojection error
"""

from __future__ import annotations

import contextlib
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from ..core.errors import LocalScaleError, OutputError
from ..core.outputs import replace_dir
from .config import ReconstructConfig
from .mapper_options import (
    MAPPING_TRIALS,
    check_mapper,
    check_trials,
    default_overrides,
    mapping_options,
)
from .steps import config_of, parser, run_step
from .two_views import GLOBAL_TWO_VIEW_OPTIONS, database_images, two_view_mapping


@dataclass
class MappingResult:
    """The models (largest first), their statistics (:func:`model_stats`) and the seconds mapping took."""

    models: list = field(default_factory=list)
    stats: list = field(default_factory=list)
    seconds: float = 0.0
    #: the global mapper's view-graph calibration: None (not run), True (done), False (failed)
    calibrated: Optional[bool] = None
    #: each run of the mapper: ``{"seed", "registered"}`` (:func:`run_mapping`'s ``trials``)
    trials: list = field(default_factory=list)
    #: the options set by name on pycolmap's defaults (:func:`set_options`)
    overrides: dict = field(default_factory=dict)
    #: what ``check`` did to the largest model (:func:`~.registration_check.check_registrations`)
    checked: list = field(default_factory=list)


#: COLMAP's bounds of plausible intrinsics (its mapper's ``min/max_focal_length_ratio``,
#: ``max_extra_param``): focal length over the longer side, and distortion terms
FOCAL_RATIO_RANGE = (0.1, 10.0)
MAX_EXTRA_PARAM = 1.0


def model_stats(rec) -> dict:
    """Images registered (their names), 3D points, observations, mean track length, mean
    reprojection error (pixels) of a ``pycolmap.Reconstruction``, and the registered images whose
    camera has implausible intrinsics (``bogus_cameras``: COLMAP's own test)."""
    names = sorted(im.name for im in rec.images.values() if im.has_pose)
    points = rec.num_points3D()
    bogus = sorted(
        im.name
        for im in rec.images.values()
        if im.has_pose and rec.cameras[im.camera_id].has_bogus_params(*FOCAL_RATIO_RANGE, MAX_EXTRA_PARAM)
    )
    return {
        "registered": len(names),
        "points": int(points),
        "observations": int(rec.compute_num_observations()),
        "mean_track_length": float(rec.compute_mean_track_length()) if points else 0.0,
        "mean_reprojection_error": float(rec.compute_mean_reprojection_error()) if points else None,
        "registered_images": names,
        "bogus_cameras": bogus,
    }


def needs_calibration(database_path) -> bool:
    """Whether fewer than half of the database's cameras have a known focal length
    (``has_prior_focal_length``): the global mapper then needs the view-graph calibration."""
    import pycolmap

    db = pycolmap.Database.open(str(database_path))
    try:
        cameras = db.read_all_cameras()
    finally:
        db.close()
    return 2 * sum(bool(c.has_prior_focal_length) for c in cameras) < len(cameras)


def calibrate_view_graph(database_path) -> bool:
    """COLMAP's view-graph calibration of ``database_path`` (in place): focal lengths from the
    fundamental matrices of the verified pairs, the pairs upgraded to calibrated two-view
    geometries. Returns whether it succeeded (at least half of the cameras have a focal length then)."""
    import pycolmap

    opts = pycolmap.ViewGraphCalibrationOptions()
    opts.random_seed = 0
    done = bool(pycolmap.calibrate_view_graph(str(database_path), opts))
    return done and not needs_calibration(database_path)  # it reports success with no pair to use


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
    database_path,
    image_dir,
    sparse_dir,
    options=None,
    num_threads: int = -1,
    verbose: bool = False,
    mapper: str = "incremental",
    trials: int = MAPPING_TRIALS,
    overrides: Optional[dict] = None,
    check=None,
) -> MappingResult:
    """Mapping of ``database_path`` with ``mapper`` (:data:`MAPPERS`); writes ``sparse_dir/<i>``
    (largest model first). ``image_dir`` gives the points their colours (COLMAP reads the images);
    ``options``: pycolmap's options of that mapper (default :func:`mapping_options` with
    ``overrides``).

    ``trials``: while the largest model leaves images of the database out, the mapper runs again
    with the next random seed (0, 1, ...), at most ``trials`` times in all; the run whose largest
    model registers the most images (then has the most observations) is kept
    (:attr:`MappingResult.trials`: each run's seed and images registered).

    ``check``: a function that changes the largest model in place before it is written and returns
    a list (:attr:`MappingResult.checked`; e.g. :func:`~.registration_check.check_registrations`)."""

    check_mapper(mapper)
    check_trials(trials)
    database_path, sparse_dir = Path(database_path), Path(sparse_dir)
    if not database_path.is_file():
        raise LocalScaleError(f"database not found: {database_path}")
    t0 = time.perf_counter()
    calibrated, checked = None, []
    temporaries = []
    try:
        sparse_dir.parent.mkdir(parents=True, exist_ok=True)
        for kind in ("tmp", "new"):
            temporaries.append(Path(tempfile.mkdtemp(prefix=f".{sparse_dir.name}.{kind}-", dir=sparse_dir.parent)))
        tmp, final_tmp = temporaries
        with colmap_log(verbose):
            if mapper == "global" and needs_calibration(database_path):
                calibrated = calibrate_view_graph(database_path)
            ordered, runs, overrides = _map(
                mapper, (database_path, image_dir, tmp), options, num_threads, overrides, trials
            )
        if check is not None and ordered:
            checked = list(check(ordered[0]))
        for i, rec in enumerate(ordered):
            d = final_tmp / str(i)
            d.mkdir()
            rec.write(d)
        replace_dir(final_tmp, sparse_dir)
    except (OSError, RuntimeError) as e:  # a full disk; COLMAP reports its failures as RuntimeError
        free = shutil.disk_usage(sparse_dir.parent).free // 1024 if sparse_dir.parent.is_dir() else 0
        why = e.strerror if isinstance(e, OSError) and e.strerror else str(e).strip().splitlines()[-1]
        raise OutputError(f"mapping into {sparse_dir} failed: {why} ({free} KB free on its file system)") from None
    finally:
        for d in temporaries:
            shutil.rmtree(d, ignore_errors=True)
    stats = [model_stats(r) for r in ordered]
    return MappingResult(ordered, stats, time.perf_counter() - t0, calibrated, runs, overrides, checked)


def _map(mapper: str, paths: tuple, options, num_threads: int, overrides: Optional[dict], trials: int) -> tuple:
    """``(models, runs, overrides)`` of the mapper on ``paths`` ``(database, images, scratch folder)``.
    A database of two images, or one where the mapper makes no model (every pair alone), is mapped
    again as two views (:mod:`.two_views`): the best pair's model; ``runs`` marks such runs."""
    import pycolmap

    database_path, image_dir, tmp = paths
    two_views = database_images(database_path) == 2
    if two_views and mapper == "global":
        overrides = {**GLOBAL_TWO_VIEW_OPTIONS, **(overrides or {})}
    opts = options or mapping_options(num_threads, mapper=mapper, overrides=overrides)
    run = pycolmap.incremental_mapping if mapper == "incremental" else pycolmap.global_mapping
    if two_views and mapper == "incremental":
        run = two_view_mapping
    ordered, runs = _best_of_trials(run, database_path, image_dir, tmp, opts, trials)
    if ordered or two_views or options is not None:
        return ordered, runs, dict(overrides or {})
    if mapper == "global":
        overrides = {**GLOBAL_TWO_VIEW_OPTIONS, **(overrides or {})}
        run, opts = pycolmap.global_mapping, mapping_options(num_threads, mapper=mapper, overrides=overrides)
    else:
        run = two_view_mapping
    (tmp / "two_views").mkdir()
    ordered, more = _best_of_trials(run, database_path, image_dir, tmp / "two_views", opts, 1)
    return ordered, runs + [dict(r, two_views=True) for r in more], dict(overrides or {})


def _best_of_trials(run, database_path, image_dir, tmp: Path, opts, trials: int) -> tuple:
    """``(models of the best run, largest first; [{"seed", "registered"}] of each run)``."""
    num_images = database_images(database_path)
    rank = lambda ms: (ms[0].num_reg_images(), ms[0].compute_num_observations()) if ms else (0, 0)  # noqa: E731
    best, runs = [], []
    for seed in range(trials):
        opts.random_seed = seed
        out = tmp / str(seed)
        out.mkdir()
        models = run(database_path, image_dir, out, opts)
        ordered = sorted(models.values(), key=lambda r: (-r.num_reg_images(), -r.num_points3D()))
        runs.append({"seed": seed, "registered": rank(ordered)[0]})
        if rank(ordered) > rank(best):
            best = ordered
        if rank(best)[0] >= num_images:
            break
    return best, runs


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


def map_files(images_dir, out_dir, conf: Optional[ReconstructConfig] = None, **kw):
    """The mapping step from ``out_dir/database.db`` -> ``out_dir/sparse`` (``conf.mapping``; the
    defaults of the database's cameras, one or one per image, under its ``mapper_options``; the
    final distortion and the suspect images as they say, :func:`~.refine.finish_model`, the close-ups
    from ``matches.h5`` and ``geometries.h5``)."""
    from .database import read_database
    from .refine import finish_model
    from .registration_check import closeups_from_files

    out, m = Path(out_dir), (conf or ReconstructConfig()).mapping
    db = read_database(out / "database.db")
    mode = "single" if len(db.cameras) == 1 else "per_image"
    overrides = {**default_overrides(m.mapper, mode), **m.mapper_options}
    closeups = closeups_from_files(out / "matches.h5", out / "geometries.h5")
    ids = camera_ids(out / "database.db")
    guessed = {name: float(db.cameras[cid].mean_focal_length()) for name, cid in ids.items()}
    threads = kw.get("num_threads", -1)
    check = lambda rec: finish_model(rec, m, mode, guessed, closeups, threads)[1]  # noqa: E731
    return run_mapping(
        out / "database.db",
        images_dir,
        out / "sparse",
        mapper=m.mapper,
        trials=m.mapping_trials,
        overrides=overrides,
        check=check,
        **kw,
    )


def camera_ids(database_path) -> dict:
    """``{image name: camera id}`` of a COLMAP database."""
    import pycolmap

    db = pycolmap.Database.open(str(database_path))
    try:
        return {im.name: im.camera_id for im in db.read_all_images()}
    finally:
        db.close()


def main(argv=None) -> int:
    """``python -m localscale.sfm.mapping``: this step alone, from files (:func:`map_files`)."""
    p = parser("mapping", __doc__, ("mapper", "mapping_trials"))
    p.add_argument("images", help="folder of images (the points' colours)")
    p.add_argument("out", help="folder with database.db; sparse/ is written there")
    p.add_argument("--num-threads", type=int, default=-1, help="COLMAP threads (-1: all cores)")
    args = p.parse_args(argv)
    return run_step(lambda: map_files(args.images, args.out, config_of(args), num_threads=args.num_threads))


if __name__ == "__main__":
    raise SystemExit(main())
