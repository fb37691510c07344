"""Deprecated: the steps of ``auto`` on a collection moved to
:mod:`localscale.matching.auto.collection`. This module keeps the old call
(:func:`match_with_graph` with the keypoint sets and the output) and goes in the next release."""

import warnings

from ..matching.auto import collection
from ..matching.auto.collection import TURN_INLIERS

warnings.warn(
    "localscale.sfm.auto_graph is deprecated and goes in the next release: import localscale.matching.auto.collection",
    DeprecationWarning,
    stacklevel=2,
)


def match_with_graph(run_items, todo, sets, output, stats, flush_s: float, same_log2: float, turn_inliers=TURN_INLIERS):
    """:func:`localscale.matching.auto.collection.match_with_graph`, the settled pairs written to
    ``output`` (:func:`~.match.apply_in_order`)."""
    from .match import apply_in_order

    def apply(results, pairs):
        apply_in_order(results, pairs, sets, output, stats, flush_s)

    collection.match_with_graph(run_items, todo, apply, stats, same_log2, turn_inliers)
