"""Deprecated: moved to :mod:`localscale.core.outputs`. This module re-exports its names and goes in the next
release."""

import warnings

from .core.outputs import (  # noqa: F401
    NAME_MAX,
    atomic_path,
    check_writable_dir,
    ensure_not_input,
    make_dir,
    replace_dir,
    resolved_path,
    stale_temporaries,
    temporary_name,
    write_bytes,
    write_image,
    write_npy,
    write_npy_bands,
    write_text,
)

__all__ = [
    "NAME_MAX",
    "atomic_path",
    "check_writable_dir",
    "ensure_not_input",
    "make_dir",
    "replace_dir",
    "resolved_path",
    "stale_temporaries",
    "temporary_name",
    "write_bytes",
    "write_image",
    "write_npy",
    "write_npy_bands",
    "write_text",
]

warnings.warn(
    "localscale.outputs is deprecated, use localscale.core.outputs; it goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)
