"""Deprecated: moved to :mod:`localscale.models.anchoring`. This module re-exports its names and goes in the next
release."""

import warnings

from .models.anchoring import (  # noqa: F401
    AnchorConfig,
    anchored_prediction,
)

__all__ = [
    "AnchorConfig",
    "anchored_prediction",
]

warnings.warn(
    "localscale.anchoring is deprecated, use localscale.models.anchoring; it goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)
