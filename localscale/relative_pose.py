"""Deprecated: moved to :mod:`localscale.geometry.relative_pose`. This module re-exports its names and goes in the next
release."""

import warnings

from .geometry.relative_pose import (  # noqa: F401
    epipolar_errors,
    median_triangulation_angle,
    pose_auc,
    pose_from_essential,
    pose_from_homography,
    refine_relative_pose,
    relative_pose_error,
    rotation_fit,
    skew,
)

__all__ = [
    "epipolar_errors",
    "median_triangulation_angle",
    "pose_auc",
    "pose_from_essential",
    "pose_from_homography",
    "refine_relative_pose",
    "relative_pose_error",
    "rotation_fit",
    "skew",
]

warnings.warn(
    "localscale.relative_pose is deprecated, use localscale.geometry.relative_pose; it goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)
