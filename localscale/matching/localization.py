"""Deprecated: moved to :mod:`localscale.matching.auto.localization`. This module re-exports its names and
goes in the next release."""

import warnings

warnings.warn(
    "localscale.matching.localization is deprecated and goes in the next release: import localscale.matching.auto.localization",
    DeprecationWarning,
    stacklevel=2,
)
