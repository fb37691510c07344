"""Deprecated: moved to :mod:`localscale.core.errors`. This module re-exports its names and goes in the next
release."""

import warnings

from .core.errors import (  # noqa: F401
    CameraError,
    CheckpointError,
    HomographyError,
    ImageError,
    LocalScaleError,
    OutputError,
)

__all__ = [
    "CameraError",
    "CheckpointError",
    "HomographyError",
    "ImageError",
    "LocalScaleError",
    "OutputError",
]

warnings.warn(
    "localscale.errors is deprecated, use localscale.core.errors; it goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)
