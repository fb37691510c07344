"""Deprecated: moved to :mod:`localscale.geometry.two_view`. This module re-exports its names and goes in the next
release."""

import warnings

from .geometry.two_view import (  # noqa: F401
    CONFIGURATION_MODEL,
    CONFIGURATIONS,
    TwoViewConfig,
    TwoViewError,
    TwoViewGeometry,
    estimate_two_view_geometry,
)

__all__ = [
    "CONFIGURATIONS",
    "CONFIGURATION_MODEL",
    "TwoViewConfig",
    "TwoViewError",
    "TwoViewGeometry",
    "estimate_two_view_geometry",
]

warnings.warn(
    "localscale.two_view is deprecated, use localscale.geometry.two_view; it goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)
