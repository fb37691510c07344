"""Deprecated: moved to :mod:`localscale.core.lazy`. This module re-exports its names and goes in the next
release."""

import warnings

from .core.lazy import (  # noqa: F401
    lazy_exports,
)

__all__ = [
    "lazy_exports",
]

warnings.warn(
    "localscale.lazy is deprecated, use localscale.core.lazy; it goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)
