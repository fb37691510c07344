"""What the scale networks can answer, and the inputs and answers outside it.

Both networks see each image letterboxed into their square frame (``image_size`` pixels,
:mod:`localscale.io.preprocess`) and answer with a distribution over the 13 bins ``x0.125 .. x8``;
the resize of each image into the frame is then corrected (``S = S_frame * f_A / f_B``). So:

* an image thinner than one cell of the feature grid in the frame (a 16 x 5000 strip is 1 pixel
  tall in a 192-pixel frame) or enlarged more than :data:`MAX_ENLARGEMENT` times to fill it (a
  16 x 16 image) shows the network nothing to measure a scale on;
* a scale outside the bins' range after the correction, ``[`` :data:`~localscale.scales.MIN_SCALE`,
  :data:`~localscale.scales.MAX_SCALE` ``]``, comes from the correction, not from the network.

Such predictions are returned, flagged: :func:`limit_reasons` says why, and the predictions'
``reliable`` flag is False (:class:`~localscale.models.scalenet.GlobalScalePrediction`,
:func:`localscale.reliability.check_pair`); the CLI prints a ``warning:`` line.
"""

from __future__ import annotations

import math

from .scales import MAX_SCALE, MIN_SCALE

#: an image enlarged more than this to fill the network's frame is too small to show a scale
MAX_ENLARGEMENT = 4.0
#: pixels of the frame per cell of the feature grid (the backbones' stride)
FEATURE_STRIDE = 8


def frame_reasons(letterbox, name: str) -> list:
    """Why the image placed by ``letterbox`` (:class:`~localscale.io.preprocess.Letterbox`) is too thin
    or too small for the network (empty: it is not)."""
    lb = letterbox
    if min(lb.new_height, lb.new_width) < FEATURE_STRIDE:
        return [
            f"image {name} ({lb.width}x{lb.height}) is {lb.new_width}x{lb.new_height} in the network's "
            f"{lb.size}x{lb.size} frame, thinner than one {FEATURE_STRIDE}-pixel cell of its feature grid"
        ]
    if lb.factor > MAX_ENLARGEMENT:
        return [
            f"image {name} ({lb.width}x{lb.height}) is enlarged x{lb.factor:.1f} to the network's "
            f"{lb.size}x{lb.size} frame (more than x{MAX_ENLARGEMENT:g}): too small to show a scale"
        ]
    return []


def range_reasons(scale: float, what: str = "the scale") -> list:
    """Why ``scale`` cannot come from the network (outside its bins' range after the resize correction)."""
    if math.isfinite(scale) and MIN_SCALE / (1 + 1e-6) <= scale <= MAX_SCALE * (1 + 1e-6):
        return []
    return [
        f"{what} x{scale:.3g} is outside the network's range x{MIN_SCALE:g} to x{MAX_SCALE:g} "
        "(it comes from the images' resize to the network's frame)"
    ]


def limit_reasons(letterbox_a, letterbox_b, scale: float, what: str = "the scale") -> list:
    """:func:`frame_reasons` of both images and :func:`range_reasons` of ``scale``."""
    return frame_reasons(letterbox_a, "A") + frame_reasons(letterbox_b, "B") + range_reasons(scale, what)
