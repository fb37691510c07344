"""The database step: the COLMAP database (pycolmap): cameras, images, keypoints, matches, two-view geometries.

The cameras are those of :func:`~.cameras.image_cameras` (``camera_mode``).

COLMAP's keypoints have the pixel centre at ``(0.5, 0.5)``; ``keypoints.h5`` has it at
``(0, 0)`` (hloc's convention), so 0.5 is added here (as hloc does).

The database is written under a temporary name and renamed: it is complete or absent (the
``-wal``/``-shm`` files an earlier database left beside the name are removed first).
:func:`read_database` reads it back (the tests' round trip).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from ..core.errors import LocalScaleError, OutputError
from ..core.outputs import atomic_path
from .cameras import CameraSetup
from .config import ReconstructConfig
from .h5io import groups_with, read_group
from .steps import cameras_of, config_of, parser, run_step, step_images


def _pycolmap():
    try:
        import pycolmap
    except ImportError:
        raise LocalScaleError("reconstruction needs pycolmap: pip install pycolmap") from None
    return pycolmap


def write_database(
    database_path, images: list, cameras: CameraSetup, keypoints_path, matches_path, geometries_path=None
) -> dict:
    """Write the COLMAP database (module docstring); returns ``{image name: image id}``.

    ``keypoints_path`` / ``matches_path``: :mod:`.match`'s files; ``geometries_path``: the verified
    two-view geometries of :mod:`.geometry` (None: none written, COLMAP would verify itself).
    """
    pycolmap = _pycolmap()
    from .geometry import read_geometries
    from .h5io import read_all_matches

    database_path = Path(database_path)
    kp_names = set(groups_with(keypoints_path, "keypoints"))
    matches = read_all_matches(matches_path)
    geometries = read_geometries(geometries_path) if geometries_path is not None else {}
    with atomic_path(database_path) as tmp:
        try:
            db = pycolmap.Database.open(tmp)
            try:
                ids = _fill(pycolmap, db, images, cameras, keypoints_path, kp_names, matches, geometries)
            finally:
                db.close()
        except RuntimeError as e:  # how pycolmap reports SQLite's failures (a full disk)
            free = shutil.disk_usage(database_path.parent).free // 1024
            raise OutputError(
                f"cannot write {database_path}: {str(e).strip().splitlines()[-1]} ({free} KB free on its file system)"
            ) from None
        finally:
            _remove_sidecars(tmp)
        _remove_sidecars(database_path)  # SQLite would replay an old database's log onto the new one
    return ids


def _remove_sidecars(path: Path) -> None:
    """Remove the ``-wal``, ``-shm`` and ``-journal`` files SQLite keeps beside the database ``path``."""
    for sidecar in ("-wal", "-shm", "-journal"):
        Path(f"{path}{sidecar}").unlink(missing_ok=True)


def _fill(pycolmap, db, images, cameras, keypoints_path, kp_names, matches, geometries) -> dict:
    """Write the cameras, images, keypoints, matches and two-view geometries into ``db``; returns the image ids."""
    ids = {}
    cam_ids = {}
    for cid, camera in cameras.cameras.items():
        cam = camera.to_pycolmap()
        cam.camera_id = cid
        cam_ids[cid] = db.write_camera(cam, use_camera_id=True)
        rig = pycolmap.Rig(rig_id=cid)
        rig.add_ref_sensor(cam.sensor_id)
        db.write_rig(rig, use_rig_id=True)
    for i, im in enumerate(images, 1):
        cid = cam_ids[cameras.of_image[im.name]]
        image = pycolmap.Image(name=im.name, camera_id=cid, image_id=i)
        ids[im.name] = db.write_image(image, use_image_id=True)
        frame = pycolmap.Frame(frame_id=i, rig_id=cid)
        frame.add_data_id(image.data_id)
        db.write_frame(frame, use_frame_id=True)
        kps = (
            read_group(keypoints_path, im.name, ("keypoints",))["keypoints"]
            if im.name in kp_names
            else np.zeros((0, 2), np.float32)
        )
        db.write_keypoints(ids[im.name], np.ascontiguousarray(kps, np.float32) + 0.5)
    for (a, b), (m, _) in matches.items():
        if a in ids and b in ids:
            db.write_matches(ids[a], ids[b], np.ascontiguousarray(m, np.uint32))
    for (a, b), g in geometries.items():
        if a in ids and b in ids:
            db.write_two_view_geometry(ids[a], ids[b], g)
    return ids


@dataclass
class DatabaseContents:
    """What :func:`read_database` reads: cameras (id -> pycolmap.Camera), image ids by name,
    keypoints by name (``N x 2`` float32, keypoints.h5's convention: 0.5 subtracted), matches and
    two-view geometries (``(config name, K x 2 inlier matches)``) by ``(name_a, name_b)``."""

    cameras: dict
    images: dict
    keypoints: dict
    matches: dict
    geometries: dict


def read_database(database_path) -> DatabaseContents:
    pycolmap = _pycolmap()
    from .geometry import config_name

    path = Path(database_path)
    if not path.is_file():
        raise LocalScaleError(f"database not found: {path}")
    db = pycolmap.Database.open(path)
    try:
        cameras = {c.camera_id: c for c in db.read_all_cameras()}
        images = {im.name: im.image_id for im in db.read_all_images()}
        names = {v: k for k, v in images.items()}
        keypoints = {n: np.asarray(db.read_keypoints(i), np.float32)[:, :2] - 0.5 for n, i in images.items()}
        matches, geometries = {}, {}
        for pair_id, m in zip(*db.read_all_matches()):
            i, j = pycolmap.pair_id_to_image_pair(pair_id)
            matches[(names[i], names[j])] = np.asarray(m, np.int64).reshape(-1, 2)
        pair_ids, tvgs = db.read_two_view_geometries()
        for pair_id, g in zip(pair_ids, tvgs):
            i, j = pycolmap.pair_id_to_image_pair(pair_id)
            geometries[(names[i], names[j])] = (config_name(g), np.asarray(g.inlier_matches, np.int64).reshape(-1, 2))
    finally:
        db.close()
    return DatabaseContents(cameras, images, keypoints, matches, geometries)


def database_of_files(images_dir, out_dir, conf: Optional[ReconstructConfig] = None):
    """The database step from the files of ``out_dir``: the h5 files -> ``database.db``."""
    out, conf = Path(out_dir), conf or ReconstructConfig()
    images = step_images(images_dir, out, conf)
    files = (out / "keypoints.h5", out / "matches.h5", out / "geometries.h5")
    return write_database(out / "database.db", images, cameras_of(images, conf), *files)


def main(argv=None) -> int:
    """``python -m localscale.sfm.database``: this step alone, from files (:func:`database_of_files`)."""
    p = parser("database", __doc__, ("camera_mode", "camera_file"))
    p.add_argument("images", help="folder of images (their cameras)")
    p.add_argument("out", help="folder with the h5 files; database.db is written there")
    args = p.parse_args(argv)
    return run_step(lambda: database_of_files(args.images, args.out, config_of(args)))


if __name__ == "__main__":
    raise SystemExit(main())
