"""Deprecated: moved to :mod:`localscale.matching.auto.graph`. This module re-exports its names and
goes in the next release."""

import warnings

from ..matching.auto.graph import (
    PairGraph,
    Relation,
)

__all__ = ["PairGraph", "Relation"]

warnings.warn(
    "localscale.sfm.pair_graph is deprecated and goes in the next release: import localscale.matching.auto.graph",
    DeprecationWarning,
    stacklevel=2,
)
