"""Matching under strong zoom and quarter turns on held-out synthetic pairs.

Pairs are made from the held-out split of the training photos (never trained on, never the real
evaluation data): a wide view is rendered from a photo by a random homography that shrinks it by
a zoom of ``--zoom LO HI`` (log-uniform) at its centre, with a small rotation and perspective, its
empty regions filled from another photo, and turned by a random quarter turn; the photo itself is
the zoomed view. Either view is A, with equal odds.

A pair is *solved* by a matcher when the homography estimated from its matches (OpenCV
``USAC_MAGSAC``, 3 px) moves the co-visible pixels of A (4-px grid) less than 5 px on average
from where the true homography puts them (pixels of B). The table gives, per matcher and
correction method, the share solved, MMA@3 (share of matches within 3 px), the median transfer
error and the seconds per pair, overall and by zoom band and turn.

    OMP_NUM_THREADS=1 python eval/synthetic_matching.py --photos ../shared/data/train_images \\
        --pairs 40 --out results/synthetic_matching.json \\
        --run sift:none aliked-lightglue:none aliked-lightglue:auto
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from localscale import LocalScaleNet, ScaleNet
from localscale.core.errors import LocalScaleError
from localscale.core.outputs import write_text
from localscale.data import list_images, split_images
from localscale.evaluation.report import git_commit
from localscale.geometry import (
    HomographyConfig,
    covisible_mask,
    grid_points,
    project,
    sample_homography,
    turn_matrix,
    warp_image,
)
from localscale.io import load_image
from localscale.matching.auto import AutoConfig, auto_options
from localscale.matching.matcher import get_matcher
from localscale.matching.metrics import reprojection_errors
from localscale.matching.pipeline import match_pair
from localscale.matching.verification import estimate_homography

SOLVED_PX = 5.0


def zoom_pairs(
    photos: list, n: int, seed: int, zoom: tuple, turns: bool, rotation_deg: float = 10.0, perspective: float = 0.1
):
    """``(name, A, B, H_{A->B}, zoom, turn)`` for ``n`` pairs (module docstring)."""
    rng = np.random.default_rng(seed)
    img = functools.lru_cache(maxsize=None)(lambda i: load_image(photos[i]))

    for k in range(n):
        i, j = rng.choice(len(photos), 2, replace=False)
        a = img(i)
        z = math.exp(rng.uniform(math.log(zoom[0]), math.log(zoom[1])))
        # the wide view is rendered from the photo (anti-aliased), so the zoomed view keeps the
        # photo's own detail, as a real zoom does
        cfg = HomographyConfig(
            scale_range=(1 / z, 1 / z), rotation_deg=rotation_deg, skew=0.05, perspective=perspective, translation=0.3
        )
        H = sample_homography(rng, a.shape[:2], a.shape[:2], cfg)
        b, _ = warp_image(a, H, a.shape[:2], fill=img(j))
        turn = int(rng.integers(4)) if turns else 0
        if turn:
            H = turn_matrix(turn, b.shape) @ H
            b = np.ascontiguousarray(np.rot90(b, turn))
        s = 1 / z
        if rng.random() < 0.5:  # the zoomed view second
            a, b, H, s = b, a, np.linalg.inv(H), z
        yield f"zoom_{k:04d}", a, b, H / H[2, 2], s, turn


def transfer_error(H_est, H_true, shape_a, shape_b, stride: int = 4) -> float:
    """Mean distance (pixels of B) between where ``H_est`` and ``H_true`` put A's co-visible pixels."""
    if H_est is None or not np.isfinite(H_est).all():
        return math.inf
    mask = covisible_mask(H_true, shape_a, shape_b, stride)
    pts = grid_points(shape_a[0], shape_a[1], stride).reshape(-1, 2)[mask.ravel()]
    if not len(pts):
        return math.inf
    with np.errstate(all="ignore"):
        d = np.linalg.norm(project(H_est, pts) - project(H_true, pts), axis=1)
    d = d[np.isfinite(d)]
    return float(d.mean()) if len(d) else math.inf


def run_one(matcher, method: str, a, b, H, local, glob) -> dict:
    t0 = time.perf_counter()
    res = match_pair(a, b, method, None, local, glob, matcher)
    seconds = time.perf_counter() - t0
    ka, kb, m = res.keypoints_a, res.keypoints_b, res.matches
    err = reprojection_errors(ka, kb, m, H)
    H_est, _ = estimate_homography(ka[m[:, 0]], kb[m[:, 1]]) if len(m) >= 4 else (None, None)
    t_err = transfer_error(H_est, H, a.shape[:2], b.shape[:2])
    out = {
        "num_matches": int(len(m)),
        "mma3": float((err < 3).mean()) if len(m) else 0.0,
        "transfer_error": t_err,
        "solved": bool(t_err < SOLVED_PX),
        "seconds": round(seconds, 3),
    }
    if "auto" in res.meta:
        out["chosen"] = res.meta["auto"]["chosen"]
        out["runs"] = len(res.meta["auto"]["trials"])
    return out


def summarise(records: list, key) -> list:
    rows = []
    for name, method in dict.fromkeys((r["matcher"], r["method"]) for r in records):
        rs = [r for r in records if r["matcher"] == name and r["method"] == method and key(r)]
        if not rs:
            continue
        te = np.array([r["transfer_error"] for r in rs])
        rows.append(
            {
                "matcher": name,
                "method": method,
                "pairs": len(rs),
                "solved": float(np.mean([r["solved"] for r in rs])),
                "mma3": float(np.mean([r["mma3"] for r in rs])),
                "median_transfer_px": float(np.median(te)),
                "seconds": float(np.mean([r["seconds"] for r in rs])),
            }
        )
    return rows


SPLITS = {
    "all": lambda r: True,
    "zoom <5x": lambda r: abs(math.log(r["zoom"])) < math.log(5),
    "zoom >=5x": lambda r: abs(math.log(r["zoom"])) >= math.log(5),
    "upright": lambda r: r["turn"] == 0,
    "turned": lambda r: r["turn"] != 0,
}


def table(records: list) -> str:
    lines = [
        "| split | matcher | method | pairs | solved | MMA@3 | median transfer px | s/pair |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for split, key in SPLITS.items():
        for row in summarise(records, key):
            lines.append(
                f"| {split} | {row['matcher']} | {row['method']} | {row['pairs']} | {row['solved']:.0%} | "
                f"{row['mma3']:.3f} | {row['median_transfer_px']:.1f} | {row['seconds']:.2f} |"
            )
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--photos", required=True, help="training photo folder (its held-out split is used)")
    p.add_argument("--holdout-every", type=int, default=10, help="as in training (default: 10)")
    p.add_argument("--pairs", type=int, default=40)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--zoom", type=float, nargs=2, default=(3.0, 8.0), metavar=("LO", "HI"))
    p.add_argument("--no-turns", dest="turns", action="store_false", help="upright pairs only")
    p.add_argument(
        "--run",
        nargs="+",
        default=["sift:none", "aliked-lightglue:none", "aliked-lightglue:auto"],
        help="MATCHER:METHOD pairs (default: %(default)s)",
    )
    p.add_argument("--num-features", type=int, default=None, help="features per image of every matcher")
    p.add_argument(
        "--auto",
        nargs="+",
        default=[],
        metavar="FIELD=VALUE",
        help="auto settings (AutoConfig fields, e.g. accept_inliers=30 window_share=0 seed=none)",
    )
    p.add_argument("--rectify-min-side", type=int, default=None, help="MatchConfig.rectify_min_side")
    p.add_argument("--label", default="", help="suffix of the method names in the table (a variant's name)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", required=True, help="JSON file (a .md table is written beside it)")
    args = p.parse_args(argv)
    if not 1 <= args.zoom[0] <= args.zoom[1]:
        print(f"error: --zoom needs 1 <= LO <= HI, got {args.zoom[0]} {args.zoom[1]}", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    _, held = split_images(list_images(args.photos), args.holdout_every)
    try:
        auto = auto_options(args.auto)
    except LocalScaleError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    runs = []
    for spec in args.run:
        name, _, method = spec.partition(":")
        options = {}
        if args.num_features:
            options["num_features"] = args.num_features
        if args.rectify_min_side is not None:
            options["rectify_min_side"] = args.rectify_min_side
        if method == "auto" and auto:
            options["auto"] = AutoConfig(**auto)
        runs.append((name, (method or "none") + args.label, get_matcher(name, **options)))
    local, glob = LocalScaleNet.from_pretrained(), ScaleNet.from_pretrained()
    records = []
    pairs = list(zoom_pairs(held, args.pairs, args.seed, tuple(args.zoom), args.turns))
    for name, a, b, H, s, turn in tqdm(pairs, desc="pairs"):
        for mname, method, matcher in runs:
            matcher.clear_cache()
            rec = run_one(
                matcher, method[: len(method) - len(args.label)] if args.label else method, a, b, H, local, glob
            )
            records.append({"pair": name, "zoom": s, "turn": turn, "matcher": mname, "method": method, **rec})
    md = table(records)
    print(md)
    out = Path(args.out)
    summary = {split: summarise(records, key) for split, key in SPLITS.items()}
    write_text(
        out,
        json.dumps(
            {"args": vars(args), "summary": summary, "records": records, "commit": git_commit()},
            indent=1,
            default=float,
        )
        + "\n",
    )
    write_text(out.with_suffix(".md"), md + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
