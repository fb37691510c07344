"""Selection set for inference-time read-outs of Local-ScaleNet (no retraining).

On held-out synthetic pairs (the held-out split of the training photos, never the real
evaluation data), the mean over pairs of the per-pair mean scale-ratio error ``r`` over the
co-visible pixels of A, for:

* ``local``: the A->B map as predicted (the default read-out);
* ``symmetric``: the map shifted by half the disagreement of the two directions,
  ``ln s - (median ln S_AB + median ln S_BA) / 2`` (ScaleNet's consistency check, densely);
* ``symmetric-weighted``: the same with medians weighted by ``reliability x visible``;
* ``fused``: the local map's shape with ScaleNet's level (the ``fused`` correction);
* ``global``: ScaleNet's consistency-checked scale as a constant map (``ScaleNet.predict``: with
  quarter turns of A and B when the upright prediction is unreliable); ``global-upright``: the
  upright prediction alone;
* ``rotation-search``: B rotated by 0/90/180/270 deg, the prediction with the highest mean
  ``reliability x visible`` kept (a canonicalisation step for rotations beyond training);
* ``shrink-A``: the map pulled towards its own level, ``c + A (ln s - c)`` with ``c`` the
  median of ``ln s`` weighted by ``reliability x visible`` (``shrink-0``: that level as a
  constant map; the per-pixel detail kept at the share ``A``);
* ``window-search``: :func:`localscale.search.search_scale_map` (windows of A or B at 1/2
  and 1/4 of the sides against the other image whole, the best-scoring pair kept);
  ``window-search-turns``: the same after trying B turned by 90/180/270 deg;
* ``const-1``: no correction.

Pair sets: the paper's homography ranges, the same with rotations over the whole circle, the
paper's ranges with A a central 70 % crop whose surroundings B shows, and zooms at the two
ends of the bin range (B 4.5-8x closer; B 4.5-8x further, i.e. A's content in 1/20-1/64 of B).

    OMP_NUM_THREADS=1 python eval/map_variants.py --photos ../shared/data/train_images --pairs 60 \
        --out results/map_variants.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from localscale import LocalScaleNet, ScaleNet
from localscale.data import list_images, split_images
from localscale.evaluation.report import git_commit
from localscale.evaluation.scale_maps import pixel_errors, synthetic_pairs
from localscale.geometry import HomographyConfig
from localscale.matching.correction import weighted_quantile
from localscale.search import WindowSearchConfig, search_scale_map

VARIANTS = (
    "local",
    "symmetric",
    "symmetric-weighted",
    "fused",
    "global",
    "global-upright",
    "rotation-search",
    "shrink-0",
    "shrink-0.5",
    "window-search",
    "window-search-turns",
    "const-1",
)
PAIR_SETS = {
    "paper ranges": (HomographyConfig(), 1.0),
    "rotation over the whole circle": (HomographyConfig(rotation_deg=180.0), 1.0),
    "paper ranges, A a 70 % crop": (HomographyConfig(), 0.7),
    "zoom-in end (4.5-8x)": (HomographyConfig(scale_range=(4.5, 8.0)), 1.0),
    "zoom-out end (1/8-1/4.5)": (HomographyConfig(scale_range=(0.125, 0.22)), 1.0),
}


def weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    return weighted_quantile(values.ravel(), weights.ravel(), 0.5)


def variant_maps(local: LocalScaleNet, scalenet: ScaleNet, a: np.ndarray, b: np.ndarray, variants=VARIANTS) -> dict:
    """``{variant: H_A x W_A map}`` for one pair."""
    out = {}
    if "window-search" in variants:
        out["window-search"] = search_scale_map(local, a, b).prediction.scale
    if "window-search-turns" in variants:
        turns = WindowSearchConfig(quarter_turns=(1, 2, 3))
        out["window-search-turns"] = search_scale_map(local, a, b, turns).prediction.scale
    if "global-upright" in variants:
        out["global-upright"] = np.full(a.shape[:2], float(scalenet.predict(a, b, turns=False).scale), np.float32)
    if "global" in variants and not set(variants) & {"symmetric", "symmetric-weighted", "fused", "rotation-search"}:
        out["global"] = np.full(a.shape[:2], float(scalenet.predict(a, b).scale), np.float32)
    variants = [v for v in variants if v not in out]
    if not variants:
        return out
    ea, eb = local.encode_image(a), local.encode_image(b)
    fwd = local.predict_from_features(ea, eb)
    if not set(variants) & {"symmetric", "symmetric-weighted", "fused", "global", "rotation-search"}:
        lf = np.log(fwd.scale)
        c = weighted_median(lf, fwd.reliability * fwd.visible)
        out.update({"local": fwd.scale, "const-1": np.ones_like(fwd.scale)})
        out.update({v: np.exp(c + float(v.split("-", 1)[1]) * (lf - c)) for v in variants if v.startswith("shrink-")})
        return out
    bwd = local.predict_from_features(eb, ea)
    g = float(scalenet.predict(a, b).scale)
    lf, lb = np.log(fwd.scale), np.log(bwd.scale)
    weight = lambda p: p.reliability * p.visible if p.reliability is not None else np.ones_like(p.scale)  # noqa: E731
    c = np.median(lf) + np.median(lb)
    cw = weighted_median(lf, weight(fwd)) + weighted_median(lb, weight(bwd))
    best, best_score = fwd, float(weight(fwd).mean())
    for k in (1, 2, 3):
        p = local.predict_from_features(ea, local.encode_image(np.ascontiguousarray(np.rot90(b, k))))
        if float(weight(p).mean()) > best_score:
            best, best_score = p, float(weight(p).mean())
    return out | {
        "local": fwd.scale,
        "symmetric": np.exp(lf - c / 2),
        "symmetric-weighted": np.exp(lf - cw / 2),
        "fused": np.exp(lf - weighted_median(lf, weight(fwd)) + math.log(g)),
        "global": np.full_like(fwd.scale, g),
        "rotation-search": best.scale,
        "shrink-0": np.full_like(fwd.scale, math.exp(weighted_median(lf, weight(fwd)))),
        "shrink-0.5": np.exp(0.5 * lf + 0.5 * weighted_median(lf, weight(fwd))),
        "const-1": np.ones_like(fwd.scale),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--photos", required=True, help="training photo folder; its held-out split is used")
    p.add_argument("--pairs", type=int, default=60, help="pairs per set")
    p.add_argument("--seed", type=int, default=777)
    p.add_argument("--model", default=None, help="Local-ScaleNet checkpoint (default: bundled)")
    p.add_argument("--global-model", default=None, help="ScaleNet checkpoint (default: bundled)")
    p.add_argument(
        "--variants",
        nargs="+",
        default=list(VARIANTS),
        help="read-outs to measure (default: all; local, shrink-A and const-1 alone are fast)",
    )
    p.add_argument("--sets", nargs="+", default=list(PAIR_SETS), help="pair sets (default: all)")
    p.add_argument("--out", default=None, help="JSON output")
    args = p.parse_args(argv)
    variants = list(args.variants)
    torch.set_num_threads(1)
    local, scalenet = LocalScaleNet.from_pretrained(args.model), ScaleNet.from_pretrained(args.global_model)
    _, held = split_images(list_images(args.photos))
    table = {}
    for name in args.sets:
        cfg, crop = PAIR_SETS[name]
        per = {v: [] for v in variants}
        for _, a, b, H in tqdm(list(synthetic_pairs(held, args.pairs, args.seed, cfg, crop)), desc=name):
            for v, m in variant_maps(local, scalenet, a, b, variants).items():
                if v not in per:
                    continue
                per[v].append(float(np.exp(pixel_errors(m, H, b.shape[:2])["err"]).mean()))
        table[name] = {v: float(np.mean(e)) for v, e in per.items()}
        table[name]["pairs"] = len(per[variants[0]])
    print("| pair set (pairs) | " + " | ".join(variants) + " |")
    print("|---|" + "---|" * len(variants))
    for name, row in table.items():
        print(f"| {name} ({row['pairs']}) | " + " | ".join(f"{row[v]:.3f}" for v in variants) + " |")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({"seed": args.seed, "table": table, "commit": git_commit()}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
