"""3D reconstruction of the photo collections: pycolmap's SIFT pipeline vs ALIKED + LightGlue, without
and with ``auto``, on each collection as it is and with close-ups added.

    OMP_NUM_THREADS=1 python eval/reconstruct_collections.py --collections kermit_bundler cyprus_dim \\
        -o results/reconstruct_collections

The close-ups, the pipelines, the cameras and the outputs: :mod:`localscale.evaluation.reconstruction`.
Every run goes to ``OUT/<collection>/<pipeline>/``; its row is added to ``OUT/results.json`` (with the
commit, written atomically after each run); a rerun skips the rows already there (``--overwrite``
redoes them). The markdown table is printed and written to ``OUT/results.md``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from localscale.evaluation.reconstruction import PIPELINES, ReconstructionRun, read_intrinsics, run


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--root", default="/work/shared/data/collections", help="folder of the collections")
    p.add_argument("--collections", nargs="+", default=["kermit_bundler"])
    p.add_argument("--pipelines", nargs="+", default=list(PIPELINES), choices=PIPELINES)
    p.add_argument("--versions", nargs="+", default=["plain", "closeups"], choices=("plain", "closeups"))
    p.add_argument("--zoom", type=float, nargs=2, default=(2.5, 5.0), metavar=("MIN", "MAX"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--threads",
        type=int,
        default=int(os.environ.get("OMP_NUM_THREADS", "1")),
        help="COLMAP threads (torch follows OMP_NUM_THREADS)",
    )
    p.add_argument(
        "--mapper",
        default="incremental",
        choices=("incremental", "global"),
        help="COLMAP's mapper for every pipeline (rows of the global one are named PIPELINE+global)",
    )
    p.add_argument(
        "--intrinsics",
        nargs="+",
        default=[],
        metavar="NAME=FILE",
        help="known PINHOLE intrinsics of collection NAME (lines 'name w h fx fy cx cy'), kept fixed by "
        "colmap-sift's mapper (a pseudo ground truth of a collection that has intrinsics only)",
    )
    p.add_argument(
        "--pairs",
        default="exhaustive",
        choices=("exhaustive", "auto"),
        help="pairs our pipelines match (auto: reconstruct's default; rows end in +pairs-auto)",
    )
    p.add_argument(
        "--ray-workers",
        type=int,
        default=0,
        help="run our pipelines' extraction and matching on a local Ray cluster of N one-thread workers "
        "(rows end in +rayN; pip install 'localscale[ray]')",
    )
    p.add_argument("-o", "--output", default="results/reconstruct_collections")
    p.add_argument("--overwrite", action="store_true", help="redo rows already in OUT/results.json")
    return p


def main(argv=None) -> int:
    p = parser()
    a = p.parse_args(argv)
    if not 1 <= a.zoom[0] <= a.zoom[1]:
        p.error("--zoom: 1 <= MIN <= MAX")
    if any("=" not in item for item in a.intrinsics):
        p.error("--intrinsics takes NAME=FILE")
    try:
        intrinsics = {k: read_intrinsics(Path(v)) for k, v in (item.split("=", 1) for item in a.intrinsics)}
    except (OSError, ValueError) as e:
        p.error(f"--intrinsics: {e}")
    if a.ray_workers < 0:
        p.error("--ray-workers must be >= 0")
    root = Path(a.root)
    for c in a.collections:
        if not (root / c / "images").is_dir():
            p.error(f"no collection {c} in {root} (no {root / c / 'images'})")
    import torch

    torch.set_num_threads(max(1, a.threads))
    t_script = time.perf_counter()
    run(ReconstructionRun(**{**vars(a), "intrinsics": intrinsics}))
    print(f"script wall time {time.perf_counter() - t_script:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
