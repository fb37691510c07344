"""What anchors a Local-ScaleNet pass: ScaleNet's global scale and quarter turn of a pair
(used by :mod:`localscale.models.anchoring`).

Example::

    anchor = anchor_of(ScaleNet.from_pretrained().predict("a.jpg", "b.jpg"))
    anchor.scale, anchor.turns
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: the anchor scale is kept within the range of the networks' bins (2^-3 .. 2^3)
MAX_ANCHOR_LOG2 = 3.0


@dataclass(frozen=True)
class Anchor:
    """ScaleNet's ``S_{A->B}`` and the quarter turns (counter-clockwise, ``np.rot90``) of B that
    bring it upright relative to A; ``reliable``: ScaleNet's consistency flag."""

    scale: float = 1.0
    turns: int = 0
    reliable: bool = True

    def swapped(self) -> "Anchor":
        """The anchor of the pair B, A."""
        return Anchor(1.0 / self.scale, (-self.turns) % 4, self.reliable)

    def to_dict(self) -> dict:
        return {"scale": self.scale, "turns": self.turns, "reliable": self.reliable}


def anchor_of(global_pred) -> Anchor:
    """The :class:`Anchor` of a :class:`~localscale.models.scalenet.GlobalScalePrediction`: its
    scale (clamped to ``2^+-MAX_ANCHOR_LOG2``; 1 when not finite) and B's turns relative to A."""
    s = float(global_pred.scale)
    if not (math.isfinite(s) and s > 0):
        return Anchor(1.0, 0, False)
    s = 2.0 ** float(np.clip(math.log2(s), -MAX_ANCHOR_LOG2, MAX_ANCHOR_LOG2))
    turns_a, turns_b = global_pred.turns
    return Anchor(s, (turns_b - turns_a) % 4, bool(global_pred.reliable))


def turned(rgb: np.ndarray, shape: tuple[int, int], turns: int) -> tuple[np.ndarray, tuple[int, int]]:
    """An image and its full size ``(H, W)`` after ``turns`` quarter turns (counter-clockwise)."""
    if turns % 4 == 0:
        return rgb, tuple(shape)
    rgb = np.ascontiguousarray(np.rot90(rgb, turns))
    return rgb, (tuple(shape[::-1]) if turns % 2 else tuple(shape))
