"""Geometry of image pairs: homographies and their scale fields, the planar prior, cameras, and
the two-view geometry (essential matrix, homography or rotation) and relative pose of a match set.

* :mod:`.homography`: analytic scale maps of a homography, random homographies, warping;
  its names are also this package's (``localscale.geometry.project``).
* :mod:`.planar`: the scale field a homography can produce, fitted to a scale map.
* :mod:`.cameras`: pinhole cameras with COLMAP's models; :mod:`.camera_checks`: plausible intrinsics.
* :mod:`.two_view`: two-view geometry of a match set; :mod:`.relative_pose`: pose, triangulation
  angles and pose error.

The submodules (NumPy, OpenCV, torch) are imported on first use of a name.
"""

from ..core.lazy import lazy_exports

_EXPORTS = {
    ".homography": (
        "HomographyConfig",
        "central_crop",
        "covisible_mask",
        "global_scale",
        "grid_points",
        "homography_rotation",
        "homography_rotation_at",
        "homography_scale_at",
        "homography_scale_map",
        "orient_homography",
        "perspective_spread",
        "project",
        "sample_homography",
        "translation",
        "turn_matrix",
        "warp_image",
    )
}
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
