"""The database step: the COLMAP database (pycolmap): cameras, images, keypoints, matches, two-view geometries.

Cameras (:func:`image_cameras`), ``camera_mode``:

* ``single``: one camera for all images (they must share a size);
* ``per_image``: one camera per image;
* ``auto``: ``single`` when every image has the same size and the same EXIF focal length
  (or none), else ``per_image`` (COLMAP's own rule).

Cameras are :class:`localscale.geometry.cameras.Camera`: COLMAP's guess from the file
(:meth:`~localscale.geometry.cameras.Camera.from_exif`: SIMPLE_RADIAL, focal length from EXIF when there is
one, else 1.2 x the longer side; bundle adjustment refines it), or the camera of ``camera_file``
(``--camera``: one ``cameras.txt`` line or a COLMAP ``cameras.txt`` with one camera, or JSON; used
for every image; its size must be the images' size, or the same aspect ratio, then it is rescaled).

COLMAP's keypoints have the pixel centre at ``(0.5, 0.5)``; ``keypoints.h5`` has it at
``(0, 0)`` (hloc's convention), so 0.5 is added here (as hloc does).

The database is written under a temporary name and renamed: it is complete or absent (the
``-wal``/``-shm`` files an earlier database left beside the name are removed first).
:func:`read_database` reads it back (the tests' round trip).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import LocalScaleError, OutputError
from ..outputs import atomic_path
from .h5io import groups_with, read_group

CAMERA_MODES = ("auto", "single", "per_image")


class CameraFileError(LocalScaleError):
    """A camera file is missing, malformed or does not fit the images."""


def _pycolmap():
    try:
        import pycolmap
    except ImportError:
        raise LocalScaleError("reconstruction needs pycolmap: pip install pycolmap") from None
    return pycolmap


def read_camera_file(path):
    """The one camera of ``path`` (:func:`localscale.geometry.cameras.read_camera`: a ``cameras.txt`` line,
    comments allowed, or JSON; or a COLMAP ``cameras.txt`` holding one camera) as a
    :class:`localscale.geometry.cameras.Camera`. Raises :class:`CameraFileError`."""
    from ..geometry.camera_checks import implausibility
    from ..geometry.cameras import CameraError, read_camera, read_cameras_txt

    path = Path(path)
    if not path.is_file():
        raise CameraFileError(f"camera file not found: {path}")
    try:
        camera = read_camera(path)
    except CameraError as e:
        try:
            cams = read_cameras_txt(path)
        except CameraError:
            raise CameraFileError(str(e)) from None
        if len(cams) != 1:
            raise CameraFileError(
                f"{path}: {len(cams)} cameras; --camera takes a file with one camera, used for every image"
            ) from None
        camera = next(iter(cams.values()))
    problem = implausibility(camera)
    if problem:
        raise CameraFileError(f"camera file {path}: {problem} ({camera.to_line()})")
    return camera


def _fit_camera(camera, shape: tuple, what: str):
    """``camera`` for an image of ``shape`` (H, W): as it is, or rescaled when only the resolution differs."""
    h, w = shape
    if (camera.width, camera.height) == (w, h):
        return camera
    if abs(camera.width / camera.height - w / h) > 0.01:
        raise CameraFileError(
            f"{what} is {camera.width}x{camera.height}, the images are {w}x{h} "
            "(another aspect ratio): give the camera of these images"
        )
    return camera.scaled(w / camera.width, h / camera.height)


@dataclass
class CameraSetup:
    """``cameras`` (camera id -> :class:`localscale.geometry.cameras.Camera`) and ``of_image`` (image name ->
    camera id); ``mode``: the mode used (``auto`` resolved); ``source``: ``exif`` or the camera file."""

    cameras: dict = field(default_factory=dict)
    of_image: dict = field(default_factory=dict)
    mode: str = "per_image"
    source: str = "exif"

    def camera(self, name: str):
        return self.cameras[self.of_image[name]]


def image_cameras(images: list, mode: str = "auto", camera_file=None) -> CameraSetup:
    """The cameras of ``images`` (:class:`~.images.ImageInfo`) under ``mode`` (module docstring)."""
    from ..geometry.cameras import Camera, CameraError

    if mode not in CAMERA_MODES:
        raise LocalScaleError(f"camera mode must be one of {', '.join(CAMERA_MODES)}, got {mode!r}")
    if camera_file is not None:
        given = read_camera_file(camera_file)
        if mode == "per_image":
            cams = {i + 1: _fit_camera(given, im.shape, f"camera of {camera_file}") for i, im in enumerate(images)}
            return CameraSetup(cams, {im.name: i + 1 for i, im in enumerate(images)}, "per_image", str(camera_file))
        shapes = {im.shape for im in images}
        if len(shapes) > 1:
            raise CameraFileError(
                f"--camera {camera_file}: the images have {len(shapes)} sizes; one camera fits one "
                "size (use --camera-mode per_image to rescale it per image)"
            )
        cam = _fit_camera(given, images[0].shape, f"camera of {camera_file}")
        return CameraSetup({1: cam}, {im.name: 1 for im in images}, "single", str(camera_file))
    guessed = []
    for im in images:
        h, w = im.shape
        try:
            cam = Camera.from_exif(im.path)  # EXIF focal length, else COLMAP's prior 1.2 x side
        except CameraError:
            cam = Camera.from_prior(w, h)
        if (cam.width, cam.height) != (w, h):
            cam = Camera.from_prior(w, h)
        guessed.append(cam)
    if mode == "auto":
        mode = "single" if all(c == guessed[0] for c in guessed) else "per_image"
    if mode == "single":
        if len({im.shape for im in images}) > 1:
            raise LocalScaleError(
                "--camera-mode single: the images have different sizes; one camera cannot fit "
                "them (use auto or per_image)"
            )
        return CameraSetup({1: guessed[0]}, {im.name: 1 for im in images}, "single", "exif")
    return CameraSetup(
        {i + 1: c for i, c in enumerate(guessed)}, {im.name: i + 1 for i, im in enumerate(images)}, "per_image", "exif"
    )


def write_database(
    database_path, images: list, cameras: CameraSetup, keypoints_path, matches_path, geometries_path=None
) -> dict:
    """Write the COLMAP database (module docstring); returns ``{image name: image id}``.

    ``keypoints_path`` / ``matches_path``: :mod:`.match`'s files; ``geometries_path``: the verified
    two-view geometries of :mod:`.geometry` (None: none written, COLMAP would verify itself).
    """
    pycolmap = _pycolmap()
    from .geometry import read_geometries
    from .match import read_all_matches

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


def main(argv=None) -> int:
    """``python -m localscale.sfm.database``: this step alone, from files (:func:`~.steps.database_of_files`)."""
    from .steps import config_of, database_of_files, parser, run_step

    p = parser("database", __doc__, ("camera_mode", "camera_file"))
    p.add_argument("images", help="folder of images (their cameras)")
    p.add_argument("out", help="folder with the h5 files; database.db is written there")
    args = p.parse_args(argv)
    return run_step(lambda: database_of_files(args.images, args.out, config_of(args)))


if __name__ == "__main__":
    raise SystemExit(main())
