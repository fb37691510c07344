"""The geometry step: the verified two-view geometry of every matched pair (``geometries.h5``).

Each pair's matches (``keypoints.h5`` / ``matches.h5``) and the two cameras
(:func:`~.cameras.image_cameras`) go to :func:`pycolmap.estimate_two_view_geometry` (COLMAP's own
verification: E, F and H by RANSAC, the configuration that explains the matches, its inliers).
A pair with fewer than ``min_inliers`` inliers, or a degenerate configuration, is kept with no
inlier matches (COLMAP's mapper then ignores it).

Each pair's geometry is estimated once, here (:func:`pair_geometry`). ``auto`` verifies the pairs
as they are with it in the match step (:func:`two_view_of` turns it into the package's
:class:`~localscale.geometry.two_view.TwoViewGeometry` for its decision) and stores it beside the
pair's matches in ``matches.h5``; this step takes a stored geometry whose inputs (:func:`inputs_sha1`)
are those of the pair's matches instead of estimating it again, and so does a rerun with
``geometries.h5``'s own.

Example::

    cams = image_cameras(images, "auto")
    verify_pairs(images, pairs, "out/keypoints.h5", "out/matches.h5", cams, "out/geometries.h5")
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from .config import ReconstructConfig
from .h5io import H5FileError, H5Writer, groups_with, open_h5, read_all_matches, read_group
from .images import names_to_pair
from .progress import progress
from .steps import cameras_of, config_of, parser, run_step, step_images

#: configurations whose inliers are kept (COLMAP's names)
VERIFIED_CONFIGS = ("CALIBRATED", "UNCALIBRATED", "PLANAR", "PANORAMIC", "PLANAR_OR_PANORAMIC")

#: inliers a pair needs (COLMAP's ``min_num_inliers``)
MIN_INLIERS = 15

#: prefix of the datasets and attributes of a geometry stored beside a pair's matches in ``matches.h5``
MATCHED_PREFIX = "two_view_"


@dataclass
class PairGeometry:
    """One pair's estimated two-view geometry: its configuration (COLMAP's name), the datasets of
    ``geometries.h5`` (``inlier_matches`` ``K' x 2`` indices into the keypoints it was estimated on,
    ``F``, ``E``, ``H``, ``R``, ``t`` where known) and the sha1 of its inputs (:func:`inputs_sha1`)."""

    config: str
    data: dict
    inputs_sha1: str = ""


@dataclass
class GeometryStats:
    """Pairs verified, their configurations and inlier counts (by ``(a, b)``), seconds."""

    verified: int = 0
    pairs: dict = field(default_factory=dict)  # (a, b) -> {"config": name, "inliers": n, "matches": m}
    seconds: float = 0.0
    estimator: str = "pycolmap"
    reused: int = 0  # pairs whose stored geometry was kept (same inputs)
    estimated: int = 0  # pairs estimated in this step
    from_matching: int = 0  # pairs whose geometry the match step estimated (``auto``: as they are)

    def to_dict(self) -> dict:
        return {
            "verified": self.verified,
            "pairs": len(self.pairs),
            "estimated": self.estimated,
            "reused": self.reused,
            "from_matching": self.from_matching,
            "estimator": self.estimator,
            "seconds": round(self.seconds, 2),
        }


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
    min_inliers: int = MIN_INLIERS,
    show_progress: bool = True,
) -> GeometryStats:
    """Verify every pair of ``matches_path`` and write ``geometries_path`` (atomically). A pair whose
    inputs (:func:`inputs_sha1`: its matches, their keypoints, the two cameras, ``min_inliers``) are
    those of a geometry already estimated keeps it: one in ``geometries_path`` (a rerun,
    ``stats.reused``) or one stored beside its matches by the match step (``stats.from_matching``).
    The others are estimated (:func:`pair_geometry`, ``stats.estimated``): each pair once."""
    t0 = time.perf_counter()
    stats = GeometryStats()
    names = {im.name for im in images}
    kps = {
        n: read_group(keypoints_path, n, ("keypoints",))["keypoints"]
        for n in groups_with(keypoints_path, "keypoints")
        if n in names
    }
    stored = _stored_inputs(geometries_path)
    matched = read_matched_geometries(matches_path)
    writer = H5Writer(geometries_path, fresh=True)
    matches = read_all_matches(matches_path)
    for (a, b), (m, _) in progress(list(matches.items()), "verify", unit="pair", disable=not show_progress):
        if a not in kps or b not in kps:
            continue
        key = names_to_pair(a, b)
        digest = inputs_sha1(kps[a], kps[b], m, cameras.camera(a), cameras.camera(b), min_inliers)
        if stored.get(key) == digest:
            data = read_group(geometries_path, key)
            config = str(data.pop("attrs")["config"])
            stats.reused += 1
        elif key in matched and matched[key].inputs_sha1 == digest:
            config, data = matched[key].config, matched[key].data
            stats.from_matching += 1
        else:
            g = pair_geometry(kps[a], kps[b], m, cameras.camera(a), cameras.camera(b), min_inliers)
            config, data = g.config, g.data
            stats.estimated += 1
        writer.add(key, data, {"config": config, "name0": a, "name1": b, "inputs_sha1": digest})
        inliers = len(data["inlier_matches"])
        stats.pairs[(a, b)] = {"config": config, "inliers": int(inliers), "matches": int(len(m))}
        stats.verified += int(inliers > 0)
    writer.flush()
    stats.seconds = time.perf_counter() - t0
    return stats


def pair_geometry(points_a, points_b, m, camera_a, camera_b, min_inliers: int = MIN_INLIERS) -> PairGeometry:
    """The :class:`PairGeometry` of one pair (:func:`estimate_pair`): ``points_*`` the images'
    keypoints, ``m`` ``K x 2`` indices into them; fewer than 5 matches are ``DEGENERATE``."""
    m = np.asarray(m, np.int64).reshape(-1, 2)
    g = None if len(m) < 5 else estimate_pair(points_a, points_b, m, camera_a, camera_b, min_inliers)
    config = "DEGENERATE" if g is None else config_name(g)
    inl = np.zeros((0, 2), np.int32) if g is None else np.asarray(g.inlier_matches, np.int32).reshape(-1, 2)
    data = {"inlier_matches": inl}
    if g is not None:
        data.update(
            {k: np.asarray(getattr(g, k), np.float64) for k in ("F", "E", "H") if getattr(g, k, None) is not None}
        )
        pose = getattr(g, "cam2_from_cam1", None)
        if pose is not None and np.linalg.norm(np.asarray(pose.translation)) > 0:
            data.update(R=np.asarray(pose.rotation.matrix(), np.float64), t=np.asarray(pose.translation, np.float64))
    digest = inputs_sha1(points_a, points_b, m, camera_a, camera_b, min_inliers)
    return PairGeometry(config, data, digest)


def two_view_of(g: PairGeometry, m: np.ndarray, S_a=None, S_b=None):
    """``g`` (estimated on the matches ``m``, ``K x 2``) as the package's
    :class:`~localscale.geometry.two_view.TwoViewGeometry`: the model of its configuration, its
    matrices and pose, and the ``K`` inlier mask over ``m``. ``S_a``, ``S_b``: ``3 x 3`` maps from
    the pixels ``g`` was estimated in to those of the result (``H`` and ``F`` follow them)."""
    from ..geometry.two_view import CONFIGURATION_MODEL, TwoViewGeometry

    m = np.asarray(m, np.int64).reshape(-1, 2)
    inl = np.asarray(g.data["inlier_matches"], np.int64).reshape(-1, 2)
    width = int(max(m[:, 1].max(initial=0), inl[:, 1].max(initial=0))) + 1
    mask = np.isin(m[:, 0] * width + m[:, 1], inl[:, 0] * width + inl[:, 1])
    model = CONFIGURATION_MODEL.get(g.config, "none")
    d = dict(g.data)
    if S_a is not None and S_b is not None:
        ia = np.linalg.inv(np.asarray(S_a, np.float64))
        if "H" in d:
            d["H"] = np.asarray(S_b, np.float64) @ d["H"] @ ia
        if "F" in d:
            d["F"] = np.linalg.inv(np.asarray(S_b, np.float64)).T @ d["F"] @ ia
    return TwoViewGeometry(
        g.config, model, len(m), mask, int(mask.sum()), d.get("H"), d.get("F"), d.get("E"), d.get("R"), d.get("t"),
        pose_source={"essential": "E", "fundamental": "F", "homography": "H"}.get(model) if "R" in d else None,
    )  # fmt: skip


def inputs_sha1(points_a, points_b, m, camera_a, camera_b, min_inliers: int = MIN_INLIERS) -> str:
    """The sha1 of what a pair's geometry depends on: its matches, their keypoints, the cameras, ``min_inliers``."""
    m = np.ascontiguousarray(m, np.int64).reshape(-1, 2)
    h = hashlib.sha1(m.tobytes())
    h.update(np.ascontiguousarray(np.asarray(points_a, np.float32)[m[:, 0]]).tobytes())
    h.update(np.ascontiguousarray(np.asarray(points_b, np.float32)[m[:, 1]]).tobytes())
    for cam in (camera_a, camera_b):
        h.update(repr(cam.to_line() if hasattr(cam, "to_line") else cam).encode())
    h.update(str(min_inliers).encode())
    return h.hexdigest()


def _stored_inputs(geometries_path) -> dict:
    """``{pair key: inputs_sha1}`` of the pairs already in ``geometries_path`` (none if it is missing or unreadable)."""
    if not Path(geometries_path).exists():
        return {}
    try:
        with open_h5(geometries_path) as f:
            keys = groups_with(geometries_path, "inlier_matches")
            return {k: str(f[k].attrs["inputs_sha1"]) for k in keys if "inputs_sha1" in f[k].attrs}
    except (OSError, H5FileError):
        return {}


def matched_datasets(g: PairGeometry) -> tuple:
    """``(datasets, attributes)`` that store ``g`` beside a pair's matches in ``matches.h5``."""
    data = {MATCHED_PREFIX + k: v for k, v in g.data.items()}
    return data, {MATCHED_PREFIX + "config": g.config, MATCHED_PREFIX + "inputs_sha1": g.inputs_sha1}


def read_matched_geometries(matches_path) -> dict:
    """``{pair key: PairGeometry}`` stored beside the matches of ``matches_path`` (:func:`matched_datasets`)."""
    out = {}
    if not Path(matches_path).exists():
        return out
    tag = MATCHED_PREFIX + "inlier_matches"
    with open_h5(matches_path) as f:
        for key in groups_with(matches_path, tag):
            grp = f[key]
            data = {k[len(MATCHED_PREFIX) :]: grp[k][()] for k in grp if k.startswith(MATCHED_PREFIX)}
            at = grp.attrs
            out[key] = PairGeometry(str(at[MATCHED_PREFIX + "config"]), data, str(at[MATCHED_PREFIX + "inputs_sha1"]))
    return out


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


def verify_files(images_dir, out_dir, conf: Optional[ReconstructConfig] = None, **kw):
    """The geometry step from the files of ``out_dir``: ``keypoints.h5`` and ``matches.h5`` -> ``geometries.h5``."""
    out, conf = Path(out_dir), conf or ReconstructConfig()
    images = step_images(images_dir, out, conf)
    return verify_pairs(
        images, out / "keypoints.h5", out / "matches.h5", cameras_of(images, conf), out / "geometries.h5", **kw
    )


def main(argv=None) -> int:
    """``python -m localscale.sfm.geometry``: this step alone, from files (:func:`verify_files`)."""
    p = parser("geometry", __doc__, ("camera_mode", "camera_file"))
    p.add_argument("images", help="folder of images (their cameras)")
    p.add_argument("out", help="folder with keypoints.h5 and matches.h5; geometries.h5 is written there")
    args = p.parse_args(argv)
    return run_step(lambda: verify_files(args.images, args.out, config_of(args)))


if __name__ == "__main__":
    raise SystemExit(main())
