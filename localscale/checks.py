"""Deprecated: moved to :mod:`localscale.core.checks`. This module re-exports its names and goes in the next
release."""

import warnings

from .core.checks import (  # noqa: F401
    check_choice,
    check_int,
    check_number,
)

__all__ = [
    "check_choice",
    "check_int",
    "check_number",
]

warnings.warn(
    "localscale.checks is deprecated, use localscale.core.checks; it goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)
