"""Deprecated: moved to :mod:`localscale.matching.auto.hypotheses`. This module re-exports its names and
goes in the next release."""

import warnings

from .auto.hypotheses import (
    Hypothesis,
    propose,
)

__all__ = ["Hypothesis", "propose"]

warnings.warn(
    "localscale.matching.hypotheses is deprecated and goes in the next release: import localscale.matching.auto.hypotheses",
    DeprecationWarning,
    stacklevel=2,
)
