"""Mapper options against placed-right: map the databases of ``eval/reconstruct_collections.py``'s runs
again under each variant and count the images placed right (:mod:`localscale.sfm.placement`).

    OMP_NUM_THREADS=1 python eval/placement_variants.py --runs results/reconstruct_collections \\
        --collections kermit_bundler cyprus_dim temple_sparse_ring_middlebury -o results/placement_variants

Variants (``--variants``), each mapped as ``reconstruct`` maps (up to 3 seeds while images are left out):

* ``fixed-k``: the camera per image keeps its distortion (``PER_IMAGE_CAMERA_OPTIONS``), no check;
* ``refine-k``: pycolmap's defaults (distortion refined all along), no check;
* ``fixed-k+check``, ``refine-k+check``: then the registration check (:mod:`localscale.sfm.registration_check`);
* ``fixed-k+closeup-prior+check``, ``refine-k+closeup-prior+check``: each close-up's camera in the database
  made SIMPLE_PINHOLE (no distortion to refine) at zoom x its photo's focal length first
  (:func:`localscale.sfm.registration_check.closeup_focal_priors`, as ``reconstruct`` does);
* ``fixed-k+final-k1+check``: the distortion fixed while mapping, then a final bundle adjustment refining the
  photos' focal lengths and distortion, close-ups' cameras kept (:func:`localscale.sfm.refine.refine_distortion`),
  then the check.

The reference: :func:`localscale.evaluation.reconstruction.reference_of` (a collection's model, else colmap-sift's).
Rows go to ``OUT.json`` and ``OUT.md``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

from localscale.core.tables import markdown_table
from localscale.evaluation.reconstruction import ReconstructionRun, placed_right, reference_of
from localscale.sfm.mapping import camera_ids

VARIANTS = (
    "fixed-k",
    "refine-k",
    "fixed-k+check",
    "refine-k+check",
    "fixed-k+final-k1+check",
    "fixed-k+closeup-prior+check",
    "refine-k+closeup-prior+check",
)


def closeups_of_run(run_dir: Path) -> dict:
    """``{close-up: (photo, zoom)}`` found in a run's matches and geometries."""
    from localscale.sfm.registration_check import closeups_from_files

    return closeups_from_files(run_dir / "matches.h5", run_dir / "geometries.h5")


def map_variant(run_dir: Path, images_dir: Path, variant: str, threads: int):
    """The largest model of ``run_dir/database.db`` mapped under ``variant``, and what the check did."""
    from localscale.sfm.database import read_database
    from localscale.sfm.mapper_options import PER_IMAGE_CAMERA_OPTIONS
    from localscale.sfm.mapping import colmap_log, run_mapping
    from localscale.sfm.refine import refine_distortion
    from localscale.sfm.registration_check import check_registrations

    closeups = closeups_of_run(run_dir)
    db = read_database(run_dir / "database.db")
    guessed = {
        db_name: float(db.cameras[cid].params[0]) for db_name, cid in camera_ids(run_dir / "database.db").items()
    }

    def check(rec):
        with colmap_log(False):
            if "final-k1" in variant:
                refine_distortion(rec, keep=set(closeups), num_threads=threads)
        return check_registrations(rec, guessed, closeups) if "check" in variant else []

    overrides = dict(PER_IMAGE_CAMERA_OPTIONS) if variant.startswith("fixed-k") else {}
    with tempfile.TemporaryDirectory() as tmp:
        shutil.copy(run_dir / "database.db", Path(tmp) / "database.db")
        if "closeup-prior" in variant:
            _set_closeup_cameras(Path(tmp) / "database.db", closeups)
        res = run_mapping(
            Path(tmp) / "database.db",
            images_dir,
            Path(tmp) / "sparse",
            num_threads=threads,
            overrides=overrides,
            check=check,
        )
    return res


def _set_closeup_cameras(database_path, closeups: dict) -> None:
    """Each close-up's own camera: SIMPLE_PINHOLE at zoom x its photo's initial focal length."""
    import pycolmap

    of = camera_ids(database_path)
    d = pycolmap.Database.open(str(database_path))
    try:
        cams = {c.camera_id: c for c in d.read_all_cameras()}
        for name, (source, zoom) in closeups.items():
            cam, photo = cams[of[name]], cams[of[source]]
            new = pycolmap.Camera(
                model="SIMPLE_PINHOLE", width=cam.width, height=cam.height,
                params=[zoom * photo.params[0], cam.params[1], cam.params[2]], camera_id=cam.camera_id,
            )  # fmt: skip
            d.update_camera(new)
    finally:
        d.close()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", required=True, help="the output folder of eval/reconstruct_collections.py")
    p.add_argument("--root", default="/work/shared/data/collections")
    p.add_argument("--collections", nargs="+", required=True)
    p.add_argument("--pipeline", default="aliked-lg-auto")
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("-o", "--output", required=True, help="OUT.json and OUT.md are written")
    a = p.parse_args(argv)
    runs = Path(a.runs)
    cfg = ReconstructionRun(root=a.root, output=str(runs))
    rows = []
    for c in a.collections:
        label = f"{c}+closeups"
        meta = json.loads((runs / "_closeup_images" / f"{c}.json").read_text())
        images_dir = runs / "_closeup_images" / c
        names = sorted(q.name for q in images_dir.iterdir() if q.suffix.lower() in (".jpg", ".jpeg", ".png"))
        what, ref = reference_of(cfg, c, label)
        for variant in a.variants:
            t0 = time.perf_counter()
            res = map_variant(runs / label / a.pipeline, images_dir, variant, a.threads)
            pl = placed_right(res.models[0] if res.models else None, names, ref, meta)
            st = res.stats[0] if res.stats else {"registered": 0, "mean_reprojection_error": None}
            rows.append(
                {
                    "collection": label, "variant": variant, "registered": f"{st['registered']}/{len(names)}",
                    "placed_right": f"{pl['placed_right']}/{pl['checked']}",
                    "photos_right": f"{pl['photos']['right']}/{pl['photos']['checked']}",
                    "closeups_right": f"{pl['closeups']['right']}/{pl['closeups']['checked']}",
                    "wrong": ", ".join(pl["wrong"]), "checked": "; ".join(f"{r['image']} {r['action']}" for r in res.checked),
                    "reprojection_error": st["mean_reprojection_error"], "reference": what, "seconds": round(time.perf_counter() - t0, 1),
                    "placement": pl,
                }
            )  # fmt: skip
            print(
                f"{label} {variant}: {rows[-1]['registered']} registered, {rows[-1]['placed_right']} right", flush=True
            )
    out = Path(a.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(rows, indent=2) + "\n")
    cols = [
        (k, k.replace("_", " "))
        for k in (
            "collection",
            "variant",
            "registered",
            "placed_right",
            "photos_right",
            "closeups_right",
            "reprojection_error",
            "wrong",
            "checked",
        )
    ]
    table = markdown_table(rows, cols)
    out.with_suffix(".md").write_text(table + "\n")
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
