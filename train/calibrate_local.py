"""Calibrate a trained Local-ScaleNet's per-pixel reliability on held-out synthetic pairs.

    python train/calibrate_local.py --model runs/local_v2/model.pt --data ../shared/data/train_images \
        --pairs 256 --out runs/local_v2/calibrated.pt

Renders ``--pairs`` pairs from the **held-out** photos (every 10th file, never trained on) with
the pair options the model was trained with (read from the checkpoint), runs the model, and
fits ``P(visible and r < 1.25)`` per cell as a logistic regression on
:func:`localscale.models.local_prediction.reliability_features`. The fitted coefficients go into the
model's config (``calibration``); the model is written to ``--out``. Also prints the pair-level
statistics of :mod:`localscale.reliability` for pairs with mean r > 2 and < 1.3, to choose
:class:`~localscale.reliability.PairCheckConfig` thresholds on synthetic data.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch
from tqdm import tqdm

from localscale import scales
from localscale.checkpoint import read_checkpoint, save_model
from localscale.data import SyntheticPairs, collate, list_images, split_images
from localscale.models import load_model
from localscale.models.local_prediction import reliability_features
from localscale.reliability import auroc, fit_calibration, pair_statistics
from localscale.training import TrainConfig

GOOD_RATIO = 1.25


@torch.inference_mode()
def collect(model, dataset, batch_size: int = 16):
    feats, labels, pairs = [], [], []
    for j in tqdm(range(0, len(dataset), batch_size), desc="calibration pairs"):
        batch = collate([dataset[i] for i in range(j, min(j + batch_size, len(dataset)))])
        fa, fb = model.encode(batch["a"]), model.encode(batch["b"])
        logits, vis = model.forward_features_all(fa, fb)
        logits_ba, vis_ba = model.forward_features_all(fb, fa)
        probs, probs_ba = torch.softmax(logits, 1), torch.softmax(logits_ba, 1)
        visible = torch.sigmoid(vis[:, 0]) if vis is not None else None
        visible_ba = torch.sigmoid(vis_ba[:, 0]) if vis_ba is not None else None
        f = reliability_features(probs, visible, 1)  # B x 3 x h x w
        log_s = scales.soft_log_scale(probs, 1)
        err = (log_s - torch.log(batch["scale"])).abs()
        good = batch["mask"] & (err < math.log(GOOD_RATIO))
        valid = batch["valid"]
        feats.append(f.permute(0, 2, 3, 1)[valid].numpy())
        labels.append(good[valid].numpy())
        ls_ba = scales.soft_log_scale(probs_ba, 1)
        for k in range(len(probs)):
            m, v = batch["mask"][k], valid[k]
            rows, cols = v.any(1).nonzero()[:, 0], v.any(0).nonzero()[:, 0]  # A's image region (a rectangle)
            crop = lambda x: x[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1].numpy()  # noqa: E731
            grid = lambda ls, vis: SimpleNamespace(  # noqa: E731
                scale=np.exp(crop(ls)), visible=crop(vis) if vis is not None else None, reliability=None
            )
            fwd, bwd = (
                grid(log_s[k], visible[k] if visible is not None else None),
                grid(ls_ba[k], visible_ba[k] if visible_ba is not None else None),
            )
            va = fwd.visible > 0.5 if fwd.visible is not None else np.ones(fwd.scale.shape, bool)
            pairs.append(
                {
                    "mean_r": float(torch.exp(err[k][m]).mean()) if m.any() else float("inf"),
                    "related": bool(batch["related"][k]),
                    **pair_statistics(fwd, bwd),
                    "features": crop(f[k].permute(1, 2, 0))[va],
                }
            )
    return np.concatenate(feats), np.concatenate(labels), pairs


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", required=True, help="trained Local-ScaleNet checkpoint (model.pt or last.pt)")
    p.add_argument("--data", default="../shared/data/train_images", help="photo folder (its held-out split is used)")
    p.add_argument("--pairs", type=int, default=256)
    p.add_argument("--seed", type=int, default=31337)
    p.add_argument("--threads", type=int, default=0)
    p.add_argument("--out", required=True, help="calibrated checkpoint to write")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    model = load_model(args.model, arch="LocalScaleNet")
    meta = read_checkpoint(args.model).get("meta", {})
    tc = meta.get("train_config", {})
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    cfg = TrainConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in tc.items() if k in known})
    _, held = split_images(list_images(args.data), cfg.holdout_every)
    dataset = SyntheticPairs(held, length=args.pairs, seed=args.seed, config=cfg.pair_config())
    x, y, pairs = collect(model, dataset)
    coef = fit_calibration(x, y)
    model.config.calibration = coef
    z = coef[0] + x @ np.asarray(coef[1:])
    prob = 1 / (1 + np.exp(-z))
    print(
        f"calibration {coef}: {len(y)} cells, {100 * y.mean():.1f}% good, AUROC {auroc(prob, y):.3f}, "
        f"mean predicted {prob.mean():.3f}",
        file=sys.stderr,
    )
    for lo in np.arange(0, 1, 0.1):
        sel = (prob >= lo) & (prob < lo + 0.1)
        if sel.any():
            print(
                f"  predicted {lo:.1f}-{lo + 0.1:.1f}: {sel.sum():7d} cells, observed {y[sel].mean():.3f}",
                file=sys.stderr,
            )
    stats = []
    for pr in pairs:  # the mean reliability over A's visible part, now that the calibration is known
        f = pr.pop("features")
        pr["mean_reliability"] = (
            float((1 / (1 + np.exp(-(coef[0] + f @ np.asarray(coef[1:]))))).mean()) if len(f) else 0.0
        )
        stats.append(pr)
    for name, sel in (
        ("bad (mean r > 2 or unrelated)", lambda s: s["mean_r"] > 2 or not s["related"]),
        ("good (mean r < 1.3)", lambda s: s["related"] and s["mean_r"] < 1.3),
    ):
        group = [s for s in stats if sel(s)]
        if group:
            q = {
                k: np.percentile([s[k] for s in group], [10, 50, 90]).round(3).tolist()
                for k in ("inconsistency_log2", "visible_fraction", "mean_reliability")
            }
            print(f"{name}: {len(group)} pairs, 10/50/90th percentiles {json.dumps(q)}", file=sys.stderr)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    (Path(args.out).with_suffix(".pairs.json")).write_text(json.dumps(stats))
    meta = dict(
        meta,
        calibration={
            "pairs": len(dataset),
            "seed": args.seed,
            "cells": int(len(y)),
            "good_ratio": GOOD_RATIO,
            "photos": "held-out split of " + str(args.data),
        },
    )
    save_model(model, args.out, meta=meta, half=True)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
