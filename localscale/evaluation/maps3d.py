"""Scale maps on 3D scenes: per-point truth from a COLMAP model, pairs as they are and close-ups.

A labelled collection is the list of :class:`~localscale.training.real_pairs.CovisiblePair` of its
COLMAP model (the ``pairs.npz`` of ``train/label_collections.py``: two photos and both photos'
observations of the 3D points they share). The truth at each shared point of A is the real-pair
label of :func:`~localscale.training.real_pairs.point_log_scales`: the median ratio of its distances
to its 8 nearest shared points in B and in A. Kinds of pair (:data:`KINDS`):

* ``as-is``: the two photos;
* ``closeup``: B replaced by a window of it with sides ``1/z`` of B's (``z`` log-uniform in
  ``zoom_range``, default 2.5-6), centred on a shared point, enlarged back to B's size; the points
  outside the window are dropped and the labels computed again on the window's pixels (a window
  with fewer than 20 labelled points is drawn again);
* ``closeup-turned``: the close-up also turned by 1-3 quarter turns (counter-clockwise).

Each predictor's ``S_{A->B}`` (:mod:`.predictors`) is read at the labelled points of A (nearest
pixel); a pair's error factor is ``exp(mean |ln(pred / truth)|)`` over its points, and the summary
averages the factors over pairs. Pairs (at most ``max_pairs`` per collection), windows and turns
are drawn from ``seed`` and the names, so every run and every predictor sees the same pairs.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import cv2
import numpy as np

from ..core.errors import LocalScaleError
from ..geometry.cameras import window_pixels
from ..training.real_pairs import CovisiblePair, point_log_scales
from .predictors import PairContext, ScaleModels, predict
from .records import RecordFile

KINDS = ("as-is", "closeup", "closeup-turned")
ZOOM_RANGE = (2.5, 6.0)


@dataclass
class LabelledPair:
    """A pair as the predictors see it, with the truth: ``xy_a`` (``N x 2``, pixels of A, the centre
    of the top-left pixel at 0) and ``log_truth`` (``N``, ``ln S_{A->B}`` there); ``zoom``,
    ``turns`` and ``window`` ``(x0, y0, w, h)`` of B for a close-up."""

    collection: str
    name_a: str
    name_b: str
    kind: str
    image_a: np.ndarray
    image_b: np.ndarray
    xy_a: np.ndarray
    log_truth: np.ndarray
    zoom: float = 1.0
    turns: int = 0
    window: Optional[tuple] = None


def pair_rng(seed: int, *names: str) -> np.random.Generator:
    """A generator fixed by ``seed`` and the names (not by the order things are drawn in)."""
    return np.random.default_rng([int(seed), zlib.crc32("/".join(names).encode())])


def closeup_window(shape_b: tuple[int, int], xy_b: np.ndarray, rng: np.random.Generator, zoom_range=ZOOM_RANGE):
    """``((x0, y0, w, h), z)``: a window of an image of ``shape_b`` with sides ``1/z`` of its own,
    centred on one of the points ``xy_b`` (moved inside the image); ``z`` log-uniform in ``zoom_range``."""
    H, W = shape_b
    z = math.exp(rng.uniform(math.log(zoom_range[0]), math.log(zoom_range[1])))
    w, h = max(1, round(W / z)), max(1, round(H / z))
    cx, cy = xy_b[rng.integers(len(xy_b))]
    x0 = int(np.clip(round(cx - w / 2), 0, W - w))
    y0 = int(np.clip(round(cy - h / 2), 0, H - h))
    return (x0, y0, w, h), z


def cut_closeup(image: np.ndarray, window, turns: int = 0) -> np.ndarray:
    """The window ``(x0, y0, w, h)`` of ``image`` enlarged to the image's size, then turned."""
    x0, y0, w, h = window
    H, W = image.shape[:2]
    crop = image[y0 : y0 + h, x0 : x0 + w]
    out = cv2.resize(crop, (W, H), interpolation=cv2.INTER_LINEAR if w < W else cv2.INTER_AREA)
    return np.ascontiguousarray(np.rot90(out, turns % 4))


def _apply(M: np.ndarray, xy: np.ndarray) -> np.ndarray:
    p = xy @ M[:2, :2].T + M[:2, 2]
    return p / (xy @ M[2, :2] + M[2, 2])[:, None]


def labelled_pair(
    pair: CovisiblePair,
    kind: str,
    image_a: np.ndarray,
    image_b: np.ndarray,
    seed: int = 0,
    zoom_range=ZOOM_RANGE,
    neighbours: int = 8,
    min_points: int = 20,
    attempts: int = 10,
) -> Optional[LabelledPair]:
    """``pair`` as ``kind`` with its per-point truth; a close-up with fewer than ``min_points``
    labelled points is drawn again (``attempts`` at most, each fixed by ``(seed, names, attempt)``);
    None when none has enough."""
    if kind not in KINDS:
        raise LocalScaleError(f"pair kind must be one of {', '.join(KINDS)}, got {kind!r}")
    xa = np.asarray(pair.xy_a, np.float64) - 0.5  # COLMAP's pixel centres are at + 0.5
    xb = np.asarray(pair.xy_b, np.float64) - 0.5
    names = (pair.collection, Path(pair.image_a).name, Path(pair.image_b).name)
    for attempt in range(attempts if kind != "as-is" else 1):
        b, pa, pb, z, turns, window = image_b, xa, xb, 1.0, 0, None
        if kind != "as-is":
            rng = pair_rng(seed, *names, kind, str(attempt))
            window, z = closeup_window(image_b.shape[:2], xb, rng, zoom_range)
            turns = int(rng.integers(1, 4)) if kind == "closeup-turned" else 0
            b = cut_closeup(image_b, window, turns)
            H, W = image_b.shape[:2]
            pb = _apply(window_pixels(window, (W, H), turns), xb)
            keep = (pb >= -0.5).all(1) & (pb[:, 0] <= b.shape[1] - 0.5) & (pb[:, 1] <= b.shape[0] - 0.5)
            pa, pb = xa[keep], pb[keep]
        log_s = point_log_scales(pa, pb, neighbours)
        ok = np.isfinite(log_s)
        if ok.sum() >= min_points:
            return LabelledPair(*names, kind, image_a, b, pa[ok], log_s[ok], z, turns, window)
    return None


def values_at(pred, xy: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A prediction (map or number) at the points ``xy`` (nearest pixel)."""
    if np.ndim(pred) == 0:
        return np.full(len(xy), float(pred))
    col = np.clip(np.rint(xy[:, 0]).astype(int), 0, shape[1] - 1)
    row = np.clip(np.rint(xy[:, 1]).astype(int), 0, shape[0] - 1)
    return np.asarray(pred, np.float64)[row, col]


def error_factor(values: np.ndarray, log_truth: np.ndarray) -> float:
    """``exp(mean |ln(pred / truth)|)``; a non-positive or non-finite prediction counts as a
    factor of 64 (the models' range is 1/8..8)."""
    v = np.asarray(values, np.float64)
    ok = np.isfinite(v) & (v > 0)
    err = np.full(len(v), math.log(64.0))
    err[ok] = np.minimum(np.abs(np.log(v[ok]) - log_truth[ok]), math.log(64.0))
    return float(np.exp(err.mean()))


def score_pair(pair: LabelledPair, predictor: str, models: ScaleModels, ctx: Optional[PairContext] = None) -> dict:
    """One predictor on one labelled pair: ``error`` (factor) and ``median`` (of the prediction at the points)."""
    ctx = ctx or PairContext(pair.image_a, pair.image_b, models)
    v = values_at(predict(predictor, ctx), pair.xy_a, pair.image_a.shape[:2])
    return {"error": error_factor(v, pair.log_truth), "median": float(np.median(v))}


def choose_pairs(
    pairs: list[CovisiblePair], max_pairs: Optional[int], seed: int, collection: str
) -> list[CovisiblePair]:
    """Up to ``max_pairs`` of ``pairs`` (all when None), drawn from ``seed`` and the collection's name, in file order."""
    if max_pairs is None or max_pairs >= len(pairs):
        return list(pairs)
    idx = pair_rng(seed, collection, "pairs").choice(len(pairs), max_pairs, replace=False)
    return [pairs[i] for i in sorted(idx)]


def evaluate_collection(
    collection: str,
    pairs: list[CovisiblePair],
    kinds,
    predictors: list[str],
    models: ScaleModels,
    load: Callable[[Path], np.ndarray],
    records: Optional[RecordFile] = None,
    seed: int = 0,
    zoom_range=ZOOM_RANGE,
) -> list[dict]:
    """One row per labelled (pair, kind): the pair, ``points``, ``truth`` (exp of the median label),
    ``zoom``, ``turns`` and per predictor :func:`score_pair`; ``skipped`` for too few points."""
    records = records if records is not None else RecordFile(None, {})
    rows = []
    for p in pairs:
        na, nb = Path(p.image_a).name, Path(p.image_b).name
        for kind in kinds:
            base = f"{collection}|{na}|{nb}|{kind}"
            missing = [q for q in predictors if records.get(f"{base}|{q}") is None]
            info = records.get(base)
            if info is None or (missing and not info.get("skipped")):
                lp = labelled_pair(p, kind, load(p.image_a), load(p.image_b), seed, zoom_range)
                info = {"collection": collection, "pair": f"{na} {nb}", "kind": kind, "skipped": lp is None}
                if lp is not None:
                    info |= {"points": len(lp.xy_a), "truth": float(np.exp(np.median(lp.log_truth)))}
                    info |= {"zoom": lp.zoom, "turns": lp.turns}
                    ctx = PairContext(lp.image_a, lp.image_b, models)
                    for q in missing:
                        records.add(f"{base}|{q}", score_pair(lp, q, models, ctx))
                records.add(base, info)
            row = dict(info)
            if not info["skipped"]:
                row |= {q: records.get(f"{base}|{q}") for q in predictors}
            rows.append(row)
    return rows


def summarise(rows: list[dict], predictors: list[str]) -> dict:
    """Mean error factor over pairs, per kind (``all`` collections pooled) and per collection and kind."""

    def block(sel):
        out = {"pairs": len(sel)}
        for q in predictors:
            out[q] = float(np.mean([r[q]["error"] for r in sel])) if sel else float("nan")
        return out

    done = [r for r in rows if not r["skipped"]]
    kinds = list(dict.fromkeys(r["kind"] for r in rows))
    collections = list(dict.fromkeys(r["collection"] for r in rows))
    return {
        "all": {k: block([r for r in done if r["kind"] == k]) for k in kinds},
        "collections": {
            c: {k: block([r for r in done if r["collection"] == c and r["kind"] == k]) for k in kinds}
            for c in collections
        },
        "skipped": sum(r["skipped"] for r in rows),
    }


def markdown(summary: dict, predictors: list[str]) -> str:
    """Mean error factor per kind (pooled), then per collection and kind."""
    head = "| collection | kind | pairs | " + " | ".join(predictors) + " |"
    lines = [head, "|---|---|---|" + "---|" * len(predictors)]
    for c, per_kind in [("all", summary["all"])] + list(summary["collections"].items()):
        for kind, b in per_kind.items():
            lines.append(f"| {c} | {kind} | {b['pairs']} | " + " | ".join(f"{b[q]:.3f}" for q in predictors) + " |")
    return "\n".join(lines) + "\n"
