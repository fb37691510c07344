"""The hypotheses of ``correction="auto"``: a scale and a quarter turn of B (with, optionally, the
maps of the patch matcher or a window), and those the networks propose, strongest evidence first.

Quarter turns are counter-clockwise, as :func:`numpy.rot90`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np


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
    from .correction import weighted_quantile

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
    from .correction import CorrectionGate

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
