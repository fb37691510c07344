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
  replaces our files (the names in :data:`OUTPUTS`) and leaves any other file alone.

Example::

    from localscale.sfm import reconstruct
    summary = reconstruct("photos/", "out/", matcher="aliked-lightglue", correction="auto")
    summary["registered"], summary["points"], summary["seconds"]
"""

from __future__ import annotations

import hashlib
import shutil
import time
from pathlib import Path
from typing import Optional

from ..errors import LocalScaleError
from ..outputs import check_writable_dir
from .report import collecting_warnings, markdown_table, read_json, warn, write_json

#: the files and folders a run writes into its output folder
OUTPUTS = (
    "run.json",
    "features.h5",
    "pairs.txt",
    "matches.h5",
    "keypoints.h5",
    "geometries.h5",
    "database.db",
    "sparse",
    "summary.json",
    "reconstruction.png",
)
#: options that change the result: a resumed run must have the same
RESULT_OPTIONS = (
    "matcher",
    "correction",
    "num_keypoints",
    "max_side",
    "pairs",
    "pairs_file_sha1",
    "pairs_nearest",
    "camera_mode",
    "camera_file_sha1",
    "merge_px",
)


class OutputFolderError(LocalScaleError):
    """The output folder holds something a run must not overwrite or resume."""


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
    entries = [p for p in out.iterdir()] if out.is_dir() else []
    if not entries:
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
) -> dict:
    """Reconstruct the images of ``images_dir`` into ``out_dir``; returns the summary (also
    ``out_dir/summary.json``).

    Args:
        matcher: a name of :data:`localscale.matching.MATCHERS` (its extractor and matching rule).
        correction: :data:`~.match.SFM_CORRECTIONS` (``none``: the cached features matched as they
            are; ``auto``: the scale and quarter-turn hypothesis loop per pair).
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
    """
    from .database import image_cameras, write_database
    from .extract import FeatureConf, build_matcher, extract_features
    from .geometry import verify_pairs
    from .images import find_images
    from .mapping import run_mapping
    from .match import match_pairs
    from .pairs import pairs_exhaustive, pairs_from_file, pairs_from_retrieval, write_pairs

    t_total = time.perf_counter()
    images_dir, out = Path(images_dir), Path(out_dir)
    _check_options(matcher, correction, pairs, pairs_nearest, camera_mode, max_side, num_keypoints)
    if out.resolve() == images_dir.resolve():
        raise OutputFolderError(f"the output folder is the images folder ({out}): give another folder")
    check_writable_dir(out)
    options = {
        "matcher": matcher,
        "correction": correction,
        "num_keypoints": num_keypoints,
        "max_side": max_side,
        "pairs": "exhaustive" if pairs == "exhaustive" else "file",
        "pairs_file_sha1": None,
        "pairs_nearest": pairs_nearest,
        "camera_mode": camera_mode,
        "camera_file_sha1": None,
        "merge_px": merge_px,
    }
    with collecting_warnings() as warnings_seen:
        if pairs != "exhaustive":
            options["pairs_file_sha1"] = _sha1(pairs)
        if camera_file is not None:
            if not Path(camera_file).is_file():
                from .database import CameraFileError

                raise CameraFileError(f"camera file not found: {camera_file}")
            options["camera_file_sha1"] = _sha1(camera_file)
        state = _output_state(out, options, overwrite)
        images = find_images(images_dir, exclude=[out], max_side=max_side)
        names = [im.name for im in images]
        cameras = image_cameras(images, camera_mode, camera_file)  # a bad camera file fails here
        pair_list = pairs_from_file(pairs, names, images_dir) if pairs != "exhaustive" else None
        stamps = {im.name: _image_stamp(im) for im in images}
        if state == "resume":
            before = read_json(out / "run.json").get("images", {})
            changed = [n for n, s in stamps.items() if n in before and list(before[n]) != s]
            if changed:
                raise OutputFolderError(
                    f"{changed[0]} changed since the run in {out}"
                    f"{f' (and {len(changed) - 1} more)' if len(changed) > 1 else ''}: "
                    "use --overwrite to start again"
                )
        # ---- everything is checked: from here on, files are written
        if state == "overwrite":
            for name in OUTPUTS:
                p = out / name
                if p.is_dir():
                    shutil.rmtree(p)
                elif p.exists():
                    p.unlink()
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "run.json", {"options": options, "images": stamps, "images_dir": str(images_dir.resolve())})
        seconds = {}
        conf = FeatureConf(matcher, num_keypoints, max_side)
        level_matcher = build_matcher(conf, device, len(images))

        t = time.perf_counter()
        extract_features(images, out / "features.h5", conf, device, matcher=level_matcher, show_progress=show_progress)
        seconds["extract"] = time.perf_counter() - t

        t = time.perf_counter()
        if pair_list is None:
            pair_list = (
                pairs_from_retrieval(names, out / "features.h5", pairs_nearest)
                if pairs_nearest
                else pairs_exhaustive(names)
            )
        write_pairs(out / "pairs.txt", pair_list)
        seconds["pairs"] = time.perf_counter() - t

        t = time.perf_counter()
        mstats = match_pairs(
            images,
            pair_list,
            out / "features.h5",
            out / "matches.h5",
            out / "keypoints.h5",
            conf,
            correction,
            device,
            matcher=level_matcher,
            merge_px=merge_px,
            show_progress=show_progress,
            local_model=local_model,
            global_model=global_model,
        )
        seconds["match"] = time.perf_counter() - t

        t = time.perf_counter()
        gstats = verify_pairs(
            images,
            out / "keypoints.h5",
            out / "matches.h5",
            cameras,
            out / "geometries.h5",
            show_progress=show_progress,
        )
        seconds["geometry"] = time.perf_counter() - t

        t = time.perf_counter()
        write_database(
            out / "database.db", images, cameras, out / "keypoints.h5", out / "matches.h5", out / "geometries.h5"
        )
        seconds["database"] = time.perf_counter() - t

        t = time.perf_counter()
        mapping = run_mapping(out / "database.db", images_dir, out / "sparse", num_threads=num_threads, verbose=verbose)
        seconds["mapping"] = time.perf_counter() - t
        seconds["total"] = time.perf_counter() - t_total

        summary = _summary(images, pair_list, mstats, gstats, mapping, cameras, options, seconds, state)
        _flag(summary)
        if plot:
            from .viz import plot_reconstruction

            status = {k: v["inliers"] > 0 for k, v in gstats.pairs.items()}
            plot_reconstruction(
                out / "reconstruction.png",
                mapping.models[0] if mapping.models else None,
                names,
                status,
                f"{images_dir.name}: {matcher}, correction {correction}",
            )
        summary["warnings"] = list(warnings_seen)
    write_json(out / "summary.json", summary)
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
        "images_in_other_models": sorted(
            {n for s in mapping.stats[1:] for n in s["registered_images"]} - set(best["registered_images"])
        ),
        "models": [{k: v for k, v in s.items() if k != "registered_images"} for s in mapping.stats],
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
        warn("no model: the mapper registered no images (too few verified pairs?)")
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
