"""Deprecated: moved to :mod:`localscale.geometry.camera_checks`. This module re-exports its names and goes in the next
release."""

import warnings

from .geometry.camera_checks import (  # noqa: F401
    FOCAL_RATIO_RANGE,
    MAX_TANGENTIAL,
    RADIAL_FACTOR_RANGE,
    check_plausible,
    implausibility,
)

__all__ = [
    "FOCAL_RATIO_RANGE",
    "MAX_TANGENTIAL",
    "RADIAL_FACTOR_RANGE",
    "check_plausible",
    "implausibility",
]

warnings.warn(
    "localscale.camera_checks is deprecated, use localscale.geometry.camera_checks; it goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)
