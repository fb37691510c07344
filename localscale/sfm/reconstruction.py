"""The whole reconstruction: images -> features -> pairs -> matches -> geometry -> database -> model.

:func:`reconstruct` runs the steps of :mod:`localscale.sfm` in order, each writing its file into
``out_dir`` (hloc style), then writes ``summary.json`` (atomically), ``reconstruction.png`` and
prints a table. Every input is checked before anything is written (bad input raises a
:class:`~localscale.errors.LocalScaleError`).

The output folder:

* missing or empty: a new run;
* holding a run of ours (``run.json``) with the same options: **resumed**: images already in
  ``features.h5`` and pairs already in ``matches.h5`` are not done again (an interrupted run goes
  on where it stopped; images added to the folder since are extracted and their pairs matched);
  the geometry, database and mapping are redone (cheap, and they depend on everything). An image
  whose file changed since (size or modification time) is an error: use ``overwrite``;
* holding a run with other options, or anything else: an error, unless ``overwrite``, which
  replaces our files (the names in :data:`~.outdir.OUTPUTS`; see :mod:`.outdir`) and leaves any other file alone.

Example::

    from localscale.sfm import reconstruct
    summary = reconstruct("photos/", "out/", matcher="aliked-lightglue", correction="auto")
    summary["registered"], summary["points"], summary["seconds"]
"""

from __future__ import annotations

import hashlib
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

from ..errors import LocalScaleError
from ..outputs import check_writable_dir, resolved_path
from . import outdir
from .outdir import OutputFolderError
from .report import collecting_warnings, markdown_table, no_model_reason, read_json, warn, write_json
from .weights import WEIGHT_OPTIONS, weight_options

#: options that change the result: a resumed run must have the same
RESULT_OPTIONS = (
    "matcher",
    "correction",
    "auto_graph",
    "num_keypoints",
    "max_side",
    "pairs",
    "pairs_file_sha1",
    "pairs_nearest",
    "camera_mode",
    "camera_file_sha1",
    "merge_px",
) + WEIGHT_OPTIONS


def _sha1(path) -> Optional[str]:
    return None if path is None else hashlib.sha1(Path(path).read_bytes()).hexdigest()


def _check_options(matcher, correction, pairs, pairs_nearest, camera_mode, max_side, num_keypoints) -> None:
    from ..matching import MATCHERS
    from .database import CAMERA_MODES
    from .match import SFM_CORRECTIONS

    if matcher not in MATCHERS:
        raise LocalScaleError(f"unknown matcher {matcher!r}; choose from {', '.join(MATCHERS)}")
    if correction not in SFM_CORRECTIONS:
        raise LocalScaleError(f"correction must be one of {', '.join(SFM_CORRECTIONS)}, got {correction!r}")
    if camera_mode not in CAMERA_MODES:
        raise LocalScaleError(f"camera mode must be one of {', '.join(CAMERA_MODES)}, got {camera_mode!r}")
    if pairs != "exhaustive" and not Path(pairs).is_file():
        raise LocalScaleError(f"--pairs must be 'exhaustive' or a pairs file; file not found: {pairs}")
    if pairs_nearest is not None:
        if pairs != "exhaustive":
            raise LocalScaleError("--pairs-nearest chooses the pairs itself: give it without a pairs file")
        if isinstance(pairs_nearest, bool) or not isinstance(pairs_nearest, int) or pairs_nearest < 1:
            raise LocalScaleError(f"--pairs-nearest must be an integer >= 1, got {pairs_nearest!r}")
    if max_side is not None and (isinstance(max_side, bool) or not isinstance(max_side, int) or max_side < 16):
        raise LocalScaleError(f"--max-side must be an integer >= 16, got {max_side!r}")
    if num_keypoints is not None and (
        isinstance(num_keypoints, bool) or not isinstance(num_keypoints, int) or num_keypoints < 1
    ):
        raise LocalScaleError(f"--num-keypoints must be an integer >= 1, got {num_keypoints!r}")


def _image_stamp(im) -> list:
    st = im.path.stat()
    return [st.st_size, st.st_mtime_ns]


def _output_state(out: Path, options: dict, overwrite: bool) -> str:
    """``new``, ``resume`` or ``overwrite`` for ``out`` (module docstring); raises :class:`OutputFolderError`."""
    if out.exists() and not out.is_dir():
        raise OutputFolderError(f"output is a file, not a folder: {out}")
    if not outdir.run_entries(out):
        return "new"
    if overwrite:
        return "overwrite"
    run = out / "run.json"
    if not run.is_file():
        raise OutputFolderError(
            f"output folder {out} is not empty and holds no run of ours (no run.json): "
            "give an empty or new folder, or --overwrite to write our files into it"
        )
    try:
        previous = read_json(run)["options"]
    except (OSError, ValueError, KeyError, TypeError):
        raise OutputFolderError(f"{run} cannot be read: use --overwrite to start again") from None
    changed = [k for k in RESULT_OPTIONS if previous.get(k) != options.get(k)]
    if changed:
        k = changed[0]
        raise OutputFolderError(
            f"{out} holds a run with other options ({k}: {previous.get(k)!r} there, "
            f"{options.get(k)!r} now): use another folder, the same options, or --overwrite"
        )
    return "resume"


def reconstruct(
    images_dir,
    out_dir,
    matcher: str = "aliked-lightglue",
    correction: str = "none",
    pairs: str = "exhaustive",
    pairs_nearest: Optional[int] = None,
    camera_mode: str = "auto",
    camera_file=None,
    max_side: Optional[int] = 1024,
    num_keypoints: Optional[int] = 2048,
    device: str = "cpu",
    overwrite: bool = False,
    merge_px: float = 1.0,
    num_threads: int = -1,
    show_progress: bool = True,
    verbose: bool = False,
    plot: bool = True,
    local_model=None,
    global_model=None,
    engine=None,
    auto_graph: bool = True,
    mapper: str = "incremental",
    mapping_trials: int = 3,
    mapper_options: Optional[dict] = None,
    input_files: tuple = (),
) -> dict:
    """Reconstruct the images of ``images_dir`` into ``out_dir``; returns the summary (also
    ``out_dir/summary.json``).

    Args:
        matcher: a name of :data:`localscale.matching.MATCHERS` (its extractor and matching rule).
        correction: :data:`~.match.SFM_CORRECTIONS` (``none``: the cached features matched as they
            are; ``auto``: scales and quarter turns found over the pair graph, :func:`~.match.match_pairs`).
        local_model, global_model: the networks of the correction (default: the bundled weights).
        pairs: ``"exhaustive"`` or a pairs file (``A B`` names per line, :func:`~.pairs.pairs_from_file`).
        pairs_nearest: with ``"exhaustive"``: each image with its ``N`` most similar instead
            (:func:`~.pairs.pairs_from_retrieval`).
        camera_mode: ``auto``, ``single`` or ``per_image`` (:func:`~.database.image_cameras`).
        camera_file: a COLMAP ``cameras.txt`` with the one camera of all images.
        max_side, num_keypoints: the working resolution and keypoints per image (None: the matcher's).
        overwrite: replace a previous run in ``out_dir`` (else it is resumed if its options are these).
        merge_px: keypoints of different levels closer than this (full-image pixels) are one.
        num_threads: COLMAP's threads (-1: all).
        engine: where extraction and matching run: None or ``"local"`` (this process), ``"ray"`` (a
            local Ray cluster with default options) or an :class:`~localscale.engine.Executor`
            (:func:`~localscale.engine.get_executor`; the caller closes it). The outputs are the same.
        auto_graph: ``auto`` driven by the pair graph (:func:`~.match.match_pairs`); False: the
            whole hypothesis loop on every pair that does not verify clearly as it is.
        mapper: ``incremental`` (COLMAP's incremental mapper) or ``global`` (its global mapper,
            GLOMAP): :func:`~.mapping.run_mapping`.
        mapping_trials: runs of the mapper (random seeds 0, 1, ...) while its largest model leaves
            images out; the run that registers the most is kept.
        mapper_options: pycolmap options of the mapper set by name
            (:func:`~.mapping.set_options`, e.g. ``{"ba_refine_extra_params": False}``).
        input_files: other files the caller read (weights): refused where the run writes (:mod:`.outdir`).
    """
    t_total = time.perf_counter()
    run = _Reconstruction(
        images_dir=Path(images_dir),
        out=Path(out_dir),
        matcher=matcher,
        correction=correction,
        pairs=pairs,
        pairs_nearest=pairs_nearest,
        camera_mode=camera_mode,
        camera_file=camera_file,
        max_side=max_side,
        num_keypoints=num_keypoints,
        device=device,
        overwrite=overwrite,
        merge_px=merge_px,
        num_threads=num_threads,
        show_progress=show_progress,
        verbose=verbose,
        plot=plot,
        local_model=local_model,
        global_model=global_model,
        engine=engine,
        auto_graph=auto_graph,
        mapper=mapper,
        mapping_trials=mapping_trials,
        mapper_options=dict(mapper_options or {}),
        input_files=tuple(input_files),
    )
    return run.run(t_total)


@dataclass
class _Reconstruction:
    """One run of :func:`reconstruct` (its arguments), one method per stage, called in order by
    :meth:`run`: :meth:`check_arguments` and :meth:`read_inputs` check everything and write nothing;
    the stages from :meth:`prepare_output` on write their files into ``out`` and their seconds into
    :attr:`seconds`, and keep what the later stages need as attributes."""

    images_dir: Path
    out: Path
    matcher: str
    correction: str
    pairs: str
    pairs_nearest: Optional[int]
    camera_mode: str
    camera_file: Any
    max_side: Optional[int]
    num_keypoints: Optional[int]
    device: str
    overwrite: bool
    merge_px: float
    num_threads: int
    show_progress: bool
    verbose: bool
    plot: bool
    local_model: Any
    global_model: Any
    engine: Any = None
    auto_graph: bool = True
    mapper: str = "incremental"
    mapping_trials: int = 3
    mapper_options: dict = field(default_factory=dict)
    input_files: tuple = ()
    seconds: dict = field(default_factory=dict)

    def run(self, t_total: float) -> dict:
        """Every stage in order; writes ``summary.json`` and returns the summary (``t_total``: when the run began)."""
        self.check_arguments()
        from ..engine import Executor, get_executor

        self.executor = self.engine if isinstance(self.engine, Executor) else get_executor(self.engine or "local")
        try:
            return self._stages(t_total)
        finally:
            if self.executor is not self.engine:
                self.executor.close()

    def _stages(self, t_total: float) -> dict:
        with collecting_warnings() as warnings_seen:
            self.read_inputs()
            # ---- everything is checked: from here on, files are written, holding the folder's lock
            with outdir.output_lock(self.out):
                self.prepare_output()
                self.extract()
                self.choose_pairs()
                self.match()
                self.verify()
                self.build_database()
                self.map_model()
                self.seconds["total"] = time.perf_counter() - t_total
                summary = self.summarize()
                summary["warnings"] = list(warnings_seen)
                write_json(self.out / "summary.json", summary)
        return summary

    def check_arguments(self) -> None:
        """The checks that read no input file; sets :attr:`options` (those of ``run.json``)."""
        _check_options(
            self.matcher,
            self.correction,
            self.pairs,
            self.pairs_nearest,
            self.camera_mode,
            self.max_side,
            self.num_keypoints,
        )
        from .mapping import check_mapper, check_trials

        check_mapper(self.mapper)
        check_trials(self.mapping_trials)
        if self.mapper_options:
            from .mapping import mapping_options

            mapping_options(mapper=self.mapper, overrides=self.mapper_options)
        if resolved_path(self.out) == resolved_path(self.images_dir):
            raise OutputFolderError(f"the output folder is the images folder ({self.out}): give another folder")
        check_writable_dir(self.out)
        self.options = {
            "matcher": self.matcher,
            "correction": self.correction,
            "num_keypoints": self.num_keypoints,
            "max_side": self.max_side,
            "pairs": "exhaustive" if self.pairs == "exhaustive" else "file",
            "pairs_file_sha1": None,
            "pairs_nearest": self.pairs_nearest,
            "camera_mode": self.camera_mode,
            "camera_file_sha1": None,
            "merge_px": self.merge_px,
            "auto_graph": self.auto_graph if self.correction == "auto" else None,
            "mapper": self.mapper,
            "mapping_trials": self.mapping_trials,
            "mapper_options": {str(k): v for k, v in sorted(self.mapper_options.items())},
        }

    def read_inputs(self) -> None:
        """Read and check the pairs and camera files, the output folder (:attr:`state`), the images
        and their cameras; nothing is written yet."""
        from .database import image_cameras
        from .images import find_images
        from .pairs import pairs_from_file

        if self.pairs != "exhaustive":
            self.options["pairs_file_sha1"] = _sha1(self.pairs)
        if self.camera_file is not None:
            if not Path(self.camera_file).is_file():
                from .database import CameraFileError

                raise CameraFileError(f"camera file not found: {self.camera_file}")
            self.options["camera_file_sha1"] = _sha1(self.camera_file)
        self.options.update(weight_options(self.correction, self.matcher, self.local_model, self.global_model))
        self.images = find_images(self.images_dir, exclude=[self.out], max_side=self.max_side)
        inputs = [
            ("images folder", self.images_dir),
            ("pairs file", None if self.pairs == "exhaustive" else self.pairs),
        ]
        inputs += [("camera file", self.camera_file)] + [("input file", p) for p in self.input_files]
        outdir.check_inputs_kept(self.out, inputs + [("image", im.path) for im in self.images])
        outdir.check_not_held(self.out)
        self.state = _output_state(self.out, self.options, self.overwrite)
        self.names = [im.name for im in self.images]
        self.cameras = image_cameras(self.images, self.camera_mode, self.camera_file)  # a bad camera file fails here
        self.pair_list = (
            pairs_from_file(self.pairs, self.names, self.images_dir) if self.pairs != "exhaustive" else None
        )
        self.stamps = {im.name: _image_stamp(im) for im in self.images}
        if self.state == "resume":
            self._check_unchanged()

    def _check_unchanged(self) -> None:
        """A resumed run: no image of the previous run changed since (size or modification time)."""
        before = read_json(self.out / "run.json").get("images", {})
        changed = [n for n, s in self.stamps.items() if n in before and list(before[n]) != s]
        if changed:
            raise OutputFolderError(
                f"{changed[0]} changed since the run in {self.out}"
                f"{f' (and {len(changed) - 1} more)' if len(changed) > 1 else ''}: "
                "use --overwrite to start again"
            )

    def prepare_output(self) -> None:
        """Holding the folder's lock: check its state again (another run may have ended meanwhile),
        remove the summary, our files of a run being overwritten and stale temporaries
        (:func:`~.outdir.begin_writing`), and write ``run.json``."""
        if _output_state(self.out, self.options, self.overwrite) != self.state:
            raise OutputFolderError(f"another run wrote to {self.out} while this one read its inputs: run again")
        if self.state == "resume":
            self._check_unchanged()
        outdir.begin_writing(self.out, self.state == "overwrite")
        write_json(
            self.out / "run.json",
            {"options": self.options, "images": self.stamps, "images_dir": str(resolved_path(self.images_dir))},
        )

    @contextmanager
    def _timed(self, stage: str):
        t = time.perf_counter()
        yield
        self.seconds[stage] = time.perf_counter() - t

    def extract(self) -> None:
        """``features.h5``, with the level matcher that the matching stage shares."""
        from .extract import FeatureConf, build_matcher, extract_features

        self.conf = FeatureConf(self.matcher, self.num_keypoints, self.max_side)
        in_process = self.executor.name == "local"
        self.level_matcher = build_matcher(self.conf, self.device, len(self.images)) if in_process else None
        with self._timed("extract"):
            extract_features(
                self.images,
                self.out / "features.h5",
                self.conf,
                self.device,
                matcher=self.level_matcher,
                show_progress=self.show_progress,
                executor=self.executor,
            )

    def choose_pairs(self) -> None:
        """``pairs.txt``: the pairs file's, the nearest by retrieval, or all."""
        from .pairs import pairs_exhaustive, pairs_from_retrieval, write_pairs

        with self._timed("pairs"):
            if self.pair_list is None:
                self.pair_list = (
                    pairs_from_retrieval(self.names, self.out / "features.h5", self.pairs_nearest)
                    if self.pairs_nearest
                    else pairs_exhaustive(self.names)
                )
            write_pairs(self.out / "pairs.txt", self.pair_list)

    def match(self) -> None:
        """``matches.h5`` and ``keypoints.h5``."""
        from .match import match_pairs

        with self._timed("match"):
            self.mstats = match_pairs(
                self.images,
                self.pair_list,
                self.out / "features.h5",
                self.out / "matches.h5",
                self.out / "keypoints.h5",
                self.conf,
                self.correction,
                self.device,
                matcher=self.level_matcher,
                merge_px=self.merge_px,
                show_progress=self.show_progress,
                local_model=self.local_model,
                global_model=self.global_model,
                executor=self.executor,
                auto_graph=self.auto_graph,
            )

    def verify(self) -> None:
        """``geometries.h5``: the verified two-view geometries."""
        from .geometry import verify_pairs

        with self._timed("geometry"):
            self.gstats = verify_pairs(
                self.images,
                self.out / "keypoints.h5",
                self.out / "matches.h5",
                self.cameras,
                self.out / "geometries.h5",
                show_progress=self.show_progress,
            )

    def build_database(self) -> None:
        """``database.db``, COLMAP's."""
        from .database import write_database

        out = self.out
        with self._timed("database"):
            write_database(
                out / "database.db",
                self.images,
                self.cameras,
                out / "keypoints.h5",
                out / "matches.h5",
                out / "geometries.h5",
            )

    def map_model(self) -> None:
        """``sparse/``: pycolmap's mapping (:attr:`mapper`), with the options of the cameras'
        mode (:func:`~.mapping.default_overrides`) and :attr:`mapper_options` over them."""
        from .mapping import default_overrides, run_mapping

        with self._timed("mapping"):
            self.mapping = run_mapping(
                self.out / "database.db",
                self.images_dir,
                self.out / "sparse",
                num_threads=self.num_threads,
                verbose=self.verbose,
                mapper=self.mapper,
                trials=self.mapping_trials,
                overrides={**default_overrides(self.mapper, self.cameras.mode), **self.mapper_options},
            )

    def summarize(self) -> dict:
        """The summary (its warnings flagged), and ``reconstruction.png`` when :attr:`plot`."""
        summary = _summary(
            self.images,
            self.pair_list,
            self.mstats,
            self.gstats,
            self.mapping,
            self.cameras,
            self.options,
            self.seconds,
            self.state,
        )
        summary["engine"] = {"name": self.executor.name, "workers": self.executor.workers}
        _flag(summary)
        if self.plot:
            from .viz import plot_reconstruction

            status = {k: v["inliers"] > 0 for k, v in self.gstats.pairs.items()}
            plot_reconstruction(
                self.out / "reconstruction.png",
                self.mapping.models[0] if self.mapping.models else None,
                self.names,
                status,
                f"{self.images_dir.name}: {self.matcher}, correction {self.correction}",
            )
        return summary


def _summary(images, pair_list, mstats, gstats, mapping, cameras, options, seconds, state) -> dict:
    best = (
        mapping.stats[0]
        if mapping.stats
        else {
            "registered": 0,
            "points": 0,
            "observations": 0,
            "mean_track_length": 0.0,
            "mean_reprojection_error": None,
            "registered_images": [],
            "bogus_cameras": [],
        }
    )
    names = [im.name for im in images]
    return {
        "images": len(images),
        "registered": best["registered"],
        "points": best["points"],
        "observations": best["observations"],
        "mean_track_length": best["mean_track_length"],
        "mean_reprojection_error": best["mean_reprojection_error"],
        "unregistered_images": sorted(set(names) - set(best["registered_images"])),
        "implausible_cameras": best.get("bogus_cameras", []),
        "images_in_other_models": sorted(
            {n for s in mapping.stats[1:] for n in s["registered_images"]} - set(best["registered_images"])
        ),
        "models": [
            {k: v for k, v in s.items() if k not in ("registered_images", "bogus_cameras")} for s in mapping.stats
        ],
        "mapper": options.get("mapper", "incremental"),
        "mapper_options": mapping.overrides,
        "view_graph_calibrated": mapping.calibrated,
        "mapping_runs": mapping.trials,
        "pairs": len(pair_list),
        "pairs_verified": gstats.verified,
        "geometry_estimator": gstats.estimator,
        "matching": mstats.to_dict(),
        "camera_mode": cameras.mode,
        "camera_source": cameras.source,
        "options": options,
        "run": state,
        "seconds": {k: round(v, 2) for k, v in seconds.items()},
    }


def _flag(summary: dict) -> None:
    """``warning:`` lines for a result that should not be trusted as it is."""
    n, r = summary["images"], summary["registered"]
    if r == 0:
        warn(f"no model: the mapper registered no images ({no_model_reason(summary)})")
    elif r < n:
        shown = ", ".join(summary["unregistered_images"][:6])
        warn(
            f"only {r} of {n} images registered in the largest model (not: {shown}"
            f"{', ...' if len(summary['unregistered_images']) > 6 else ''})"
        )
    if summary["images_in_other_models"]:
        shown = ", ".join(summary["images_in_other_models"][:6])
        warn(
            f"the images split into {len(summary['models'])} models: {len(summary['images_in_other_models'])} "
            f"image(s) are only in smaller models, not aligned with the largest ({shown})"
        )
    if summary.get("implausible_cameras"):
        shown = ", ".join(summary["implausible_cameras"][:6])
        warn(
            f"{len(summary['implausible_cameras'])} registered image(s) have implausible intrinsics (focal "
            f"length outside 0.1-10 x the image size or distortion > 1): their poses are not to be trusted ({shown})"
        )
    if summary.get("view_graph_calibrated") is False:
        warn("the view-graph calibration failed: the global mapper ran on guessed focal lengths")
    err = summary["mean_reprojection_error"]
    if err is not None and err > 2.0:
        warn(f"mean reprojection error {err:.2f} px is high: wrong matches or a wrong camera model")


SUMMARY_COLUMNS = [
    ("registered", "registered"),
    ("points", "points"),
    ("observations", "observations"),
    ("mean_track_length", "mean track"),
    ("mean_reprojection_error", "reproj. error (px)"),
    ("pairs_verified", "verified pairs"),
]


def summary_table(summary: dict) -> str:
    """The markdown table of one run: results and seconds per stage."""
    row = dict(summary)
    row["registered"] = f"{summary['registered']}/{summary['images']}"
    row["pairs_verified"] = f"{summary['pairs_verified']}/{summary['pairs']}"
    stages = [(k, f"{k} s") for k in summary["seconds"]]
    row.update(summary["seconds"])
    return markdown_table([row], SUMMARY_COLUMNS + stages)
