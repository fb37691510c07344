"""The hypotheses of ``correction="auto"``: a scale and a quarter turn of B (with, optionally, the
maps of the patch matcher or a window), and those the networks propose, strongest evidence first.

Quarter turns are counter-clockwise, as :func:`numpy.rot90`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional

import cv2
import numpy as np

from .localization import homography_window
from .turns import nearest_turn

if TYPE_CHECKING:
    from ..verification import VerificationResult


@dataclass
class Hypothesis:
    """A guess of the pair's relation: B turned by ``turn`` quarter turns, then ``S_{A->B} = scale``.

    ``maps``: ``(map of A, map of B)`` for the patch matcher (B's in the turned frame); ``None``: the
    constant ``scale`` and ``1 / scale``. ``window``: ``(image, x0, y0, x1, y1)``, the part of A
    (``image`` 0) or B (1, before its turn) that the other image shows, in its pixels; only that part
    is matched (a verified geometry's, so that the wide view of a strong zoom is enlarged rather
    than the zoomed view shrunk)."""

    scale: float
    turn: int
    source: str
    maps: Optional[tuple] = None
    window: Optional[tuple] = None

    def describe(self) -> str:
        turn = f", B turned {90 * self.turn} deg" if self.turn else ""
        window = f", in a window of {'AB'[self.window[0]]}" if self.window else ""
        return f"{self.source}: x{self.scale:.3g}{turn}{window}"


def _level(pred, gate) -> float:
    """The level of a Local-ScaleNet map over the part of A that B shows (weighted median, log2)."""
    from ..correction import weighted_quantile

    s = np.asarray(pred.scale, np.float64).ravel()
    w = gate.weights_of(pred)
    w = None if w is None else np.asarray(w, np.float64).ravel()
    ok = np.isfinite(s) & (s > 0)
    return float(2.0 ** weighted_quantile(np.log2(s[ok]), None if w is None else w[ok], 0.5)) if ok.any() else 1.0


def propose(
    image_a: np.ndarray,
    image_b: np.ndarray,
    local_model=None,
    global_model=None,
    gate=None,
    patches: bool = False,
    bf16: bool = False,
) -> tuple:
    """The hypotheses of the networks, strongest evidence first, and a function that ranks B's
    quarter turns at a scale (called only when the first hypotheses fail).

    Returns ``(hypotheses, more, maps)``: ``more(scale) -> [Hypothesis, ...]`` gives B's three other
    quarter turns ranked by ScaleNet's consistency on each; ``maps`` are Local-ScaleNet's ungated
    ``(S_{A->B} on A, S_{B->A} on B)`` (``None`` without a local model).
    """
    from ..correction import CorrectionGate

    gate = gate or CorrectionGate()
    out, maps_ab = [], None
    if global_model is not None:
        g = global_model.predict(image_a, image_b, bf16=bf16)
        if math.isfinite(g.scale) and g.scale > 0:
            turn = (g.turns[1] - g.turns[0]) % 4
            out.append(Hypothesis(float(g.scale), turn, "ScaleNet" + (" (turned)" if turn else "")))
    if local_model is not None:
        pa = local_model.predict(image_a, image_b, bf16=bf16)
        pb = local_model.predict(image_b, image_a, bf16=bf16)
        level = math.sqrt(_level(pa, gate) / _level(pb, gate))
        maps = gate.apply_predictions(pa, pb) if patches else None
        out.append(Hypothesis(level, 0, "Local-ScaleNet", maps))
        maps_ab = (np.asarray(pa.scale, np.float32), np.asarray(pb.scale, np.float32))
    out.append(Hypothesis(1.0, 0, "identity"))

    def more(scale: float) -> list:
        if global_model is None:
            return [Hypothesis(scale, k, "turn") for k in (2, 1, 3)]
        ranked = []
        for k in (1, 2, 3):
            p = global_model.predict(image_a, np.rot90(image_b, k), bf16=bf16, turns=False)
            ranked.append(
                (
                    p.inconsistency_log2 if math.isfinite(p.inconsistency_log2) else math.inf,
                    k,
                    float(p.scale) if math.isfinite(p.scale) and p.scale > 0 else scale,
                )
            )
        return [Hypothesis(s, k, "ScaleNet turn") for _, k, s in sorted(ranked)]

    return out, more, maps_ab


def already_tried(h: Hypothesis, tried: list, same_log2: float) -> bool:
    return any(
        t.turn == h.turn
        and abs(math.log2(h.scale) - math.log2(t.scale)) < same_log2
        and (h.maps is None) == (t.maps is None)
        and (h.window is None) == (t.window is None)
        for t in tried
    )


def geometry_hypothesis(v: VerificationResult, margin: float = 0.25, max_share: float = 0.5) -> Optional[Hypothesis]:
    """The ``(scale, quarter turn of B)`` that a verified result's own geometry implies: the
    median geometric scale at its inliers, and the quarter turn of B that brings the homography's
    rotation at the inliers' centre closest to none, and the window of the image whose content is
    smaller that the other image covers under it (its bounding box grown by ``margin`` on each
    side), when that is at most ``max_share`` of it; for a fundamental or essential matrix, a
    similarity fitted to the inliers stands in for the homography. ``None`` if it did not verify."""
    if not v.verified or v.num_inliers == 0:
        return None
    inl = np.asarray(v.inliers, bool)
    s = np.asarray(v.local_scales, np.float64)[inl]
    s = s[np.isfinite(s) & (s > 0)]
    if not len(s):
        return None
    scale = float(np.exp(np.median(np.log(s))))
    pa, pb = np.asarray(v.points_a, np.float64)[inl], np.asarray(v.points_b, np.float64)[inl]
    if v.H is not None:
        return mapping_hypothesis(v.H, scale, pa, v.shape_a, v.shape_b, "geometry", margin, max_share)
    # a fundamental or essential matrix: a similarity fitted to the inliers stands in for H
    M, _ = cv2.estimateAffinePartial2D(pa, pb, method=cv2.LMEDS) if len(pa) >= 3 else (None, None)
    if M is None or not np.isfinite(M).all():
        return Hypothesis(scale, 0, "geometry")
    S = np.vstack([M, [0.0, 0.0, 1.0]])
    return mapping_hypothesis(S, scale, pa, v.shape_a, v.shape_b, "geometry", margin, max_share)


def mapping_hypothesis(
    H: np.ndarray,
    scale: float,
    points_a: np.ndarray,
    shape_a: tuple,
    shape_b: tuple,
    source: str,
    margin: float = 0.25,
    max_share: float = 0.5,
) -> Hypothesis:
    """The hypothesis of a mapping ``H`` (``3 x 3``, A's pixels to B's) at ``scale``: the quarter
    turn of B that brings its rotation at the centre of ``points_a`` (``N x 2``) closest to none, and
    the window of the image whose content is smaller that the other covers (:func:`homography_window`)."""
    turn = nearest_turn(H, np.asarray(points_a, np.float64).reshape(-1, 2).mean(0), shape_b)
    return Hypothesis(scale, turn, source, window=homography_window(H, scale, shape_a, shape_b, margin, max_share))


# ---------------------------------------------------------------- the loop
