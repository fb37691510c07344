"""The cameras of a reconstruction's images (``camera_mode``):

* ``single``: one camera for all images (they must share a size);
* ``per_image``: one camera per image;
* ``auto``: ``single`` when every image has the same size and the same EXIF focal length
  (or none), else ``per_image`` (COLMAP's own rule).

Cameras are :class:`localscale.geometry.cameras.Camera`: COLMAP's guess from the file
(:meth:`~localscale.geometry.cameras.Camera.from_exif`: SIMPLE_RADIAL, focal length from EXIF when there is
one, else 1.2 x the longer side; bundle adjustment refines it), or the camera of ``camera_file``
(``--camera``: one ``cameras.txt`` line or a COLMAP ``cameras.txt`` with one camera, or JSON; used
for every image; its size must be the images' size, or the same aspect ratio, then it is rescaled).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..core.errors import LocalScaleError

CAMERA_MODES = ("auto", "single", "per_image")


class CameraFileError(LocalScaleError):
    """A camera file is missing, malformed or does not fit the images."""


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
