"""Deprecated: moved to :mod:`localscale.geometry.planar`. This module re-exports its names and goes in the next
release."""

import warnings

from .geometry.planar import (  # noqa: F401
    fit_planar_log_scale,
    normalised_grid,
    planar_scale_map,
    planarize,
)

__all__ = [
    "fit_planar_log_scale",
    "normalised_grid",
    "planar_scale_map",
    "planarize",
]

warnings.warn(
    "localscale.planar is deprecated, use localscale.geometry.planar; it goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)
