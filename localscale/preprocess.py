"""Deprecated: moved to :mod:`localscale.io.preprocess`. This module re-exports its names and goes in the next
release."""

import warnings

from .io.preprocess import (  # noqa: F401
    Letterbox,
    letterbox,
    make_letterbox,
    to_tensor,
)

__all__ = [
    "Letterbox",
    "letterbox",
    "make_letterbox",
    "to_tensor",
]

warnings.warn(
    "localscale.preprocess is deprecated, use localscale.io.preprocess; it goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)
