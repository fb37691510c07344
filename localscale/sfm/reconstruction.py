"""The whole reconstruction: images -> features -> pairs -> matches -> geometry -> database -> model.

:func:`reconstruct` runs the steps of :mod:`localscale.sfm` in order, each reading the files of the
steps before and writing its own into ``out_dir`` (hloc style; each also runs alone), then writes ``summary.json`` (atomically), ``reconstruction.png`` and
prints a table. Every input is checked before anything is written (bad input raises a
:class:`~localscale.core.errors.LocalScaleError`).

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

    from localscale.sfm import ReconstructConfig, reconstruct
    summary = reconstruct("photos/", "out/", matcher="aliked-lightglue", correction="auto")
    conf = ReconstructConfig.from_flat(matcher="sift", pairs_nearest=10)  # the same options, whole
    summary = reconstruct("photos/", "out/", conf)
    summary["registered"], summary["points"], summary["seconds"]
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

from ..core.errors import LocalScaleError
from ..core.outputs import check_writable_dir, resolved_path
from . import outdir
from .config import PAIRS_RULES, RESULT_OPTIONS, ReconstructConfig, upgrade_pairs
from .outdir import OutputFolderError
from .report import collecting_warnings, read_json, write_json
from .summary import build_summary, flag, placement_summary, summary_table  # noqa: F401 (summary_table: re-exported)
from .weights import weight_options

_flag = flag  # the summary's warnings (:func:`.summary.flag`)

#: what a ``run.json`` written before an option existed ran with
OPTIONS_BEFORE = {"lightglue_precision": "fp32", "prune_mnn": 0}


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
    previous = upgrade_pairs({**OPTIONS_BEFORE, **previous})
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
    conf: Optional[ReconstructConfig] = None,
    *,
    device: str = "cpu",
    overwrite: bool = False,
    num_threads: int = -1,
    show_progress: bool = True,
    verbose: bool = False,
    plot: bool = True,
    local_model=None,
    global_model=None,
    engine=None,
    input_files: tuple = (),
    reference_model=None,
    **options,
) -> dict:
    """Reconstruct the images of ``images_dir`` into ``out_dir``; returns the summary (also
    ``out_dir/summary.json``).

    Args:
        conf: the options of the run (:class:`~.config.ReconstructConfig` or its ``asdict()``; default: its defaults).
        options: options of ``conf`` to set by name (``matcher="sift"``, ``correction="auto"``,
            ``pairs_nearest=10``, ``mapper="global"``, ...: :meth:`~.config.ReconstructConfig.replace`).
        device: the torch device of extraction and matching.
        overwrite: replace a previous run in ``out_dir`` (else it is resumed if its options are these).
        num_threads: COLMAP's threads (-1: all).
        show_progress, verbose, plot: progress bars, COLMAP's log, ``reconstruction.png``.
        local_model, global_model: the networks of the correction (default: the bundled weights).
        engine: where extraction and matching run: None or ``"local"`` (this process), ``"ray"`` (a
            local Ray cluster with default options) or an :class:`~localscale.engine.Executor`
            (:func:`~localscale.engine.get_executor`; the caller closes it). The outputs are the same.
        input_files: other files the caller read (weights): refused where the run writes (:mod:`.outdir`).
        reference_model: a reference for ``summary.json``'s ``placement`` (how many images the model
            places right, :mod:`.placement`): a COLMAP model folder or a ``name K R t`` table.
    """
    t_total = time.perf_counter()
    if isinstance(conf, dict):
        conf = ReconstructConfig.from_dict(conf)
    elif conf is not None and not isinstance(conf, ReconstructConfig):
        raise LocalScaleError(
            f"conf must be a ReconstructConfig or its dict, got {type(conf).__name__}: give options by name"
        )
    conf = (conf or ReconstructConfig()).replace(**options)
    run = _Reconstruction(
        Path(images_dir),
        Path(out_dir),
        conf,
        _RunTime(
            device, overwrite, num_threads, show_progress, verbose, plot, engine, tuple(input_files), reference_model
        ),
        local_model,
        global_model,
    )
    return run.run(t_total)


@dataclass(frozen=True)
class _RunTime:
    """The arguments of :func:`reconstruct` that do not change the result."""

    device: str = "cpu"
    overwrite: bool = False
    num_threads: int = -1
    show_progress: bool = True
    verbose: bool = False
    plot: bool = True
    engine: Any = None
    input_files: tuple = ()
    reference_model: Any = None


@dataclass
class _Reconstruction:
    """One run of :func:`reconstruct`, one method per stage, called in order by :meth:`run`:
    :meth:`check_arguments` and :meth:`read_inputs` check everything and write nothing; the stages
    from :meth:`prepare_output` on read the files of the stages before from ``out``, write their own
    and their seconds into :attr:`seconds`."""

    images_dir: Path
    out: Path
    conf: ReconstructConfig
    rt: _RunTime
    local_model: Any = None
    global_model: Any = None
    seconds: dict = field(default_factory=dict)

    def run(self, t_total: float) -> dict:
        """Every stage in order; writes ``summary.json`` and returns the summary (``t_total``: when the run began)."""
        self.check_arguments()
        from ..engine import Executor, get_executor

        engine = self.rt.engine
        self.executor = engine if isinstance(engine, Executor) else get_executor(engine or "local")
        try:
            return self._stages(t_total)
        finally:
            if self.executor is not engine:
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
        self.conf.check()
        if resolved_path(self.out) == resolved_path(self.images_dir):
            raise OutputFolderError(f"the output folder is the images folder ({self.out}): give another folder")
        check_writable_dir(self.out)
        self.options = self.conf.options()

    def read_inputs(self) -> None:
        """Read and check the pairs and camera files, the output folder (:attr:`state`), the images
        and their cameras; nothing is written yet."""
        from .cameras import image_cameras
        from .images import find_images
        from .pairs import pairs_from_file

        f, p, m = self.conf.features, self.conf.pairs, self.conf.mapping
        self.options.update(
            weight_options(self.conf.correction.correction, f.matcher, self.local_model, self.global_model)
        )
        self.images = find_images(self.images_dir, exclude=[self.out], max_side=f.max_side)
        pairs_file = None if p.pairs in PAIRS_RULES else p.pairs
        inputs = [("images folder", self.images_dir), ("pairs file", pairs_file), ("camera file", m.camera_file)]
        inputs += [("input file", path) for path in self.rt.input_files]
        inputs += [("reference model", self.rt.reference_model)] if self.rt.reference_model else []
        self.reference = None
        if self.rt.reference_model is not None:
            from .placement import read_reference_centres

            self.reference = read_reference_centres(self.rt.reference_model)
        outdir.check_inputs_kept(self.out, inputs + [("image", im.path) for im in self.images])
        outdir.check_not_held(self.out)
        self.state = _output_state(self.out, self.options, self.rt.overwrite)
        self.names = [im.name for im in self.images]
        self.cameras = image_cameras(self.images, m.camera_mode, m.camera_file)  # a bad camera file fails here
        self.pair_list = pairs_from_file(pairs_file, self.names, self.images_dir) if pairs_file else None
        self.stamps = {im.name: _image_stamp(im) for im in self.images}
        if self.state == "resume":
            self._check_unchanged()
        self._choose_rule()

    def _choose_rule(self) -> None:
        """:attr:`rule`, the :class:`~.pairs.PairsRule` of the run (recorded in its options as
        ``pairs_rule`` and ``pairs_rule_nearest``): a resumed run keeps the rule it began with, so
        that images added to the folder do not switch it between every pair and retrieval (with
        retrieval, their pairs are the nearest among all the images, as in a new run)."""
        from .pairs import PairsRule, pairs_rule

        self.rule = pairs_rule(self.conf.pairs, len(self.names))
        if self.state == "resume":
            before = read_json(self.out / "run.json").get("options", {})
            if before.get("pairs_rule") and self.rule.rule != "file":
                kept = PairsRule(before["pairs_rule"], before.get("pairs_rule_nearest"))
                if kept != self.rule:
                    from .report import warn

                    warn(
                        f"the resumed run keeps its pairs rule, {kept} ({self.rule} for {len(self.names)} images "
                        "now): use --overwrite to choose again"
                    )
                self.rule = kept
        self.options.update(pairs_rule=self.rule.rule, pairs_rule_nearest=self.rule.nearest)

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
        (:func:`~.outdir.begin_writing`), and write ``run.json`` (the options, the configuration,
        the images' stamps)."""
        if _output_state(self.out, self.options, self.rt.overwrite) != self.state:
            raise OutputFolderError(f"another run wrote to {self.out} while this one read its inputs: run again")
        if self.state == "resume":
            self._check_unchanged()
        outdir.begin_writing(self.out, self.state == "overwrite")
        run = {"options": self.options, "config": self.conf.asdict(), "images": self.stamps}
        write_json(self.out / "run.json", {**run, "images_dir": str(resolved_path(self.images_dir))})

    @contextmanager
    def _timed(self, stage: str):
        t = time.perf_counter()
        yield
        self.seconds[stage] = time.perf_counter() - t

    def extract(self) -> None:
        """``features.h5``."""
        from .extract import FeatureConf, extract_features

        f = self.conf.features
        with self._timed("extract"):
            extract_features(
                self.images,
                self.out / "features.h5",
                FeatureConf(f.matcher, f.num_keypoints, f.max_side),
                self.rt.device,
                show_progress=self.rt.show_progress,
                executor=self.executor,
            )

    def choose_pairs(self) -> None:
        """``pairs.txt``: the pairs file's, or those of :attr:`rule` (every pair, or the nearest by
        retrieval from ``features.h5``)."""
        from .pairs import pairs_by_rule, write_pairs

        with self._timed("pairs"):
            if self.pair_list is None:
                self.pair_list = pairs_by_rule(self.rule, self.names, self.out / "features.h5")
            write_pairs(self.out / "pairs.txt", self.pair_list)

    def match(self) -> None:
        """``matches.h5`` and ``keypoints.h5`` from ``features.h5`` and the pairs."""
        from .match import match_pairs

        with self._timed("match"):
            self.mstats = match_pairs(
                self.images,
                self.pair_list,
                self.out / "features.h5",
                self.out / "matches.h5",
                self.out / "keypoints.h5",
                self.conf,
                self.rt.device,
                models=(self.local_model, self.global_model),
                show_progress=self.rt.show_progress,
                executor=self.executor,
            )

    def verify(self) -> None:
        """``geometries.h5`` from ``keypoints.h5`` and ``matches.h5``: the verified two-view geometries."""
        from .geometry import verify_pairs

        with self._timed("geometry"):
            self.gstats = verify_pairs(
                self.images,
                self.out / "keypoints.h5",
                self.out / "matches.h5",
                self.cameras,
                self.out / "geometries.h5",
                show_progress=self.rt.show_progress,
            )

    def build_database(self) -> None:
        """``database.db``, COLMAP's, from the h5 files; a close-up of a photo (found by the matching and
        geometry steps, :func:`~.registration_check.closeup_sources`) with a guessed camera of its own
        starts from zoom x the photo's focal length."""
        from .database import write_database
        from .registration_check import closeup_focal_priors, closeup_sources

        out = self.out
        self.closeups = closeup_sources(self.mstats.pairs, self.gstats.pairs)
        self.guessed_focal = {n: self.cameras.camera(n).focal_lengths[0] for n in self.names}
        self.closeup_priors = closeup_focal_priors(self.cameras, self.closeups)
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
        """``sparse/``: pycolmap's mapping (the mapping section of :attr:`conf`), with the options of
        the cameras' mode (:func:`~.mapper_options.default_overrides`) and ``mapper_options`` over them."""
        from .mapping import default_overrides, run_mapping

        m = self.conf.mapping
        with self._timed("mapping"):
            self.mapping = run_mapping(
                self.out / "database.db",
                self.images_dir,
                self.out / "sparse",
                num_threads=self.rt.num_threads,
                verbose=self.rt.verbose,
                mapper=m.mapper,
                trials=m.mapping_trials,
                overrides={**default_overrides(m.mapper, self.cameras.mode), **m.mapper_options},
                check=self._check,
            )

    def _check(self, rec) -> list:
        """:func:`~.refine.finish_model` of the largest model (the final distortion, the suspect images)."""
        from .mapping import colmap_log
        from .refine import finish_model

        with colmap_log(self.rt.verbose):
            self.distortion_refined, checked = finish_model(
                rec, self.conf.mapping, self.cameras.mode, self.guessed_focal, self.closeups, self.rt.num_threads
            )
        return checked

    def summarize(self) -> dict:
        """The summary (its warnings flagged), and ``reconstruction.png`` when asked."""
        summary = build_summary(
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
        summary.update(placement_summary(self.mapping, self.names, self.closeups, self.reference, self.closeup_priors))
        summary["distortion_refined"] = getattr(self, "distortion_refined", [])
        flag(summary)
        if self.rt.plot:
            from .viz import plot_reconstruction

            status = {k: v["inliers"] > 0 for k, v in self.gstats.pairs.items()}
            plot_reconstruction(
                self.out / "reconstruction.png",
                self.mapping.models[0] if self.mapping.models else None,
                self.names,
                status,
                f"{self.images_dir.name}: {self.conf.features.matcher}, correction {self.conf.correction.correction}",
            )
        return summary
