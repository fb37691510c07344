"""Plausibility of a camera given as input (a ``cameras.txt`` line, a camera file, a dict).

:class:`~localscale.geometry.cameras.Camera` takes any finite parameters with positive focal lengths (a
window cut from an image has its principal point outside it). A camera a user gives is checked
further, so that a typing error is one ``error:`` line and not an empty reconstruction:

* focal lengths within :data:`FOCAL_RATIO_RANGE` times the longer side of the image;
* the principal point at most one image width (height) outside the image;
* distortion that keeps the image's corners: the radial factor ``r_d / r`` within
  :data:`RADIAL_FACTOR_RANGE` from the centre to the farthest corner, tangential terms within
  ``+-`` :data:`MAX_TANGENTIAL`.

The bounds are wide (a fisheye's focal length is about 0.3 x the side, a long telephoto's 30 x);
they refuse what no lens makes.
"""

from __future__ import annotations

import numpy as np

from ..core.errors import CameraError

#: focal length over the longer side of the image
FOCAL_RATIO_RANGE = (0.05, 50.0)
#: the radial distortion's factor (distorted over undistorted radius) from the centre to the corners
RADIAL_FACTOR_RANGE = (0.1, 10.0)
#: the tangential terms p1, p2
MAX_TANGENTIAL = 1.0


def check_plausible(camera, source: str = "camera"):
    """``camera`` (a :class:`~localscale.geometry.cameras.Camera`) when its intrinsics are plausible
    (module docstring), else a :class:`CameraError` naming ``source`` and what is wrong."""
    problem = implausibility(camera)
    if problem:
        raise CameraError(f"{source}: {problem} ({camera.to_line()})")
    return camera


def implausibility(camera) -> str:
    """What is implausible about ``camera``'s intrinsics ('' when nothing)."""
    w, h = camera.width, camera.height
    fx, fy = camera.focal_lengths
    lo, hi = FOCAL_RATIO_RANGE
    for name, f in (("fx", fx), ("fy", fy)):
        if not lo <= f / max(w, h) <= hi:
            return (
                f"focal length {name} = {f:.4g} px is {f / max(w, h):.3g} x the image's longer side "
                f"({max(w, h)} px); a lens gives {lo:g} to {hi:g} x"
            )
    cx, cy = camera.principal_point
    if not (-w <= cx <= 2 * w and -h <= cy <= 2 * h):
        return (
            f"principal point ({cx:.4g}, {cy:.4g}) is far outside the {w}x{h} image "
            f"(more than one image size away; it is near the centre, ({w / 2:g}, {h / 2:g}), for most cameras)"
        )
    return _distortion_problem(camera)


def _distortion_problem(camera) -> str:
    d = np.zeros(8)
    d[: len(camera.dist())] = camera.dist()
    k1, k2, p1, p2, k3, k4, k5, k6 = d
    if max(abs(p1), abs(p2)) > MAX_TANGENTIAL:
        return f"tangential distortion p1 = {p1:.4g}, p2 = {p2:.4g} is beyond +-{MAX_TANGENTIAL:g}"
    if not camera.has_distortion:
        return ""
    K = camera.K_colmap()
    corners = np.array([[0, 0], [camera.width, 0], [0, camera.height], [camera.width, camera.height]], float)
    r_max = float(np.max(np.hypot((corners[:, 0] - K[0, 2]) / K[0, 0], (corners[:, 1] - K[1, 2]) / K[1, 1])))
    r2 = np.linspace(0.0, r_max, 64) ** 2
    with np.errstate(all="ignore"):
        factor = (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
    lo, hi = RADIAL_FACTOR_RANGE
    if not np.all(np.isfinite(factor)) or factor.min() < lo or factor.max() > hi:
        worst = factor[np.nanargmax(np.abs(np.log(np.abs(factor) + 1e-300)))] if np.isfinite(factor).any() else np.nan
        return (
            f"radial distortion (k = {', '.join(f'{v:.4g}' for v in (k1, k2, k3, k4, k5, k6) if v)}) scales the "
            f"radius by {worst:.3g} within the image; a lens gives {lo:g} to {hi:g}"
        )
    return ""
