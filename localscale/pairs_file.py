"""Deprecated: moved to :mod:`localscale.io.pairs_file`. This module re-exports its names and goes in the next
release."""

import warnings

from .io.pairs_file import (  # noqa: F401
    PAIRS_FORMAT,
    PairsFileError,
    read_pairs_file,
    read_pairs_lines,
)

__all__ = [
    "PAIRS_FORMAT",
    "PairsFileError",
    "read_pairs_file",
    "read_pairs_lines",
]

warnings.warn(
    "localscale.pairs_file is deprecated, use localscale.io.pairs_file; it goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)
