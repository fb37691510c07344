"""3D reconstruction of the photo collections: pycolmap's SIFT pipeline vs ALIKED + LightGlue, without
and with ``auto``, on each collection as it is and with close-ups added.

Collections: folders of a root (``/work/shared/data/collections``, see its README), each
``<name>/images``. The close-up version (``<name>+closeups``) adds, for every third photo (at least
two), a window showing ``1/z`` of its width and height (``z`` log-uniform in ``zoom``, default
2.5-5), centred at a random point of the photo's central half, resized to the photo's size (the
window's camera is the photo's with a larger focal length and a shifted principal point,
:func:`localscale.geometry.cameras.cut_window`) and turned by a random quarter turn (1-3). They are written
to ``OUT/_closeup_images/<name>`` (the photos linked beside them), described in
``OUT/_closeup_images/<name>.json`` (source, window, zoom, turn). A close-up has the camera
centre of its source photo, so the distance between the two centres in the model (over the median
distance of the cameras to their centroid) says whether a registered close-up sits where it
should (column ``close-up centre err``). Column ``placed right``: the images a model places right
(:mod:`localscale.sfm.placement`: photos within 5% of the spread of the reference's centre, close-ups
within 50% of their photo's) against the collection's reference (:data:`REFERENCES`; else COLMAP SIFT's
model, :func:`reference_of`); each row's ``placement`` has every image's error.

Pipelines (``pipelines``), each mapped with ``mapper`` (COLMAP's ``incremental`` mapper, or its
``global`` one, GLOMAP: rows named ``PIPELINE+global``):

* ``colmap-sift``: ``pycolmap.extract_features`` / ``match_exhaustive`` (COLMAP's SIFT, its own
  verification) / the mapper of ``mapper``, one run (:func:`localscale.sfm.mapping.run_mapping`, ``trials=1``);
  with ``intrinsics[NAME]`` (:func:`read_intrinsics`) the listed photos of NAME get those PINHOLE cameras, kept fixed
  (cyprus's ``derived/intrinsics_resized.txt``: a pseudo ground truth for :mod:`localscale.evaluation.pose`);
* ``aliked-lg``: :func:`localscale.sfm.reconstruct` with ALIKED + LightGlue, 2048 keypoints at 1024 px,
  exhaustive pairs, no correction (what an hloc user runs);
* ``aliked-lg-auto``: the same with ``correction="auto"`` (driven by the pair graph);
* ``aliked-lg-auto-per-pair``: ``auto`` with the whole hypothesis loop on every pair that does not
  verify clearly as it is (``auto_graph=False``);
* ``-fp32``, ``-prune`` after ``aliked-lg`` / ``aliked-lg-auto``: the same with LightGlue in float32
  (``lightglue_precision="fp32"``), or with pairs of fewer than 10 mutual nearest neighbours not given
  to LightGlue as they are (``prune_mnn=10``) (:data:`PIPELINE_OPTIONS`).

Cameras: COLMAP's ``auto`` camera mode on the collections as they are; ``per_image`` on the
close-up versions for every pipeline (a close-up is a zoomed camera: sharing the photos' camera
would be wrong, and a real zoomed photo's EXIF would say so).

``CPU s``: the process's CPU time over the pipeline (all its threads): on a loaded machine a
steadier measure than the wall-clock stages.

Every run goes to ``OUT/<collection>/<pipeline>/``; its row is added to ``OUT/results.json``
(written atomically after each run); a rerun skips the rows already there (``overwrite`` redoes
them). The markdown table is printed and written to ``OUT/results.md``.
"""

from __future__ import annotations

import json
import math
import os
import random
import shutil
import time
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List

import numpy as np

from ..core.outputs import write_text
from .report import git_commit

#: the reference model of a collection (relative to its folder): camera centres by image name
#: (:func:`localscale.sfm.placement.read_reference_centres`); the others use colmap-sift's own model
REFERENCES = {
    "kermit_bundler": "derived/colmap_txt",
    "skull_alansartlog": "derived/colmap_txt_resized",
    "temple_sparse_ring_middlebury": "derived/templeSR_par_jpgnames.txt",
}
PIPELINES = (
    "colmap-sift",
    "aliked-lg",
    "aliked-lg-auto",
    "aliked-lg-auto-per-pair",
    "aliked-lg-fp32",
    "aliked-lg-auto-fp32",
    "aliked-lg-prune",
    "aliked-lg-auto-prune",
)
#: ``-SUFFIX`` of a pipeline name: the reconstruction options it changes
PIPELINE_OPTIONS = {"fp32": {"lightglue_precision": "fp32"}, "prune": {"prune_mnn": 10}}
COLUMNS = [
    ("collection", "collection"),
    ("pipeline", "pipeline"),
    ("registered", "registered"),
    ("closeups_registered", "close-ups reg."),
    ("closeup_centre_error", "close-up centre err"),
    ("placed_right", "placed right"),
    ("reference", "reference"),
    ("points", "points"),
    ("observations", "observations"),
    ("mean_track_length", "mean track"),
    ("mean_reprojection_error", "reproj. err (px)"),
    ("extract_s", "extract s"),
    ("match_s", "match s"),
    ("verify_s", "verify s"),
    ("map_s", "db + map s"),
    ("total_s", "total s"),
    ("cpu_s", "CPU s"),
]


# ---------------------------------------------------------------- close-ups


def make_closeups(images_dir: Path, out_dir: Path, zoom: tuple, seed: int) -> dict:
    """``out_dir`` with links to the photos of ``images_dir`` and the close-ups (module docstring);
    returns ``{close-up name: {"source", "window", "zoom", "turn"}}`` (also ``<out_dir>.json``)."""
    import cv2

    from ..geometry.cameras import Camera, cut_window

    meta_path = out_dir.with_name(out_dir.name + ".json")
    inside = out_dir / "closeups.json"  # where an earlier version kept it (then read as a non-image)
    if inside.is_file() and not meta_path.is_file():
        write_text(meta_path, inside.read_text())
        inside.unlink()
    if meta_path.is_file() and out_dir.is_dir():
        return json.loads(meta_path.read_text())
    tmp = out_dir.with_name(out_dir.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    photos = sorted(p for p in images_dir.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    for p in photos:
        os.symlink(p.resolve(), tmp / p.name)
    rng = random.Random(seed)
    count = max(2, round(len(photos) / 3))
    sources = [photos[int(round(i * (len(photos) - 1) / max(1, count - 1)))] for i in range(count)]
    meta = {}
    for p in dict.fromkeys(sources):
        bgr = cv2.imread(str(p))
        H, W = bgr.shape[:2]
        z = math.exp(rng.uniform(math.log(zoom[0]), math.log(zoom[1])))
        w, h = int(round(W / z)), int(round(H / z))
        cx = rng.uniform(W / 4, 3 * W / 4)
        cy = rng.uniform(H / 4, 3 * H / 4)
        x0 = int(np.clip(round(cx - w / 2), 0, W - w))
        y0 = int(np.clip(round(cy - h / 2), 0, H - h))
        turn = rng.randint(1, 3)
        img, cam, _ = cut_window(bgr, Camera.from_prior(W, H), (x0, y0, w, h), (W, H), turn)
        name = f"closeup_{p.stem}_z{z:.2f}_t{turn}.jpg"
        cv2.imwrite(str(tmp / name), img, [cv2.IMWRITE_JPEG_QUALITY, 92])
        meta[name] = {"source": p.name, "window": [x0, y0, w, h], "zoom": round(z, 3), "turn": turn}
    shutil.rmtree(out_dir, ignore_errors=True)
    tmp.rename(out_dir)
    write_text(meta_path, json.dumps(meta, indent=2) + "\n")
    return meta


# ---------------------------------------------------------------- pipelines


def read_intrinsics(path: Path) -> dict:
    """``{image name: "fx,fy,cx,cy"}`` from lines ``name w h fx fy cx cy`` (PINHOLE; ``#`` comments),
    the layout of a collection's ``derived/intrinsics_resized.txt``."""
    out = {}
    for line in Path(path).read_text().splitlines():
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        if len(parts) != 7:
            raise ValueError(f"{path}: expected 'name w h fx fy cx cy', got {line!r}")
        out[parts[0]] = ",".join(str(float(v)) for v in parts[3:])
    return out


#: the mapper keeps known intrinsics as they are
FIXED_INTRINSICS = {
    "ba_refine_focal_length": False,
    "ba_refine_principal_point": False,
    "ba_refine_extra_params": False,
}


def run_colmap_sift(
    images_dir: Path, run_dir: Path, camera_mode: str, threads: int, mapper: str, intrinsics: dict = None
) -> dict:
    """COLMAP's SIFT pipeline; ``intrinsics`` (:func:`read_intrinsics`): each listed image gets its
    own PINHOLE camera with those parameters, which the mapper does not refine (the others as
    ``camera_mode`` says)."""
    import pycolmap

    from ..sfm.mapping import colmap_log, run_mapping

    shutil.rmtree(run_dir, ignore_errors=True)
    run_dir.mkdir(parents=True)
    db = run_dir / "database.db"
    mode = {"auto": pycolmap.CameraMode.AUTO, "per_image": pycolmap.CameraMode.PER_IMAGE}[camera_mode]
    names = sorted(p.name for p in images_dir.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    seconds = {}
    with colmap_log(False):
        t = time.perf_counter()
        ext = pycolmap.FeatureExtractionOptions()
        ext.num_threads = threads
        known = [n for n in names if n in (intrinsics or {})]
        for name in known:
            reader = pycolmap.ImageReaderOptions()
            reader.camera_model, reader.camera_params = "PINHOLE", intrinsics[name]
            pycolmap.extract_features(
                db, images_dir, image_names=[name], camera_mode=pycolmap.CameraMode.PER_IMAGE,
                reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu,
            )  # fmt: skip
        rest = [n for n in names if n not in known]
        if rest:
            pycolmap.extract_features(
                db, images_dir, image_names=rest, camera_mode=mode, extraction_options=ext, device=pycolmap.Device.cpu
            )
        seconds["extract"] = time.perf_counter() - t
        t = time.perf_counter()
        mopt = pycolmap.FeatureMatchingOptions()
        mopt.num_threads = threads
        pycolmap.match_exhaustive(db, matching_options=mopt, device=pycolmap.Device.cpu)
        seconds["match"] = time.perf_counter() - t
    # the mapping step of localscale's pipeline, one run as COLMAP makes it
    overrides = FIXED_INTRINSICS if intrinsics else None
    mapped = run_mapping(
        db, images_dir, run_dir / "sparse", num_threads=threads, mapper=mapper, trials=1, overrides=overrides
    )
    seconds["map"] = mapped.seconds
    return {
        "stats": mapped.stats[0] if mapped.stats else None,
        "model": mapped.models[0] if mapped.models else None,
        "images": len(names),
        "seconds": {
            "extract": seconds["extract"],
            "match": seconds["match"],
            "verify": None,
            "map": seconds["map"],
            "total": sum(seconds.values()),
        },
    }


def run_ours(
    images_dir: Path,
    run_dir: Path,
    correction: str,
    camera_mode: str,
    threads: int,
    auto_graph: bool = True,
    mapper: str = "incremental",
    pairs: str = "exhaustive",
    ray_workers: int = 0,
    **options,
) -> dict:
    from ..engine import get_executor
    from ..sfm import read_models, reconstruct

    cluster = get_executor("ray", workers=ray_workers, threads_per_worker=1) if ray_workers else nullcontext()
    with cluster as executor:
        summary = reconstruct(
            images_dir,
            run_dir,
            matcher="aliked-lightglue",
            correction=correction,
            pairs=pairs,
            camera_mode=camera_mode,
            num_keypoints=2048,
            max_side=1024,
            num_threads=threads,
            overwrite=True,
            show_progress=False,
            auto_graph=auto_graph,
            mapper=mapper,
            engine=executor,
            **options,
        )
    models = read_models(run_dir / "sparse")
    s = summary["seconds"]
    stats = (
        None
        if not models
        else {
            k: summary[k]
            for k in ("registered", "points", "observations", "mean_track_length", "mean_reprojection_error")
        }
    )
    return {
        "stats": stats,
        "model": models[0] if models else None,
        "images": summary["images"],
        "seconds": {
            "extract": s["extract"],
            "match": s["pairs"] + s["match"],
            "verify": s["geometry"],
            "map": s["database"] + s["mapping"],
            "total": s["total"],
        },
        "pairs_verified": summary["pairs_verified"],
        "pairs": summary["pairs"],
        "added_keypoints": summary["matching"]["added_keypoints"],
        "feature_sets": summary["matching"]["feature_sets_computed"],
        "warnings": summary["warnings"],
    }


def closeup_check(model, closeups: dict) -> tuple:
    """``(close-ups registered, median centre error)``: a close-up's centre vs its source photo's,
    over the median distance of the registered cameras to their centroid (None when not measurable)."""
    if model is None or not closeups:
        return 0, None
    centres = {im.name: np.asarray(im.projection_center()) for im in model.images.values() if im.has_pose}
    registered = [n for n in closeups if n in centres]
    if len(centres) < 3:
        return len(registered), None
    c = np.array(list(centres.values()))
    scale = float(np.median(np.linalg.norm(c - c.mean(0), axis=1)))
    errs = [
        float(np.linalg.norm(centres[n] - centres[closeups[n]["source"]])) / scale
        for n in registered
        if closeups[n]["source"] in centres
    ]
    return len(registered), (float(np.median(errs)) if errs else None)


# ---------------------------------------------------------------- table


def markdown(rows: list) -> str:
    from ..core.tables import markdown_table

    return markdown_table(rows, COLUMNS)


# ---------------------------------------------------------------- a run
@dataclass
class ReconstructionRun:
    """Collections, versions and pipelines to reconstruct, and where (the script's flags)."""

    root: str = "/work/shared/data/collections"
    collections: List[str] = field(default_factory=lambda: ["kermit_bundler"])
    pipelines: List[str] = field(default_factory=lambda: list(PIPELINES))
    versions: List[str] = field(default_factory=lambda: ["plain", "closeups"])
    zoom: tuple = (2.5, 5.0)
    seed: int = 0
    threads: int = 1
    mapper: str = "incremental"
    #: the pairs our pipelines match: ``exhaustive`` (as COLMAP's SIFT pipeline here) or ``auto``
    #: (``reconstruct``'s default: retrieval beyond its size limit); rows of ``auto`` end in ``+pairs-auto``
    pairs: str = "exhaustive"
    #: our pipelines' extraction and matching on a local Ray cluster of this many one-thread
    #: workers (0: in this process); rows end in ``+rayN``
    ray_workers: int = 0
    intrinsics: Dict[str, dict] = field(default_factory=dict)  # collection -> read_intrinsics(...)
    output: str = "results/reconstruct_collections"
    overwrite: bool = False


def collection_version(cfg: ReconstructionRun, collection: str, version: str):
    """``(label, images folder, close-ups, camera mode)`` of a collection as it is or with close-ups."""
    root, out = Path(cfg.root), Path(cfg.output)
    if version == "plain":
        return collection, root / collection / "images", {}, "auto"
    images_dir = out / "_closeup_images" / collection
    closeups = make_closeups(root / collection / "images", images_dir, tuple(cfg.zoom), cfg.seed)
    return f"{collection}+closeups", images_dir, closeups, "per_image"


def run_pipeline(cfg: ReconstructionRun, method: str, images_dir: Path, run_dir: Path, camera_mode: str, known) -> dict:
    if method == "colmap-sift":
        return run_colmap_sift(images_dir, run_dir, camera_mode, cfg.threads, cfg.mapper, known)
    correction = "auto" if "-auto" in method else "none"
    options = PIPELINE_OPTIONS.get(method.rsplit("-", 1)[-1], {})
    return run_ours(
        images_dir,
        run_dir,
        correction,
        camera_mode,
        cfg.threads,
        not method.endswith("per-pair"),
        cfg.mapper,
        cfg.pairs,
        cfg.ray_workers,
        **options,
    )


def row_name(cfg: "ReconstructionRun", method: str) -> str:
    """A pipeline's row name: the method, then ``+global``, ``+pairs-auto``, ``+rayN`` where they apply
    (COLMAP's SIFT pipeline runs in this process on its exhaustive pairs whatever ``cfg`` says)."""
    name = method if cfg.mapper == "incremental" else f"{method}+{cfg.mapper}"
    if method != "colmap-sift":
        name += ("+pairs-auto" if cfg.pairs == "auto" else "") + (f"+ray{cfg.ray_workers}" if cfg.ray_workers else "")
    return name


def reference_of(cfg: "ReconstructionRun", collection: str, label: str):
    """``(what, {name: centre})``: the collection's reference model (:data:`REFERENCES`), else the
    model of its ``colmap-sift`` run on the photos alone (``OUT/<collection>/colmap-sift``, with
    ``--intrinsics`` where given), else on this version (``OUT/<label>/colmap-sift``; None when there is none), less its
    images with implausible intrinsics (COLMAP leaves them in, thousands of spreads away)."""
    from ..sfm.mapping import FOCAL_RATIO_RANGE, MAX_EXTRA_PARAM, read_models
    from ..sfm.placement import read_reference_centres

    if collection in REFERENCES:
        return "given", read_reference_centres(Path(cfg.root) / collection / REFERENCES[collection])
    pipe = "colmap-sift" if cfg.mapper == "incremental" else f"colmap-sift+{cfg.mapper}"
    plain = Path(cfg.output) / collection / pipe / "sparse"  # the photos alone (with --intrinsics: fixed)
    models = read_models(plain) or read_models(Path(cfg.output) / label / pipe / "sparse")
    if not models:
        return None, None
    pipe = f"{pipe} ({collection if read_models(plain) else label})"
    rec = models[0]
    bogus = lambda im: rec.cameras[im.camera_id].has_bogus_params(*FOCAL_RATIO_RANGE, MAX_EXTRA_PARAM)  # noqa: E731
    return pipe, {
        im.name: np.asarray(im.projection_center()) for im in rec.images.values() if im.has_pose and not bogus(im)
    }


def placed_right(model, images: list, reference, closeups: dict) -> dict:
    """:func:`localscale.sfm.placement.placement` of a model's registered images (``model``: a
    ``pycolmap.Reconstruction`` or None) against ``reference`` and the close-ups' sources."""
    from ..sfm.placement import placement

    centres = {} if model is None else {im.name: im.projection_center() for im in model.images.values() if im.has_pose}
    return placement(centres, images, reference, {k: v["source"] for k, v in closeups.items()})


def result_row(label: str, pipe: str, res: dict, closeups: dict, wall: float, camera_mode: str, threads: int) -> dict:
    """The results row of one pipeline run (``res``: :func:`run_colmap_sift` or :func:`run_ours`)."""
    st = res["stats"] or {
        "registered": 0,
        "points": 0,
        "observations": 0,
        "mean_track_length": None,
        "mean_reprojection_error": None,
    }
    n_close, centre_err = closeup_check(res["model"], closeups)
    return {
        "collection": label,
        "pipeline": pipe,
        "registered": f"{st['registered']}/{res['images']}",
        "closeups_registered": f"{n_close}/{len(closeups)}" if closeups else None,
        "closeup_centre_error": centre_err,
        "placed_right": (
            f"{res['placement']['placed_right']}/{res['placement']['checked']}"
            if res.get("placement") and res["placement"]["checked"]
            else None
        ),
        "reference": res.get("reference"),
        "placement": res.get("placement"),
        "points": st["points"],
        "observations": st["observations"],
        "mean_track_length": st["mean_track_length"],
        "mean_reprojection_error": st["mean_reprojection_error"],
        **{f"{k}_s": (None if v is None else round(v, 1)) for k, v in res["seconds"].items()},
        "wall_s": round(wall, 1),
        "camera_mode": camera_mode,
        "threads": threads,
        **{k: res[k] for k in ("pairs", "pairs_verified", "added_keypoints", "feature_sets", "warnings") if k in res},
    }


def save_rows(out: Path, rows: list) -> None:
    """``OUT/results.json``: the rows, the close-ups' descriptions and the commit, atomically."""
    metas = {k.stem: json.loads(k.read_text()) for k in sorted((out / "_closeup_images").glob("*.json"))}
    doc = {"rows": rows, "closeups": metas, "commit": git_commit()}
    write_text(out / "results.json", json.dumps(doc, indent=2) + "\n")


def run(cfg: ReconstructionRun) -> list:
    """Reconstruct every collection, version and pipeline of ``cfg`` not yet in ``OUT/results.json``
    (all with ``overwrite``); returns the rows, written to ``OUT/results.md`` as a table."""
    out = Path(cfg.output)
    out.mkdir(parents=True, exist_ok=True)
    results_path = out / "results.json"
    rows = json.loads(results_path.read_text())["rows"] if results_path.is_file() else []
    done = {(r["collection"], r["pipeline"]) for r in rows}
    for c in cfg.collections:
        for version in cfg.versions:
            label, images_dir, closeups, camera_mode = collection_version(cfg, c, version)
            for method in cfg.pipelines:
                pipe = row_name(cfg, method)
                if (label, pipe) in done and not cfg.overwrite:
                    print(f"{label} / {pipe}: in {results_path}, skipped", flush=True)
                    continue
                print(f"{label} / {pipe} ...", flush=True)
                t0, c0 = time.perf_counter(), time.process_time()
                known = cfg.intrinsics.get(c) if version == "plain" else None
                res = run_pipeline(cfg, method, images_dir, out / label / pipe, camera_mode, known)
                wall = time.perf_counter() - t0
                res["reference"], ref = reference_of(cfg, c, label)
                names = sorted(p.name for p in images_dir.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
                res["placement"] = placed_right(res["model"], names, ref, closeups)
                row = result_row(label, pipe, res, closeups, wall, camera_mode, cfg.threads)
                row["cpu_s"] = round(time.process_time() - c0, 1)
                rows = [r for r in rows if (r["collection"], r["pipeline"]) != (label, pipe)] + [row]
                save_rows(out, rows)
                print(f"{label} / {pipe}: {row['registered']} registered, {wall:.0f} s", flush=True)
    table = markdown(rows)
    write_text(out / "results.md", table + "\n")
    print(table)
    return rows
