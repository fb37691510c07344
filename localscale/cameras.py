"""Deprecated: moved to :mod:`localscale.geometry.cameras`. This module re-exports its names and goes in the next
release."""

import warnings

from .geometry.cameras import (  # noqa: F401
    CAMERA_MODELS,
    PRIOR_FOCAL_FACTOR,
    Camera,
    CameraError,
    CameraLike,
    as_camera,
    camera_prior,
    cut_window,
    import_pycolmap,
    read_camera,
    read_cameras_txt,
    turn_rotation,
    window_camera,
    window_pixels,
)

__all__ = [
    "CAMERA_MODELS",
    "Camera",
    "CameraError",
    "CameraLike",
    "PRIOR_FOCAL_FACTOR",
    "as_camera",
    "camera_prior",
    "cut_window",
    "import_pycolmap",
    "read_camera",
    "read_cameras_txt",
    "turn_rotation",
    "window_camera",
    "window_pixels",
]

warnings.warn(
    "localscale.cameras is deprecated, use localscale.geometry.cameras; it goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)
