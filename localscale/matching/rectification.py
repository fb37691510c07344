"""Scale rectification of a pair: the pair's level from its maps, and the resize factors that bring it to 1.

The dense extractors are scale-rectified: the image whose content is bigger is shrunk by the
pair's level ``S_{A->B}`` (or, for small images, shrunk less and the other one enlarged).
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np


def pair_scale(scale_a=None, scale_b=None) -> float:
    """The pair's level ``S_{A->B}`` from the maps of both images (floats, ``H x W`` maps or
    ``None`` = 1): ``2 ** ((median log2 S_A - median log2 S_B) / 2)`` over finite positive values."""
    levels = []
    for s, sign in ((scale_a, 1.0), (scale_b, -1.0)):
        if s is None:
            levels.append(0.0)
            continue
        v = np.asarray(s, np.float64).ravel()
        v = v[np.isfinite(v) & (v > 0)]
        levels.append(sign * float(np.median(np.log2(v))) if v.size else 0.0)
    return float(2.0 ** (sum(levels) / 2))


def rectify_factors(
    scale: float,
    min_log2: float = 0.0,
    shapes: Optional[tuple] = None,
    min_side: int = 0,
    max_side: Optional[int] = None,
) -> tuple[float, float]:
    """Resize factors ``(for A, for B)`` that bring a pair of scale ``S_{A->B}`` to 1.

    The image whose content is bigger is shrunk (``S > 1``: B by ``1 / S``; ``S < 1``: A by ``S``).
    With ``shapes`` (``((h_A, w_A), (h_B, w_B))``) it is shrunk no further than a longer side of
    ``min_side`` pixels, and the other image is enlarged for the rest, up to a longer side of
    ``max_side`` (None: no enlargement); past that the shrinking goes on. ``|log2 S| <= min_log2``
    leaves both images as they are.
    """
    if not (math.isfinite(scale) and scale > 0) or abs(math.log2(scale)) <= min_log2:
        return 1.0, 1.0
    ratio = scale if scale < 1 else 1.0 / scale  # applied to the image whose content is bigger
    big_first = scale < 1
    f_big, f_small = ratio, 1.0
    if shapes is not None and max_side is not None:
        big, small = (max(shapes[0][:2]), max(shapes[1][:2])) if big_first else (max(shapes[1][:2]), max(shapes[0][:2]))
        f_big = min(1.0, max(ratio, min_side / max(1, big)))
        f_small = min(f_big / ratio, max(1.0, max_side / max(1, small)))
        f_big = ratio * f_small
    return (f_big, f_small) if big_first else (f_small, f_big)
