"""Throughput of ``predict --pairs``-like work per engine: prints a markdown table and writes JSON.

The pairs are real: ``(1, k)`` and ``(k, 1)``, ``k = 2..6``, of the planar sequences in
``--data`` (``/work/shared/data/sequences``), interleaved over the sequences; the first ``N`` of
them for each ``N`` of ``--sizes`` (default 8 and 64). Each run does what ``predict --pairs`` does
per pair: features of every image once, the head per pair, and the driver writes the maps
(:func:`localscale.maps.files.write_scale_map`) into a fresh folder as each prediction arrives.

Rows:

* ``cli-loop``: the command's in-process loop today (:func:`localscale.cache.predict_pairs`,
  batched heads, LRU feature cache), one torch thread;
* ``local``: :func:`localscale.engine.predict_pairs_with` on the local engine, one torch thread;
* ``ray``: the same on a Ray cluster started for the run, ``--workers`` x ``--threads`` CPUs.

Every run starts from nothing (a new executor: the cluster and its workers start inside the timed
run); ``startup_s`` is that start (cluster + workers' models). ``marginal pairs/s`` is
``(N_max - N_min) / (t(N_max) - t(N_min))``: the rate once the start is paid. Run it with
``OMP_NUM_THREADS=1`` so that every process uses one thread::

    OMP_NUM_THREADS=1 python eval/engine_benchmark.py --json results/engine_benchmark.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

from localscale.evaluation.report import git_commit


def real_pairs(root: Path) -> list[tuple[Path, Path]]:
    seqs = sorted(d for d in root.iterdir() if (d / "1.png").is_file())
    per_seq = [
        [(d / "1.png", d / f"{k}.png") for k in range(2, 7)] + [(d / f"{k}.png", d / "1.png") for k in range(2, 7)]
        for d in seqs
    ]
    out = []
    for j in range(max(len(p) for p in per_seq)):  # interleaved: every run sees several sequences
        out += [p[j] for p in per_seq if j < len(p)]
    return out


def run_cli_loop(pairs, out: Path) -> dict:
    import torch

    from localscale import LocalScaleNet
    from localscale.cache import FeatureCache, predict_pairs
    from localscale.maps.files import write_scale_map

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    model = LocalScaleNet.from_pretrained()
    startup = time.perf_counter() - t0
    cache = FeatureCache(model)
    for i, (_, pred) in enumerate(predict_pairs(model, pairs, cache)):
        write_scale_map(pred, out, f"{i:05d}")
    return {"seconds": time.perf_counter() - t0, "startup_s": startup, "workers": 1, "failed": 0}


def run_engine(pairs, out: Path, engine: str, workers: int, threads: int) -> dict:
    from localscale.engine import PairStats, get_executor, predict_pairs_with
    from localscale.maps.files import write_scale_map

    t0 = time.perf_counter()
    stats = PairStats()
    with get_executor(engine, workers=workers if engine == "ray" else None, threads_per_worker=threads) as ex:
        for i, pred in predict_pairs_with(ex, pairs, stats=stats):
            if isinstance(pred, Exception):
                raise SystemExit(f"error: pair {i}: {pred}")
            write_scale_map(pred, out, f"{i:05d}")
    seconds = time.perf_counter() - t0  # the cluster's stop included
    return {
        "seconds": seconds,
        "startup_s": stats.startup_seconds,
        "workers": stats.workers,
        "failed": stats.failed,
        "retried": stats.retried,
        "summary": stats.summary(),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=Path("/work/shared/data/sequences"))
    ap.add_argument("--sizes", type=int, nargs=2, default=(8, 64), metavar=("SMALL", "LARGE"))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1, help="torch threads per worker (and of the local engine)")
    ap.add_argument("--rows", nargs="+", default=["cli-loop", "local", "ray"], choices=["cli-loop", "local", "ray"])
    ap.add_argument("--json", type=Path, default=None, help="write the results here")
    args = ap.parse_args(argv)
    load = list(os.getloadavg())
    pairs = real_pairs(args.data)
    if len(pairs) < max(args.sizes):
        raise SystemExit(f"error: {args.data} gives {len(pairs)} pairs, fewer than {max(args.sizes)}")
    results = []
    scratch = Path(tempfile.mkdtemp(prefix="engine-bench-"))
    try:
        for row in args.rows:
            runs = {}
            for n in args.sizes:
                out = scratch / f"{row}-{n}"
                if row == "cli-loop":
                    runs[n] = run_cli_loop(pairs[:n], out)
                else:
                    runs[n] = run_engine(pairs[:n], out, row, args.workers, args.threads)
                assert len(list(out.glob("*_scale.npy"))) == n, f"{row}: not every pair was written"
                print(f"{row} {n} pairs: {runs[n]['seconds']:.1f} s", file=sys.stderr)
                shutil.rmtree(out)
            small, large = args.sizes
            marginal = (large - small) / max(1e-9, runs[large]["seconds"] - runs[small]["seconds"])
            results.append(
                {
                    "engine": row,
                    "workers": runs[large]["workers"],
                    "threads_per_worker": args.threads if row != "cli-loop" else 1,
                    "startup_s": round(runs[large]["startup_s"], 2),
                    "seconds": {str(n): round(r["seconds"], 2) for n, r in runs.items()},
                    "pairs_per_s": {str(n): round(n / r["seconds"], 2) for n, r in runs.items()},
                    "marginal_pairs_per_s": round(marginal, 2),
                }
            )
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    small, large = args.sizes
    lines = [
        f"| engine | workers x threads | startup s | {small} pairs s | {large} pairs s | "
        f"{large} pairs/s overall | marginal pairs/s |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results:
        lines.append(
            f"| {r['engine']} | {r['workers']} x {r['threads_per_worker']} | {r['startup_s']:.1f} | "
            f"{r['seconds'][str(small)]:.1f} | {r['seconds'][str(large)]:.1f} | "
            f"{r['pairs_per_s'][str(large)]:.2f} | {r['marginal_pairs_per_s']:.2f} |"
        )
    print("\n".join(lines))
    if args.json:
        from localscale.core.outputs import write_text

        args.json.parent.mkdir(parents=True, exist_ok=True)
        doc = {
            "command": " ".join(["python"] + sys.argv),
            "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
            "cpus": os.cpu_count(),
            "load_average_at_start": load,
            "python": platform.python_version(),
            "data": str(args.data),
            "results": results,
            "commit": git_commit(),
        }
        write_text(args.json, json.dumps(doc, indent=1) + "\n")
        print(f"wrote {args.json}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
