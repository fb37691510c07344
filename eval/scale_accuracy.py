"""Accuracy of the scale models on held-out synthetic pairs and on real sequences.

Local mode (Local-ScaleNet): per-pixel scale-ratio error ``r = max(s,g)/min(s,g)`` over the
co-visible pixels of A (original resolution, sampled on a 4-px grid), against

* ``const-1``: the constant map 1 (no correction),
* ``oracle const``: the best single global scale of each pair (median of the GT log-scale,
  which minimises the mean |log error|): what a perfect *global* ScaleNet could do.

``local+planar`` is the same prediction with the planar prior (``predict(..., planar=True)``,
valid for planar scenes only, which all pairs here are). Tables are split by scale band (|log2 s| < 1, 1..2, > 2) and by perspective strength of
the pair (std of log2 s over the co-visible region: low < 0.15 <= medium < 0.35 <= high).

Real mode also scores ``refined``: the local maps (gated) for a first HardNet matching pass, the
matches verified with a MAGSAC homography, the local map refined by the verified geometry and a
second matching pass (:func:`localscale.matching.match_refined_pair`; when the first pass is not
verified, OpenCV SIFT matches are verified instead and their geometry refines the map); where
verification fails the refined map is the local map. With ``--search`` it also scores the
window search (:func:`localscale.search.search_scale_map`) and ScaleNet run on the windows the
search chose, and (unless ``--no-refined``) the refinement seeded by the searched maps of both
directions instead of the one-pass maps.

Global mode (ScaleNet): per-pair r of the consistency-checked soft scale (``ScaleNet.predict``'s,
with quarter turns when the upright prediction is unreliable, and the upright one alone), the A->B soft
scale alone, the D-ScaleNet hard read-out, the constant 1, a random bin, and the median of
Local-ScaleNet's map as a global estimate; plus timing with and without cached features.
The ground-truth global scale of a pair is exp of the mean log of the analytic map over the
co-visible region (the paper's average in log space).

    python eval/scale_accuracy.py --mode local --photos ../shared/data/train_images \
        --sequences ../shared/data/sequences --out results/scale_accuracy_local.json
"""

from __future__ import annotations

import argparse
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
from localscale.data import list_images, split_images
from localscale.evaluation.report import git_commit
from localscale.evaluation.scale_maps import (
    STRIDE,
    local_table,
    pixel_errors,
    sequence_pairs,
    synthetic_pairs,
)
from localscale.evaluation.scale_real import TITLES, columns, evaluate_real
from localscale.geometry import (
    HomographyConfig,
)
from localscale.geometry.planar import planarize


def print_local_table(title: str, table: dict) -> None:
    print(f"\n### {title}\n")
    print(
        "| subset | pairs | local mean r | local median r | local+planar mean / median r | const-1 mean r "
        "| oracle-const mean r | local < oracle (pairs) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for k, v in table.items():
        if not v.get("pairs"):
            print(f"| {k} | 0 | | | | | | |")
            continue
        pl = v.get("local+planar")
        pl = f"{pl['mean_r']:.3f} / {pl['median_r']:.3f}" if pl else "-"
        print(
            f"| {k} | {v['pairs']} | {v['local']['mean_r']:.3f} | {v['local']['median_r']:.3f} | {pl} | "
            f"{v['const-1']['mean_r']:.3f} | {v['oracle const']['mean_r']:.3f} | {100 * v['local_beats_oracle_pairs']:.0f}% |"
        )


def run_local(args) -> dict:
    model = LocalScaleNet.from_pretrained(args.model)
    torch.set_num_threads(args.threads) if args.threads else None
    results = {"model": str(args.model or "bundled"), "stride_px": STRIDE}
    if args.photos:
        _, held = split_images(list_images(args.photos))
        cfg = HomographyConfig(scale_range=(0.16, 6.0), perspective=args.perspective)
        rows = []
        for _name, a, b, H in tqdm(
            list(synthetic_pairs(held, args.pairs, args.seed, cfg, args.crop)), desc="synthetic"
        ):
            pred = model.predict(a, b)
            rows.append(pixel_errors(pred.scale, H, b.shape[:2], planarize(pred.scale, pred.confidence)))
        results["synthetic"] = local_table(rows)
        results["synthetic_setup"] = {
            "photos": "held-out split (every 10th sorted file) of " + str(args.photos),
            "pairs": len(rows),
            "seed": args.seed,
            "perspective": args.perspective,
            "crop": args.crop,
            "scale_range": [0.16, 6.0],
        }
        print_local_table(f"held-out synthetic pairs ({len(rows)})", results["synthetic"])
    if args.sequences:
        rows, names = [], []
        for name, a, b, H in tqdm(list(sequence_pairs(Path(args.sequences))), desc="sequences"):
            pred = model.predict(a, b)
            rows.append(pixel_errors(pred.scale, H, b.shape[:2], planarize(pred.scale, pred.confidence)))
            names.append(name)
        results["sequences"] = local_table(rows)
        results["sequences_per_pair"] = {
            n: {
                "mean_r": float(np.exp(r["err"]).mean()),
                "const1_mean_r": float(np.exp(r["const1"]).mean()),
                "oracle_mean_r": float(np.exp(r["oracle"]).mean()),
                "planar_mean_r": float(np.exp(r["planar"]).mean()),
                "spread": r["spread"],
            }
            for n, r in zip(names, rows)
        }
        print_local_table(f"real sequences ({len(rows)} pairs)", results["sequences"])
    return results


def run_global(args) -> dict:
    model = ScaleNet.from_pretrained(args.model)
    local = LocalScaleNet.from_pretrained(args.local_model) if args.local_model != "none" else None
    torch.set_num_threads(args.threads) if args.threads else None
    _, held = split_images(list_images(args.photos))
    cfg = HomographyConfig(scale_range=(0.16, 6.0), perspective=args.perspective)
    rng = np.random.default_rng(args.seed + 1)
    err = {
        k: [] for k in ("consistency", "consistency, upright only", "A->B only", "D-ScaleNet", "const-1", "random bin")
    }
    if local is not None:
        err["median of Local-ScaleNet map"] = []
    t_full, t_cached = [], []
    for _name, a, b, H in tqdm(list(synthetic_pairs(held, args.pairs, args.seed, cfg, args.crop)), desc="global"):
        from localscale.geometry import global_scale

        g = math.log(global_scale(H, a.shape[:2], b.shape[:2]))
        t0 = time.perf_counter()
        ea, eb = model.encode_image(a), model.encode_image(b)
        t1 = time.perf_counter()
        p = model.predict_from_features(ea, eb)
        t2 = time.perf_counter()
        t_full.append(t2 - t0)
        t_cached.append(t2 - t1)
        err["consistency"].append(abs(math.log(model.retry_turned(p, a, b, ea, eb).scale) - g))
        err["consistency, upright only"].append(abs(math.log(p.scale) - g))
        err["A->B only"].append(abs(math.log(p.scale_ab) - g))
        err["D-ScaleNet"].append(abs(math.log(p.hard_scale) - g))
        err["const-1"].append(abs(g))
        err["random bin"].append(abs(math.log(math.sqrt(2)) * rng.integers(-6, 7) - g))
        if local is not None:
            err["median of Local-ScaleNet map"].append(abs(float(np.median(np.log(local.predict(a, b).scale))) - g))
    res = {k: {"mean_r": float(np.mean(np.exp(v))), "median_r": float(np.exp(np.median(v)))} for k, v in err.items()}
    res["timing_ms"] = {
        "uncached_pair_median": 1000 * float(np.median(t_full)),
        "cached_pair_median": 1000 * float(np.median(t_cached)),
        "threads": torch.get_num_threads(),
    }
    res["setup"] = {"pairs": len(err["const-1"]), "seed": args.seed, "perspective": args.perspective, "crop": args.crop}
    print(f"\n### global ScaleNet, held-out synthetic pairs ({len(err['const-1'])})\n")
    print("| read-out | mean r | median r |\n|---|---|---|")
    for k in err:
        print(f"| {k} | {res[k]['mean_r']:.3f} | {res[k]['median_r']:.3f} |")
    print(
        f"\ntiming per pair (median, {torch.get_num_threads()} threads): uncached "
        f"{res['timing_ms']['uncached_pair_median']:.1f} ms, cached features {res['timing_ms']['cached_pair_median']:.1f} ms"
    )
    return res


def run_real(args) -> dict:
    """All real pairs (:func:`localscale.evaluation.scale_real.evaluate_real`), the table printed."""
    local = LocalScaleNet.from_pretrained(args.model)
    scalenet = ScaleNet.from_pretrained(args.global_model)
    torch.set_num_threads(args.threads) if args.threads else None
    res = {
        "local_model": str(args.model or "bundled"),
        "global_model": str(args.global_model or "bundled"),
        **evaluate_real(
            local,
            scalenet,
            [Path(r) for r in args.real],
            refine=not args.no_refined,
            sift_seed=args.refine_seed == "sift",
            search=args.search,
            refine_matcher=args.refine_matcher,
        ),
    }
    print_real(res, columns(not args.no_refined, args.search))
    return res


def print_real(res: dict, keys) -> None:
    print(f"\n### real pairs ({res['pairs']}): mean over pairs of the mean r over each pair's co-visible pixels of A\n")
    print("| set | pairs | " + " | ".join(TITLES[k] for k in keys) + " |")
    print("|---|---|" + "---|" * len(keys))
    for g, v in res["table"].items():
        print(f"| {g} | {v['pairs']} | " + " | ".join(f"{v[k]:.3f}" for k in keys) + " |")
    if "refined_summary" in res:
        print(f"refined: {res['refined_summary']}")
    if "search_refined_verified_pairs" in res:
        print(f"refined from the searched maps: {res['search_refined_verified_pairs']} pairs verified")
    print(f"\nco-visibility IoU (mean over pairs): {res['visibility_iou_mean']}")
    print(f"reliability AUROC (r <= 1.25 vs r > 1.5): {res['reliability_auroc']:.3f}")
    print(f"pair flag: {res['flag']}")
    d = res["direction_errors"]
    print(f"wrong direction ({d['rule']}; {d['pairs_counted']} pairs): local {d['local']}, global {d['global']}")
    print("\n| image | predict(A, A) median | predict(gray A, A) median | ScaleNet(A, A) |\n|---|---|---|---|")
    for r in res["invariants"]:
        print(
            f"| {r['image']} | {r['identity_median']:.3f} | {r['gray_vs_colour_median']:.3f} | {r['global_identity']:.3f} |"
        )


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--mode", choices=["local", "global", "real"], default="local")
    p.add_argument(
        "--real",
        nargs="*",
        default=["../shared/data/sequences", "../shared/data/pairs"],
        help="real mode: HPatches-layout folders (the first one also gives the invariant images)",
    )
    p.add_argument("--global-model", default=None, help="real mode: ScaleNet checkpoint (default: bundled)")
    p.add_argument("--model", default=None, help="checkpoint (default: bundled)")
    p.add_argument(
        "--local-model",
        default=None,
        help="global mode: also score the median of this Local-ScaleNet's "
        "map as a global estimate (default: bundled; 'none' to skip)",
    )
    p.add_argument("--photos", default=None, help="photo folder; its held-out split makes the synthetic pairs")
    p.add_argument("--sequences", default=None, help="HPatches-layout folder of real sequences (local mode)")
    p.add_argument("--pairs", type=int, default=200)
    p.add_argument("--perspective", type=float, default=0.45)
    p.add_argument(
        "--crop",
        type=float,
        default=1.0,
        help="< 1: A is this central part of the photo and B shows its real surroundings",
    )
    p.add_argument("--seed", type=int, default=12345)
    p.add_argument("--threads", type=int, default=0)
    p.add_argument("--no-refined", action="store_true", help="real mode: skip the refined column (no matching)")
    p.add_argument(
        "--refine-seed",
        choices=("sift", "none"),
        default="sift",
        help="real mode: OpenCV SIFT matches as the seed geometry when the first pass is not verified",
    )
    p.add_argument(
        "--refine-matcher",
        default=None,
        metavar="NAME",
        help="real mode: refine with the geometry of correction='auto' and this matcher (e.g. "
        "aliked-lightglue) instead of the hardnet refinement passes",
    )
    p.add_argument(
        "--search",
        action="store_true",
        help="real mode: also score the window search (localscale.search), ScaleNet on its windows "
        "and the refinement seeded by the searched maps",
    )
    p.add_argument("--out", default=None, help="JSON output")
    args = p.parse_args(argv)
    if not 0 < args.crop <= 1:
        p.error(f"--crop must be in (0, 1], got {args.crop}")
    missing = [
        f
        for f in (args.real if args.mode == "real" else []) + [args.photos, args.sequences]
        if f and not Path(f).is_dir()
    ]
    if missing:
        p.error(f"folder not found: {missing[0]}")
    try:
        res = {"local": run_local, "global": run_global, "real": run_real}[args.mode](args)
    except LocalScaleError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({**res, "commit": git_commit()}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
