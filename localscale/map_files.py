"""Deprecated: moved to :mod:`localscale.maps.files`. This module re-exports its names and goes in the next
release."""

import warnings

from .maps.files import (  # noqa: F401
    scale_map_paths,
    write_refinement,
    write_scale_map,
)

__all__ = [
    "scale_map_paths",
    "write_refinement",
    "write_scale_map",
]

warnings.warn(
    "localscale.map_files is deprecated, use localscale.maps.files; it goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)
