"""Deprecated: moved to :mod:`localscale.matching.auto.turns`. This module re-exports its names and
goes in the next release."""

import warnings

from .auto.turns import (
    match_turned,
    nearest_turn,
    turn_matrix,
    unturn_points,
)

__all__ = ["match_turned", "nearest_turn", "turn_matrix", "unturn_points"]

warnings.warn(
    "localscale.matching.turns is deprecated and goes in the next release: import localscale.matching.auto.turns",
    DeprecationWarning,
    stacklevel=2,
)
