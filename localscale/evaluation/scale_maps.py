"""Scale-map accuracy against a homography: the pairs (held-out synthetic, HPatches-layout real) and
the per-pixel scale-ratio error ``r = max(s, g) / min(s, g)`` over the co-visible pixels of A,
sampled on a :data:`STRIDE`-pixel grid, against the constant map 1 (``const1``) and the best
constant of each pair (``oracle``: the median of the true log scale)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import numpy as np

from ..geometry import (
    HomographyConfig,
    central_crop,
    covisible_mask,
    homography_scale_map,
    sample_homography,
    translation,
    warp_image,
)
from ..io import load_image, read_homography

BANDS = [("|log2 s|<1", 0, 1), ("1<=|log2 s|<2", 1, 2), ("|log2 s|>=2", 2, 99)]
PERSPECTIVE = [("low", 0, 0.15), ("medium", 0.15, 0.35), ("high", 0.35, 99)]
STRIDE = 4


def synthetic_pairs(photos: list[Path], n: int, seed: int, cfg: HomographyConfig, crop: float = 1.0):
    """Held-out pairs at the photos' own resolution: ``(name, A, B, H)``; B filled from another photo.

    ``crop < 1``: A is the central ``crop`` part of the photo and B is rendered from the whole
    photo, so around A's content B shows the photo's real surroundings."""
    rng = np.random.default_rng(seed)
    cache = {}

    def img(i):
        if i not in cache:
            cache[i] = load_image(photos[i])
        return cache[i]

    for k in range(n):
        i, j = rng.choice(len(photos), 2, replace=False)
        full = img(i)
        a, (x0, y0) = central_crop(full, crop)
        H = sample_homography(rng, a.shape[:2], a.shape[:2], cfg)
        b, _ = warp_image(full, H @ translation(-x0, -y0), a.shape[:2], fill=img(j))
        if covisible_mask(H, a.shape[:2], b.shape[:2], 8).sum() < 8:
            continue
        yield f"synthetic_{k:04d}", a, b, H


def sequence_pairs(root: Path):
    for seq in sorted(p for p in root.iterdir() if p.is_dir()):
        ones = sorted(seq.glob("1.*"))
        if not ones:
            continue
        a = load_image(ones[0])
        for hf in sorted(seq.glob("H_1_*")):
            k = hf.name.split("_")[-1]
            bfile = next(iter(sorted(seq.glob(f"{k}.*"))), None)
            if bfile is not None:
                yield f"{seq.name}/1-{k}", a, load_image(bfile), read_homography(hf)


def real_pairs(roots: list[Path]):
    """``(name, A, B, H)`` of every HPatches-layout folder under each root (sequences and two-image pairs)."""
    for root in roots:
        yield from ((f"{root.name}/{n}", a, b, H) for n, a, b, H in sequence_pairs(root))


def pixel_errors(pred: np.ndarray, H: np.ndarray, shape_b, planar: Optional[np.ndarray] = None) -> dict:
    h, w = pred.shape
    gt = homography_scale_map(H, h, w, STRIDE)
    m = covisible_mask(H, (h, w), shape_b, STRIDE) & np.isfinite(gt)
    ys = np.minimum(np.arange(gt.shape[0]) * STRIDE + STRIDE // 2, h - 1)
    xs = np.minimum(np.arange(gt.shape[1]) * STRIDE + STRIDE // 2, w - 1)
    sub = lambda x: x[np.ix_(ys, xs)][m]  # noqa: E731  (pixel nearest to each grid cell centre)
    lg = np.log(gt[m])
    spread = float(np.log2(gt[m]).std()) if m.sum() > 1 else 0.0
    out = {
        "log_gt": lg,
        "log_pred": np.log(sub(pred)),
        "err": np.abs(np.log(sub(pred)) - lg),
        "const1": np.abs(lg),
        "oracle": np.abs(lg - np.median(lg)),
        "spread": spread,
    }
    if planar is not None:
        out["planar"] = np.abs(np.log(sub(planar)) - lg)
    return out


def summarise(rows: list[dict], select=None) -> dict:
    errs = {k: [] for k in ("err", "planar", "const1", "oracle") if k in rows[0]}
    npairs = 0
    for r in rows:
        m = np.ones_like(r["err"], bool) if select is None else select(r)
        if m.any():
            npairs += 1
            for k in errs:
                errs[k].append(r[k][m])
    if not npairs:
        return {"pairs": 0}
    out = {"pairs": npairs, "pixels": int(sum(len(e) for e in errs["err"]))}
    for k, name in (("err", "local"), ("planar", "local+planar"), ("const1", "const-1"), ("oracle", "oracle const")):
        if k not in errs:
            continue
        e = np.concatenate(errs[k])
        out[name] = {"mean_r": float(np.exp(e).mean()), "median_r": float(np.exp(np.median(e)))}
    out["local_beats_oracle_pairs"] = float(
        np.mean(
            [np.exp(r["err"]).mean() < np.exp(r["oracle"]).mean() for r in rows if select is None or select(r).any()]
        )
    )
    return out


def local_table(rows: list[dict]) -> dict:
    table = {"all": summarise(rows)}
    for name, lo, hi in BANDS:
        table[f"scale {name}"] = summarise(
            rows,
            lambda r, lo=lo, hi=hi: (
                (np.abs(r["log_gt"] / math.log(2)) >= lo) & (np.abs(r["log_gt"] / math.log(2)) < hi)
            ),
        )
    for name, lo, hi in PERSPECTIVE:
        table[f"perspective {name}"] = summarise(
            rows, lambda r, lo=lo, hi=hi: np.full(r["err"].shape, lo <= r["spread"] < hi)
        )
    return table
