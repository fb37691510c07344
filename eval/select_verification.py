"""Selection of the verification thresholds and the refinement support on held-out synthetic pairs.

Pairs: held-out photos (every 10th of ``--photos``, never trained on) cut to their central 70 %
(B shows the photo's real surroundings), random homographies (scale 1/4..4, rotation 30 deg,
strong perspective). Per pair: the bundled Local-ScaleNet's maps, a first HardNet matching pass
with the gated maps, verification with permissive thresholds (so that every geometry is kept), and
the per-pixel r (over the co-visible pixels of A) of the local map and of the refined map for each
support variant. The tables then show, for a grid of ``min_inliers`` / ``min_inlier_ratio``, the
mean r of "refined where verified, else local" and on how many pairs it is worse than the local map;
and, with the default :class:`VerificationConfig`, the whole ``match_refined_pair`` (two passes) without
and with the OpenCV SIFT seed (used when the first pass is not verified).

    python eval/select_verification.py --photos ../shared/data/train_images --pairs 80 \
        --out results/select_verification.json
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

import numpy as np
import torch

from localscale import LocalScaleNet
from localscale.data import list_images, split_images
from localscale.evaluation.report import git_commit
from localscale.evaluation.scale_maps import pixel_errors, synthetic_pairs
from localscale.geometry import HomographyConfig
from localscale.matching.correction import CorrectionGate
from localscale.matching.pipeline import match_refined_pair
from localscale.matching.refinement import refine_pair_maps
from localscale.matching.verification import VerificationConfig

PERMISSIVE = VerificationConfig(min_inliers=8, min_inlier_ratio=0.0, min_coverage=0.0, max_scale_disagreement_log2=99.0)
VARIANTS = {
    "covisible": VerificationConfig(),
    "hull": VerificationConfig(support="hull"),
    "covisible, decay 0.25": VerificationConfig(decay=0.25),
}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--photos", default="../shared/data/train_images")
    p.add_argument("--pairs", type=int, default=80)
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--out", default=None, help="JSON output")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    _, held = split_images(list_images(args.photos))
    model = LocalScaleNet.from_pretrained()
    cfg = HomographyConfig(scale_range=(0.25, 4.0), rotation_deg=30, skew=0.1, perspective=0.6, translation=0.1)
    rows = []
    for name, a, b, H in synthetic_pairs(held, args.pairs, args.seed, cfg, crop=0.7):
        fwd, bwd = model.predict(a, b), model.predict(b, a)
        fa, fb = CorrectionGate().apply_predictions(fwd, bwd)
        res = match_refined_pair(a, b, fa, fb, fwd.scale, bwd.scale, verification=PERMISSIVE, max_passes=1)
        v = res.verification
        r = {
            "name": name,
            "local": float(np.exp(pixel_errors(fwd.scale, H, b.shape[:2])["err"]).mean()),
            "model": v.model,
            "inliers": v.num_inliers,
            "matches": len(v.inliers),
            "ratio": v.inlier_ratio,
            "coverage": v.coverage,
            "disagreement_log2": v.scale_disagreement_log2,
        }
        if v.model == "homography":
            forced = copy.copy(v)
            forced.verified = True
            for k, c in VARIANTS.items():
                ra, _ = refine_pair_maps(fwd.scale, bwd.scale, forced, c)
                r[k] = float(np.exp(pixel_errors(ra.scale, H, b.shape[:2])["err"]).mean())
        full = match_refined_pair(a, b, fa, fb, fwd.scale, bwd.scale, sift_seed=True)
        r["seed_used"] = full.meta["seed_inliers"] is not None
        r["refined_seed"] = float(np.exp(pixel_errors(full.refined_a.scale, H, b.shape[:2])["err"]).mean())
        r["refined_seed_verified"] = bool(full.refined_a.verified)
        r["refined_noseed"] = r["local"] if r["seed_used"] else r["refined_seed"]
        rows.append(r)
        print(json.dumps(r), flush=True)
    grid = []
    for n in (8, 12, 20, 30, 50):
        for q in (0.0, 0.05, 0.08, 0.1, 0.15):
            use = [("covisible" in r) and r["inliers"] >= n and r["ratio"] >= q for r in rows]
            rr = [r["covisible"] if u else r["local"] for r, u in zip(rows, use)]
            grid.append(
                {
                    "min_inliers": n,
                    "min_inlier_ratio": q,
                    "verified": int(sum(use)),
                    "mean_r": float(np.mean(rr)),
                    "worse_than_local": int(sum(x > r["local"] + 1e-9 for x, r in zip(rr, rows))),
                }
            )
    ok = [r for r in rows if "covisible" in r and r["inliers"] >= 20 and r["ratio"] >= 0.15]
    support = {k: float(np.mean([r[k] for r in ok])) for k in VARIANTS} if ok else {}
    print(f"\n{len(rows)} pairs; local map mean r {np.mean([r['local'] for r in rows]):.3f}\n")
    print(
        "| min_inliers | min_inlier_ratio | verified pairs | mean r (refined where verified, else local) | "
        "pairs worse than local |\n|---|---|---|---|---|"
    )
    for g in grid:
        print(
            f"| {g['min_inliers']} | {g['min_inlier_ratio']} | {g['verified']} | {g['mean_r']:.3f} | "
            f"{g['worse_than_local']} |"
        )
    print("\nsupport variants on the pairs verified with 20 inliers / ratio 0.15 (mean r):", support)
    seed = {}
    for k in ("refined_noseed", "refined_seed"):
        seed[k] = {
            "mean_r": float(np.mean([r[k] for r in rows])),
            "worse_than_local": int(sum(r[k] > r["local"] + 1e-9 for r in rows)),
        }
    seed["seed_used"] = int(sum(r["seed_used"] for r in rows))
    seed["seed_verified"] = int(sum(r["seed_used"] and r["refined_seed_verified"] for r in rows))
    print("match_refined_pair with the default config, without / with the SIFT seed:", seed)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(
            json.dumps(
                {
                    "pairs": rows,
                    "grid": grid,
                    "support_variants": support,
                    "sift_seed": seed,
                    "args": vars(args),
                    "commit": git_commit(),
                },
                indent=1,
            )
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
