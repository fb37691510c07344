"""Deprecated: moved to :mod:`localscale.io.image_files`. This module re-exports its names and goes in the next
release."""

import warnings

from .io.image_files import (  # noqa: F401
    TIFF_MAGIC,
    float_file_to_unit,
    read_float_tiff,
    read_header,
)

__all__ = [
    "TIFF_MAGIC",
    "float_file_to_unit",
    "read_float_tiff",
    "read_header",
]

warnings.warn(
    "localscale.image_files is deprecated, use localscale.io.image_files; it goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)
