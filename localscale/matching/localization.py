"""Deprecated: moved to :mod:`localscale.matching.auto.localization`. This module re-exports its names and
goes in the next release."""

import warnings

from .auto.localization import (
    homography_window,
    locate_similarity,
    locate_turn,
    locate_window,
    similarity_votes,
    translation_votes,
)

__all__ = [
    "homography_window",
    "locate_similarity",
    "locate_turn",
    "locate_window",
    "similarity_votes",
    "translation_votes",
]

warnings.warn(
    "localscale.matching.localization is deprecated and goes in the next release: import localscale.matching.auto.localization",
    DeprecationWarning,
    stacklevel=2,
)
