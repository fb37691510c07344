"""Accuracy of the scale models on real pairs labelled by 3D models (collections' COLMAP models).

For each labelled collection (``pairs.npz`` of ``train/label_collections.py``), ``--samples`` seeded
samples of :class:`localscale.training.real_pairs.RealPairs` (target scales log-uniform in [1/6, 6],
close-ups cut from the photos, quarter turns): per labelled cell of A's stride-8 grid, the
Local-ScaleNet error ``r = exp|ln S_pred - ln S_label|`` (processing frame, soft read-out), and per
pair the ScaleNet error of the consistency-checked scale against the paper's global label; against
the constant 1. Direction errors: pairs with ``|log2 label| >= 0.5`` predicted on the other side of 1.

    OMP_NUM_THREADS=1 python eval/real_pair_accuracy.py --labels runs/real_models --out results/real_pairs/bundled.json

``--loco RUNS`` scores each collection with the models trained without it
(``RUNS/local_without_<collection>/model.pt``, ``RUNS/global_without_<collection>/model.pt``, from
``train/train_real_pairs.py``) instead of one pair of models for all.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch

from localscale import LocalScaleNet, ScaleNet, scales
from localscale.evaluation.report import git_commit
from localscale.training.loop import real_validation_batches

DIRECTION_MIN_LOG2 = 0.5


@torch.no_grad()
def evaluate(local, scalenet, batches: list[dict]) -> dict:
    cell_err, cell_base, pair_rows = [], [], []
    for batch in batches:
        m, gt = batch["mask"], torch.log(batch["scale"])
        ls = scales.soft_log_scale(torch.softmax(local(batch["a"], batch["b"]).float(), 1), 1)
        cell_err.append((ls - gt).abs()[m])
        cell_base.append(gt.abs()[m])
        l_ab, l_ba = scalenet(batch["a"], batch["b"])
        g = scales.consistent_log_scale(
            scales.soft_log_scale(torch.softmax(l_ab.float(), 1), 1),
            scales.soft_log_scale(torch.softmax(l_ba.float(), 1), 1),
        )
        g_gt = torch.log(batch["global_scale"].float())
        for k in range(len(m)):
            pair_rows.append(
                {
                    "label_log2": float(g_gt[k]) / math.log(2),
                    "global_log2": float(g[k]) / math.log(2),
                    "local_median_log2": float(ls[k][m[k]].median()) / math.log(2),
                    "cells_median_label_log2": float(gt[k][m[k]].median()) / math.log(2),
                }
            )
    e, b = torch.cat(cell_err).double(), torch.cat(cell_base).double()
    ge = np.array([abs(r["global_log2"] - r["label_log2"]) for r in pair_rows]) * math.log(2)
    gb = np.array([abs(r["label_log2"]) for r in pair_rows]) * math.log(2)
    due = [r for r in pair_rows if abs(r["label_log2"]) >= DIRECTION_MIN_LOG2]
    return {
        "pairs": len(pair_rows),
        "cells": int(len(e)),
        "local": {"mean_r": float(torch.exp(e).mean()), "median_r": float(torch.exp(e.median()))},
        "local_const1": {"mean_r": float(torch.exp(b).mean())},
        "global": {"mean_r": float(np.exp(ge).mean()), "median_r": float(np.exp(np.median(ge)))},
        "global_const1": {"mean_r": float(np.exp(gb).mean())},
        "direction_errors": {
            "pairs_counted": len(due),
            "local": sum(r["local_median_log2"] * r["cells_median_label_log2"] < 0 for r in due),
            "global": sum(r["global_log2"] * r["label_log2"] < 0 for r in due),
        },
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--labels", type=Path, default=Path("runs/real_models"), help="folder of <collection>/pairs.npz")
    p.add_argument("--collections", nargs="*", default=None)
    p.add_argument("--local-model", default=None, help="default: the bundled Local-ScaleNet")
    p.add_argument("--global-model", default=None, help="default: the bundled ScaleNet")
    p.add_argument("--samples", type=int, default=128)
    p.add_argument("--seed", type=int, default=123)
    p.add_argument("--turn-probability", type=float, default=0.5, help="share of samples with B turned (0: upright)")
    p.add_argument("--loco", type=Path, default=None, help="folder of leave-one-collection-out runs")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    names = args.collections or sorted(d.name for d in args.labels.iterdir() if (d / "pairs.npz").exists())
    if args.loco is None:
        local = LocalScaleNet.from_pretrained(args.local_model).eval()
        scalenet = ScaleNet.from_pretrained(args.global_model).eval()
        results = {
            "turn_probability": args.turn_probability,
            "local_model": args.local_model or "bundled",
            "global_model": args.global_model or "bundled",
        }
    else:
        results = {
            "turn_probability": args.turn_probability,
            "local_model": f"{args.loco}/local_without_<collection>",
            "global_model": f"{args.loco}/global_without_<collection>",
        }
    print(
        "| collection | samples | local mean r | local median r | const-1 | ScaleNet mean r | const-1 | direction errors local / global |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name in names:
        if args.loco is not None:
            local = LocalScaleNet.from_pretrained(args.loco / f"local_without_{name}" / "model.pt").eval()
            scalenet = ScaleNet.from_pretrained(args.loco / f"global_without_{name}" / "model.pt").eval()
        batches = real_validation_batches(
            str(args.labels / name / "pairs.npz"), args.samples, args.seed, 192, turn_probability=args.turn_probability
        )
        r = evaluate(local, scalenet, batches)
        results[name] = r
        d = r["direction_errors"]
        print(
            f"| {name} | {r['pairs']} | {r['local']['mean_r']:.3f} | {r['local']['median_r']:.3f} | "
            f"{r['local_const1']['mean_r']:.3f} | {r['global']['mean_r']:.3f} | {r['global_const1']['mean_r']:.3f} | "
            f"{d['local']} / {d['global']} of {d['pairs_counted']} |",
            flush=True,
        )
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.out.with_suffix(".tmp")
        tmp.write_text(json.dumps({**results, "commit": git_commit()}, indent=1))
        tmp.replace(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
