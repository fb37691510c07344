"""Sanity pairs from any photo: zooms, quarter turns and rotations with a known scale map.

From one photo ``P`` (``h x w``), a :class:`SanityCase` makes a pair ``(A, B)`` related by a known
homography ``H`` (A -> B), with the truth ``S_{A->B}(x) = sqrt|det J_H(x)|`` and the mask of the
pixels of A that B shows:

* zoom ``z >= 1``: A is ``P``, B the centred window of ``P`` with sides ``1/z`` of its own,
  enlarged back to ``h x w`` (content is ``z`` times bigger in B); the truth inside the window is ``z``;
* zoom ``z < 1``: the other way round: A is the enlarged centred window (``1/z``), B is ``P``;
  the truth is ``z`` everywhere on A;
* ``rotation`` (degrees, counter-clockwise on screen): B is also turned about its centre (the
  corners it no longer covers are black);
* ``turns``: B is finally turned by quarter turns (``np.rot90``, exact).

So ``H = T_turns . R_rotation . M_z`` with ``M_z`` the magnification by ``z`` about the centre, and
the truth is ``z`` wherever A is visible in B (rotations and turns keep sizes).

For each case and predictor (:mod:`.predictors`) the evaluation takes the median of the predicted
map over the visible region against the truth: ``ratio = median / truth``; the case passes when
``|ln ratio| <= ln(1 + tolerance)`` (tolerance 0.1: within 10 % either way).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction
from typing import Iterable, Optional

import cv2
import numpy as np

from ..core.errors import LocalScaleError
from ..geometry import covisible_mask, homography_scale_map, turn_matrix
from .predictors import PairContext, ScaleModels, predict
from .records import RecordFile

#: a case passes when its median is within this factor of the truth (``1 + 0.1``)
TOLERANCE = 0.10


@dataclass(frozen=True)
class SanityCase:
    """``zoom``: the true ``S_{A->B}`` (> 1: B is a magnified window of A; < 1: A one of B);
    ``turns``: quarter turns of B (counter-clockwise); ``rotation``: in-plane rotation of B, degrees."""

    zoom: float = 1.0
    turns: int = 0
    rotation: float = 0.0

    def __post_init__(self):
        if not (math.isfinite(self.zoom) and self.zoom > 0):
            raise LocalScaleError(f"sanity case: zoom must be positive, got {self.zoom}")

    @property
    def name(self) -> str:
        parts = []
        if self.zoom != 1:
            parts.append(f"zoom {_number(self.zoom)}")
        if self.rotation:
            parts.append(f"rot {self.rotation:g}")
        if self.turns % 4:
            parts.append(f"turn {90 * (self.turns % 4)}")
        return " + ".join(parts) or "identity"

    @property
    def group(self) -> str:
        """``identity``, ``zoom``, ``turn``, ``rotation`` or ``combined``."""
        kinds = [k for k, on in (("zoom", self.zoom != 1), ("rotation", self.rotation), ("turn", self.turns % 4)) if on]
        return "identity" if not kinds else kinds[0] if len(kinds) == 1 else "combined"


def _number(z: float) -> str:
    """``4`` or ``1/4`` (``1/1.5`` for a zoom that is not the inverse of a short number)."""
    if z >= 1:
        return f"{z:g}"
    inv = 1 / z
    f = Fraction(inv).limit_denominator(8)
    return f"1/{float(f):g}" if abs(float(f) - inv) < 1e-6 else f"{z:.3g}"


def default_cases(
    zooms: Iterable[float] = (1.5, 2, 3, 4, 6, 8),
    turns: Iterable[int] = (1, 2, 3),
    rotations: Iterable[float] = (30, 45),
    combined_zooms: Iterable[float] = (2, 4),
    combined_with: Iterable[tuple[int, float]] = ((1, 0.0), (0, 45.0)),
) -> list[SanityCase]:
    """The identity; each zoom in both directions (``z`` and ``1/z``); each quarter turn and
    rotation alone; each of ``combined_zooms`` (both directions) with each ``(turns, rotation)``
    of ``combined_with``."""
    cases = [SanityCase()]
    for z in zooms:
        cases += [SanityCase(float(z)), SanityCase(1 / float(z))]
    cases += [SanityCase(turns=int(t)) for t in turns]
    cases += [SanityCase(rotation=float(r)) for r in rotations]
    for z in combined_zooms:
        for t, r in combined_with:
            cases += [SanityCase(float(z), int(t), float(r)), SanityCase(1 / float(z), int(t), float(r))]
    return cases


@dataclass
class SanityPair:
    """A pair of a :class:`SanityCase`: images, ``H`` (A -> B), truth ``S_{A->B}`` and the visible mask (on A)."""

    case: SanityCase
    image_a: np.ndarray
    image_b: np.ndarray
    H: np.ndarray
    truth: np.ndarray
    visible: np.ndarray


def magnification(z: float, shape: tuple[int, int]) -> np.ndarray:
    """``3 x 3``: magnification by ``z`` about the centre of an image of ``shape`` ``(h, w)``."""
    cy, cx = (shape[0] - 1) / 2, (shape[1] - 1) / 2
    return np.array([[z, 0, (1 - z) * cx], [0, z, (1 - z) * cy], [0, 0, 1.0]])


def rotation_about_centre(degrees: float, shape: tuple[int, int]) -> np.ndarray:
    """``3 x 3``: rotation about the centre of an image of ``shape``, counter-clockwise on screen."""
    cy, cx = (shape[0] - 1) / 2, (shape[1] - 1) / 2
    return np.vstack([cv2.getRotationMatrix2D((cx, cy), degrees, 1.0), [0, 0, 1]])


def _warp(photo: np.ndarray, M: np.ndarray) -> np.ndarray:
    if np.allclose(M, np.eye(3)):
        return photo.copy()
    h, w = photo.shape[:2]
    return cv2.warpPerspective(photo, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def make_sanity_pair(photo: np.ndarray, case: SanityCase) -> SanityPair:
    """The pair ``case`` makes from ``photo`` (``h x w x 3``); see the module docstring."""
    shape = photo.shape[:2]
    R = rotation_about_centre(case.rotation, shape) if case.rotation else np.eye(3)
    if case.zoom >= 1:
        warp_a, warp_b = np.eye(3), R @ magnification(case.zoom, shape)
    else:
        warp_a, warp_b = magnification(1 / case.zoom, shape), R
    a, b = _warp(photo, warp_a), _warp(photo, warp_b)
    H = warp_b @ np.linalg.inv(warp_a)
    if case.turns % 4:
        H = turn_matrix(case.turns, b.shape) @ H
        b = np.ascontiguousarray(np.rot90(b, case.turns % 4))
    truth = homography_scale_map(H, *shape).astype(np.float32)
    visible = covisible_mask(H, shape, b.shape[:2]) & np.isfinite(truth)
    return SanityPair(case, a, b, H, truth, visible)


def score_map(pred, truth: np.ndarray, visible: np.ndarray, tolerance: float = TOLERANCE) -> dict:
    """Median of ``pred`` (map or number) over ``visible`` against the truth's median there: the
    median, ``ratio``, ``pass`` and the mean error factor ``exp(mean |ln(pred / truth)|)``."""
    t = truth[visible].astype(np.float64)
    p = np.asarray(pred, np.float64)
    p = np.full_like(t, float(p)) if p.ndim == 0 else p[visible]
    ok = np.isfinite(p) & (p > 0)
    if not ok.any() or not t.size:
        return {"median": float("nan"), "ratio": float("nan"), "pass": False, "error": float("nan")}
    t_med = float(np.median(t))
    med = float(np.median(p[ok]))
    ratio = med / t_med
    return {
        "median": med,
        "ratio": ratio,
        "pass": bool(abs(math.log(ratio)) <= math.log1p(tolerance) + 1e-9),
        "error": float(np.exp(np.abs(np.log(p[ok] / t[ok])).mean())),
    }


def evaluate_photo(
    name: str,
    photo: np.ndarray,
    cases: list[SanityCase],
    predictors: list[str],
    models: ScaleModels,
    records: Optional[RecordFile] = None,
    tolerance: float = TOLERANCE,
) -> list[dict]:
    """One record per case of ``photo``: ``photo``, ``case``, ``group``, ``truth``, ``visible`` (share
    of A) and per predictor :func:`score_map` (computed once per ``records`` key)."""
    records = records if records is not None else RecordFile(None, {})
    out = []
    for case in cases:
        pair, ctx = None, None
        row = {"photo": name, "case": case.name, "group": case.group}
        for p in predictors:
            key = f"{name}|{case.name}|{p}"
            rec = records.get(key)
            if rec is None:
                if pair is None:
                    pair = make_sanity_pair(photo, case)
                    ctx = PairContext(pair.image_a, pair.image_b, models, pair.H)
                rec = score_map(predict(p, ctx), pair.truth, pair.visible, tolerance)
                rec |= {"truth": float(np.median(pair.truth[pair.visible])), "visible": float(pair.visible.mean())}
                records.add(key, rec)
            row["truth"], row["visible"] = rec["truth"], rec["visible"]
            row[p] = {k: rec[k] for k in ("median", "ratio", "pass", "error")}
        out.append(row)
    return out


def summarise(rows: list[dict], predictors: list[str]) -> dict:
    """Per case (in order of first appearance) and predictor: the median over photos of the window
    medians and of the ratios, the passes out of the photos; and the passes per predictor and group."""
    cases: dict[str, dict] = {}
    for r in rows:
        c = cases.setdefault(r["case"], {"case": r["case"], "group": r["group"], "truth": r["truth"], "rows": []})
        c["rows"].append(r)
    table, totals = [], {p: {} for p in predictors}
    for c in cases.values():
        entry = {"case": c["case"], "group": c["group"], "truth": c["truth"], "photos": len(c["rows"])}
        for p in predictors:
            meds = [r[p]["median"] for r in c["rows"]]
            passes = sum(r[p]["pass"] for r in c["rows"])
            entry[p] = {
                "median": float(np.nanmedian(meds)) if np.isfinite(meds).any() else float("nan"),
                "ratio": float(np.nanmedian([r[p]["ratio"] for r in c["rows"]]))
                if np.isfinite(meds).any()
                else float("nan"),
                "passed": int(passes),
            }
            g = totals[p].setdefault(c["group"], [0, 0])
            g[0] += passes
            g[1] += len(c["rows"])
        table.append(entry)
    return {"cases": table, "passed": totals}


def markdown(summary: dict, predictors: list[str]) -> str:
    """The case table: per predictor the median over photos of the visible-region medians and
    ``(passes/photos)``, then the passes per group."""
    lines = [
        "| case | truth | " + " | ".join(predictors) + " |",
        "|---|---|" + "---|" * len(predictors),
    ]
    for e in summary["cases"]:
        cells = [f"{e[p]['median']:.3g} ({e[p]['passed']}/{e['photos']})" for p in predictors]
        lines.append(f"| {e['case']} | {e['truth']:.3g} | " + " | ".join(cells) + " |")
    groups = list(dict.fromkeys(e["group"] for e in summary["cases"]))
    for g in groups + ["all"]:
        cells = []
        for p in predictors:
            t = summary["passed"][p]
            k = sum(v[0] for v in t.values()) if g == "all" else t[g][0]
            n = sum(v[1] for v in t.values()) if g == "all" else t[g][1]
            cells.append(f"{k}/{n}")
        lines.append(f"| passed: {g} | | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
