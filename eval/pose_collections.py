"""Relative pose on real photo collections: plain pairs and zoom + quarter-turn pairs.

The protocol, the collections and the methods: :mod:`localscale.evaluation.pose` and
:mod:`localscale.evaluation.pose_data`. Collections live in ``--root`` (default
``/work/shared/data/collections``); ``--gt-model NAME=DIR`` gives any other collection a COLMAP
model as its pseudo ground truth (e.g. ``eval/reconstruct_collections.py``'s
``OUT/NAME/colmap-sift/sparse/0``).

Per-pair results go to ``<out>.pairs.jsonl`` (or ``--cache``) as they are computed; a rerun skips the
pairs found there (same collection, pair, kind, method and options). The table (markdown) is printed
and the summary written atomically to ``--out``, with the command and the commit.

    OMP_NUM_THREADS=1 python eval/pose_collections.py --methods opencv-sift aliked-lightglue:none \\
        aliked-lightglue:auto --pairs 55 --out results/pose_collections.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from localscale.evaluation.pose import PoseRun, run
from localscale.evaluation.pose_data import COLLECTIONS
from localscale.evaluation.report import one_line_errors
from localscale.geometry.two_view import TwoViewConfig
from localscale.matching.auto import auto_options


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--root", default="/work/shared/data/collections")
    p.add_argument(
        "--collections", nargs="+", default=list(COLLECTIONS), help=f"{', '.join(COLLECTIONS)}, or one of --gt-model"
    )
    p.add_argument(
        "--gt-model",
        nargs="+",
        default=[],
        metavar="NAME=DIR",
        help="a COLMAP model (binary or text) of collection NAME as its pseudo ground truth",
    )
    p.add_argument("--methods", nargs="+", default=["opencv-sift", "aliked-lightglue:none", "aliked-lightglue:auto"])
    p.add_argument("--pairs", type=int, default=55, help="plain pairs per collection (each also gives a zoom pair)")
    p.add_argument("--kinds", nargs="+", default=["plain", "zoom"], choices=("plain", "zoom"))
    p.add_argument("--max-side", type=int, default=1024)
    p.add_argument("--zoom", type=float, nargs=2, default=(2.5, 6.0), metavar=("MIN", "MAX"))
    p.add_argument("--min-covisible", type=int, default=30, help="3D points two images must share")
    p.add_argument("--min-share", type=float, default=0.1, help="... as a share of the smaller image's points")
    p.add_argument("--max-axis-angle", type=float, default=60.0, help="degrees between the optical axes")
    p.add_argument("--max-error", type=float, default=TwoViewConfig.max_error, help="MAGSAC threshold, pixels")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="results/pose_collections.json")
    p.add_argument("--num-features", type=int, default=None, help="keypoints of the library's matchers (their default)")
    p.add_argument(
        "--lightglue-precision",
        default=None,
        choices=("auto", "fp32", "bf16", "int8"),
        help="LightGlue's precision in the library's matchers (default: theirs, fp32 for two views)",
    )
    p.add_argument(
        "--lightglue-confidence",
        type=float,
        nargs=2,
        default=None,
        metavar=("DEPTH", "WIDTH"),
        help="LightGlue's adaptive depth and width confidences (default: kornia's, 0.95 0.99 for ALIKED)",
    )
    p.add_argument("--auto", nargs="+", default=[], metavar="FIELD=VALUE", help="AutoConfig fields of the auto methods")
    p.add_argument("--cache", default=None, help="per-pair results (JSON lines; default: OUT with .pairs.jsonl)")
    p.add_argument("--local-weights", default=None, help="Local-ScaleNet weights of the corrections (default: bundled)")
    return p


def main(argv=None) -> int:
    p = parser()
    a = p.parse_args(argv)
    if a.pairs < 1 or not 1 <= a.zoom[0] <= a.zoom[1]:
        p.error("--pairs must be >= 1 and 1 <= --zoom MIN <= MAX")
    if any("=" not in g for g in a.gt_model):
        p.error("--gt-model takes NAME=DIR")
    gt_models = dict(g.split("=", 1) for g in a.gt_model)
    unknown = [c for c in a.collections if c not in COLLECTIONS and c not in gt_models]
    if unknown:
        p.error(f"no reader for {', '.join(unknown)}: give its --gt-model NAME=DIR (known: {', '.join(COLLECTIONS)})")
    auto = auto_options(a.auto)
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass
    options = {k: v for k, v in vars(a).items() if k not in ("gt_model", "auto")}
    cfg = PoseRun(**options, gt_models=gt_models, auto=auto)
    run(cfg, " ".join([Path(sys.argv[0]).name] + (argv if argv is not None else sys.argv[1:])))
    return 0


def cli(argv=None) -> int:
    """:func:`main` with bad input reported as one ``error:`` line and exit code 2."""
    return one_line_errors(main, argv)


if __name__ == "__main__":
    sys.exit(cli())
