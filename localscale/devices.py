"""Deprecated: moved to :mod:`localscale.core.devices`. This module re-exports its names and goes in the next
release."""

import warnings

from .core.devices import (  # noqa: F401
    resolve_device,
)

__all__ = [
    "resolve_device",
]

warnings.warn(
    "localscale.devices is deprecated, use localscale.core.devices; it goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)
