"""Throughput of ``reconstruct``'s extraction and matching stages per engine: a markdown table and JSON.

For one collection (``--images``) and each engine (``local``: this process, one torch thread;
``ray``: a local Ray cluster of ``--workers`` x ``--threads`` CPUs, started inside the timed run),
each run starts from an empty folder: the executor starts (``startup_s``: the cluster and its
workers), every image's features are extracted (:func:`localscale.sfm.extract_features`), then the
first ``N`` pairs of the exhaustive list are matched (:func:`localscale.sfm.match_pairs`, with
``--correction``), for each ``N`` of ``--sizes``. ``marginal pairs/s`` is
``(N_max - N_min) / (t(N_max) - t(N_min))`` of the matching stage: its rate once the start is paid.
The outputs of the two engines are compared (``matches.h5`` identical). Run it with
``OMP_NUM_THREADS=1``::

    OMP_NUM_THREADS=1 python eval/engine_reconstruct_benchmark.py \
        --images ../shared/data/collections/kermit_bundler/images --json results/engine/reconstruct_benchmark.json
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

from localscale.evaluation.report import git_commit


def run(images_dir: Path, out: Path, engine: str, workers: int, threads: int, n_pairs: int, correction: str) -> dict:
    import torch

    from localscale.engine import get_executor
    from localscale.sfm import extract_features, find_images, match_pairs, pairs_exhaustive
    from localscale.sfm.extract import FeatureConf

    torch.set_num_threads(1)
    images = find_images(images_dir)
    pairs = pairs_exhaustive([im.name for im in images])[:n_pairs]
    conf = FeatureConf("aliked-lightglue", 2048, 1024)
    t0 = time.perf_counter()
    ex = get_executor(engine, workers=workers if engine == "ray" else None, threads_per_worker=threads)
    try:
        if engine == "ray":
            ex.start()
        startup = time.perf_counter() - t0
        t1 = time.perf_counter()
        extract_features(images, out / "features.h5", conf, show_progress=False, executor=ex)
        t2 = time.perf_counter()
        match_pairs(
            images,
            pairs,
            out / "features.h5",
            out / "matches.h5",
            out / "keypoints.h5",
            conf,
            correction,
            show_progress=False,
            executor=ex,
        )
        t3 = time.perf_counter()
    finally:
        ex.close()
    return {
        "engine": engine,
        "workers": workers if engine == "ray" else 1,
        "pairs": len(pairs),
        "images": len(images),
        "startup_s": round(startup, 2),
        "extract_s": round(t2 - t1, 2),
        "match_s": round(t3 - t2, 2),
    }


def same_matches(a: Path, b: Path) -> bool:
    import h5py
    import numpy as np

    with h5py.File(a) as fa, h5py.File(b) as fb:
        keys = []
        fa.visit(lambda k: keys.append(k) if isinstance(fa[k], h5py.Dataset) else None)
        return all(k in fb and np.array_equal(fa[k][()], fb[k][()]) for k in keys) and bool(keys)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--images", type=Path, required=True)
    p.add_argument("--sizes", type=int, nargs=2, default=[8, 36])
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--correction", default="none")
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    rows, tmp = [], Path(tempfile.mkdtemp(prefix="recon_bench_"))
    try:
        for n in args.sizes:
            for engine in ("local", "ray"):
                out = tmp / f"{engine}_{n}"
                out.mkdir()
                rows.append(run(args.images, out, engine, args.workers, args.threads, n, args.correction))
                print(json.dumps(rows[-1]), flush=True)
            rows[-1]["matches_equal_local"] = same_matches(
                tmp / f"local_{n}" / "matches.h5", tmp / f"ray_{n}" / "matches.h5"
            )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    lo, hi = min(args.sizes), max(args.sizes)
    summary = {}
    for engine in ("local", "ray"):
        r = {x["pairs"]: x for x in rows if x["engine"] == engine}
        summary[engine] = {
            "marginal_pairs_per_s": (hi - lo) / max(1e-9, r[hi]["match_s"] - r[lo]["match_s"]),
            "extract_images_per_s": r[hi]["images"] / r[hi]["extract_s"],
            "startup_s": r[hi]["startup_s"],
        }
    print(
        f"\n| engine | workers x threads | startup s | extraction images/s | matching marginal pairs/s ({lo} -> {hi} pairs) |"
    )
    print("|---|---|---|---|---|")
    for engine, s in summary.items():
        wt = f"{args.workers} x {args.threads}" if engine == "ray" else "1 x 1"
        print(
            f"| {engine} | {wt} | {s['startup_s']:.1f} | {s['extract_images_per_s']:.2f} | {s['marginal_pairs_per_s']:.2f} |"
        )
    ratio = summary["ray"]["marginal_pairs_per_s"] / summary["local"]["marginal_pairs_per_s"]
    print(
        f"\nray / local matching: {ratio:.2f}x; matches identical: {all(r.get('matches_equal_local', True) for r in rows)}"
    )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        doc = {
            "rows": rows,
            "summary": summary,
            "ratio": ratio,
            "correction": args.correction,
            "machine": {"cpus": __import__("os").cpu_count(), "platform": platform.platform()},
            "commit": git_commit(),
        }
        args.json.write_text(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
