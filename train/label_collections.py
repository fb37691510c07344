"""Labelled real training pairs from the shared photo collections.

Each collection is reconstructed with pycolmap's own SIFT pipeline (extraction, exhaustive
matching, incremental mapping, one camera per image); the largest model is written to
``OUT/<collection>/sparse`` (binary). A collection whose model exists is skipped, so the
script resumes. Then every pair of images sharing at least ``--min-points`` 3D points is written
with both images' observations of them to ``OUT/<collection>/pairs.npz``
(:func:`localscale.training.real_pairs.covisible_pairs`); the labels need only these 2D
observations, so the model's own scale and frame do not matter.

    OMP_NUM_THREADS=1 python train/label_collections.py ../shared/data/collections -o runs/real_models
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path


def reconstruct(images_dir: Path, out: Path, threads: int) -> dict:
    import pycolmap

    from localscale.sfm.mapping import colmap_log, model_stats

    work = out.with_name(out.name + ".partial")
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    db = work / "database.db"
    names = sorted(p.name for p in images_dir.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    t0 = time.perf_counter()
    with colmap_log(False):
        ext = pycolmap.FeatureExtractionOptions()
        ext.num_threads = threads
        pycolmap.extract_features(
            db,
            images_dir,
            image_names=names,
            camera_mode=pycolmap.CameraMode.PER_IMAGE,
            extraction_options=ext,
            device=pycolmap.Device.cpu,
        )
        mopt = pycolmap.FeatureMatchingOptions()
        mopt.num_threads = threads
        pycolmap.match_exhaustive(db, matching_options=mopt, device=pycolmap.Device.cpu)
        opts = pycolmap.IncrementalPipelineOptions()
        opts.num_threads = threads
        opts.random_seed = 0
        models = pycolmap.incremental_mapping(db, images_dir, work / "models", opts)
    if not models:
        raise RuntimeError(f"{images_dir}: COLMAP registered no model")
    best = max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
    (work / "sparse").mkdir()
    best.write(work / "sparse")
    stats = dict(model_stats(best), images=len(names), seconds=round(time.perf_counter() - t0, 1))
    (work / "sparse" / "summary.json").write_text(json.dumps(stats, indent=1))
    shutil.rmtree(work / "models")
    db.unlink()
    work.rename(out)
    return stats


def write_pairs(out: Path, images_dir: Path, name: str, min_points: int) -> None:
    import pycolmap

    from localscale.training.real_pairs import covisible_pairs, save_covisible_pairs

    pairs = covisible_pairs(pycolmap.Reconstruction(out / "sparse"), images_dir.resolve(), min_points, name)
    save_covisible_pairs(out / "pairs.npz", pairs)
    points = sum(len(p.xy_a) for p in pairs)
    print(f"{name}: {len(pairs)} pairs with >= {min_points} co-visible points ({points} observations)", flush=True)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("root", type=Path, help="folder of collections, each with an images/ folder")
    p.add_argument("-o", "--out", type=Path, default=Path("runs/real_models"))
    p.add_argument("--collections", nargs="*", default=None, help="default: every folder under ROOT with images/")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--min-points", type=int, default=50, help="co-visible 3D points a pair needs")
    args = p.parse_args(argv)
    names = args.collections or sorted(d.name for d in args.root.iterdir() if (d / "images").is_dir())
    for name in names:
        out = args.out / name
        if (out / "sparse" / "summary.json").exists():
            print(f"{name}: model exists", flush=True)
        else:
            stats = reconstruct(args.root / name / "images", out, args.threads)
            print(f"{name}: {json.dumps(stats)}", flush=True)
        write_pairs(out, args.root / name / "images", name, args.min_points)
    return 0


if __name__ == "__main__":
    sys.exit(main())
