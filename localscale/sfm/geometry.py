"""Step 4: the verified two-view geometry of every matched pair (``geometries.h5``).

Each pair's matches (``keypoints.h5`` / ``matches.h5``) and the two cameras
(:func:`~.database.image_cameras`) go to :func:`localscale.two_view.estimate_two_view_geometry`
when that module exists, else to :func:`pycolmap.estimate_two_view_geometry` (COLMAP's own
verification: E, F and H by RANSAC, the configuration that explains the matches, its inliers).
A pair with fewer than ``min_inliers`` inliers, or a degenerate configuration, is kept with no
inlier matches (COLMAP's mapper then ignores it).

Example::

    cams = image_cameras(images, "auto")
    verify_pairs(images, pairs, "out/keypoints.h5", "out/matches.h5", cams, "out/geometries.h5")
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .h5io import H5Writer, groups_with, open_h5, read_group
from .images import names_to_pair
from .match import read_all_matches
from .progress import progress

#: configurations whose inliers are kept (COLMAP's names)
VERIFIED_CONFIGS = ("CALIBRATED", "UNCALIBRATED", "PLANAR", "PANORAMIC", "PLANAR_OR_PANORAMIC")


@dataclass
class GeometryStats:
    """Pairs verified, their configurations and inlier counts (by ``(a, b)``), seconds."""

    verified: int = 0
    pairs: dict = field(default_factory=dict)  # (a, b) -> {"config": name, "inliers": n, "matches": m}
    seconds: float = 0.0
    estimator: str = "pycolmap"

    def to_dict(self) -> dict:
        return {
            "verified": self.verified,
            "pairs": len(self.pairs),
            "estimator": self.estimator,
            "seconds": round(self.seconds, 2),
        }


def _two_view_module():
    try:
        from ..matching import two_view
    except ImportError:
        return None
    return two_view if hasattr(two_view, "estimate_two_view_geometry") else None


def _as_pycolmap(tv, matches: np.ndarray):
    """A ``pycolmap.TwoViewGeometry`` from the project's two-view result (configuration name or
    value, F, E, H, inlier mask over ``matches``)."""
    import pycolmap

    g = pycolmap.TwoViewGeometry()
    config = getattr(tv, "configuration", getattr(tv, "config", "UNDEFINED"))
    name = config if isinstance(config, str) else getattr(config, "name", str(config))
    g.config = pycolmap.TwoViewGeometryConfiguration.__members__.get(
        str(name).upper(), pycolmap.TwoViewGeometryConfiguration.UNDEFINED
    )
    mask = getattr(tv, "inlier_mask", getattr(tv, "inliers", None))
    mask = np.zeros(len(matches), bool) if mask is None else np.asarray(mask, bool).reshape(-1)
    g.inlier_matches = np.ascontiguousarray(matches[mask], np.uint32).reshape(-1, 2)
    for k in ("F", "E", "H"):
        v = getattr(tv, k, None)
        if v is not None:
            setattr(g, k, np.asarray(v, np.float64))
    R, t = getattr(tv, "R", None), getattr(tv, "t", None)
    if R is not None and t is not None:
        g.cam2_from_cam1 = pycolmap.Rigid3d(
            pycolmap.Rotation3d(np.asarray(R, np.float64)), np.asarray(t, np.float64).reshape(3)
        )
    return g


def _to_pycolmap(camera):
    return camera.to_pycolmap() if hasattr(camera, "to_pycolmap") else camera


def config_name(g) -> str:
    """The name of a ``pycolmap.TwoViewGeometry``'s configuration (pycolmap gives an enum or an int)."""
    import pycolmap

    c = g.config
    return c.name if hasattr(c, "name") else pycolmap.TwoViewGeometryConfiguration(int(c)).name


def estimate_pair(
    points_a: np.ndarray, points_b: np.ndarray, matches: np.ndarray, camera_a, camera_b, min_inliers: int = 15
):
    """The ``pycolmap.TwoViewGeometry`` of one pair: ``points_*`` are the images' keypoints
    (keypoints.h5's convention), ``matches`` ``K x 2`` indices into them."""
    import pycolmap

    mod = _two_view_module()
    if mod is not None:
        tv = mod.estimate_two_view_geometry(points_a[matches[:, 0]], points_b[matches[:, 1]], camera_a, camera_b)
        g = _as_pycolmap(tv, matches)
    else:
        opts = pycolmap.TwoViewGeometryOptions()
        opts.min_num_inliers = min_inliers
        opts.ransac.random_seed = 0
        g = pycolmap.estimate_two_view_geometry(
            _to_pycolmap(camera_a),
            np.asarray(points_a, np.float64) + 0.5,
            _to_pycolmap(camera_b),
            np.asarray(points_b, np.float64) + 0.5,
            np.ascontiguousarray(matches, np.uint32),
            opts,
        )
    if config_name(g) not in VERIFIED_CONFIGS or len(g.inlier_matches) < min_inliers:
        g.inlier_matches = np.zeros((0, 2), np.uint32)
    return g


def verify_pairs(
    images: list,
    keypoints_path,
    matches_path,
    cameras,
    geometries_path,
    min_inliers: int = 15,
    show_progress: bool = True,
) -> GeometryStats:
    """Verify every pair of ``matches_path`` and write ``geometries_path`` (anew, atomically)."""
    t0 = time.perf_counter()
    stats = GeometryStats(estimator="localscale.two_view" if _two_view_module() else "pycolmap")
    names = {im.name for im in images}
    kps = {
        n: read_group(keypoints_path, n, ("keypoints",))["keypoints"]
        for n in groups_with(keypoints_path, "keypoints")
        if n in names
    }
    writer = H5Writer(geometries_path, fresh=True)
    matches = read_all_matches(matches_path)
    for (a, b), (m, _) in progress(list(matches.items()), "verify", unit="pair", disable=not show_progress):
        if a not in kps or b not in kps:
            continue
        if len(m) < 5:
            g = None
        else:
            g = estimate_pair(kps[a], kps[b], m, cameras.camera(a), cameras.camera(b), min_inliers)
        config = "DEGENERATE" if g is None else config_name(g)
        inl = np.zeros((0, 2), np.int32) if g is None else np.asarray(g.inlier_matches, np.int32).reshape(-1, 2)
        data = {"inlier_matches": inl}
        if g is not None:
            data.update(
                {k: np.asarray(getattr(g, k), np.float64) for k in ("F", "E", "H") if getattr(g, k, None) is not None}
            )
            pose = getattr(g, "cam2_from_cam1", None)
            if pose is not None and np.linalg.norm(np.asarray(pose.translation)) > 0:
                data.update(
                    R=np.asarray(pose.rotation.matrix(), np.float64), t=np.asarray(pose.translation, np.float64)
                )
        writer.add(names_to_pair(a, b), data, {"config": config, "name0": a, "name1": b})
        stats.pairs[(a, b)] = {"config": config, "inliers": int(len(inl)), "matches": int(len(m))}
        stats.verified += int(len(inl) > 0)
    writer.flush()
    stats.seconds = time.perf_counter() - t0
    return stats


def read_geometries(geometries_path) -> dict:
    """``{(name_a, name_b): pycolmap.TwoViewGeometry}`` of ``geometries.h5``."""
    import pycolmap

    out = {}
    if geometries_path is None or not Path(geometries_path).exists():
        return out
    keys = groups_with(geometries_path, "inlier_matches")
    with open_h5(geometries_path) as f:
        for key in keys:
            grp = f[key]
            g = pycolmap.TwoViewGeometry()
            g.config = pycolmap.TwoViewGeometryConfiguration.__members__[str(grp.attrs["config"])]
            g.inlier_matches = np.ascontiguousarray(grp["inlier_matches"][()], np.uint32).reshape(-1, 2)
            for k in ("F", "E", "H"):
                if k in grp:
                    setattr(g, k, np.asarray(grp[k][()], np.float64))
            if "R" in grp and "t" in grp:
                g.cam2_from_cam1 = pycolmap.Rigid3d(pycolmap.Rotation3d(grp["R"][()]), grp["t"][()])
            out[(str(grp.attrs["name0"]), str(grp.attrs["name1"]))] = g
    return out
