"""Cameras as COLMAP camera models: intrinsics, distortion and normalised points.

A :class:`Camera` is a COLMAP camera model name, the image size and the model's parameters, the
same triple as a line of COLMAP's ``cameras.txt`` (``MODEL WIDTH HEIGHT PARAMS...``). Supported
models (parameters in COLMAP's order):

* ``SIMPLE_PINHOLE``: ``f, cx, cy``
* ``PINHOLE``: ``fx, fy, cx, cy``
* ``SIMPLE_RADIAL``: ``f, cx, cy, k``
* ``RADIAL``: ``f, cx, cy, k1, k2``
* ``OPENCV``: ``fx, fy, cx, cy, k1, k2, p1, p2``
* ``FULL_OPENCV``: ``fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6``

All of them are OpenCV's pinhole model with (a subset of) OpenCV's distortion coefficients, so
:meth:`Camera.K`, :meth:`Camera.dist` and ``cv2.undistortPoints`` do the work.

Pixel conventions: COLMAP's principal point is in continuous coordinates (the top-left corner of
the top-left pixel is ``(0, 0)``, its centre ``(0.5, 0.5)``); localscale's points (keypoints,
matches) have the centre of the top-left pixel at ``(0, 0)``. :attr:`Camera.params` keep
COLMAP's convention; :meth:`Camera.K` is the matrix for localscale/OpenCV points
(``cx - 0.5, cy - 0.5``), :meth:`Camera.K_colmap` the one for COLMAP's.

Sources: a ``pycolmap.Camera`` (:meth:`Camera.from_pycolmap`), a ``cameras.txt`` line
(:meth:`Camera.parse`), a text/JSON file holding one (:func:`read_camera`), EXIF focal length
(:meth:`Camera.from_exif`) or COLMAP's prior ``f = 1.2 * max(W, H)`` (:meth:`Camera.from_prior`).
pycolmap is optional (``pip install localscale[sfm]``) and imported only when a pycolmap object is
asked for.

Example::

    cam = Camera.parse("SIMPLE_RADIAL 1024 683 2322.9 512 341.5 0.045")
    xy_n = cam.normalize(keypoints)           # N x 2 undistorted normalised coordinates
    win, R_turn = window_camera(cam, (100, 50, 300, 200), (1024, 683), turns=1)
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence, Tuple, Union

import numpy as np

from ..core.errors import CameraError

#: COLMAP model name -> parameter names, in COLMAP's order
CAMERA_MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}

#: COLMAP's focal length prior when nothing is known: ``f = PRIOR_FOCAL_FACTOR * max(W, H)``
PRIOR_FOCAL_FACTOR = 1.2

#: diagonal of a 35 mm film frame (36 x 24 mm), mm
_FILM_35MM_DIAGONAL = math.hypot(36.0, 24.0)


@dataclass(eq=False)
class Camera:
    """One camera: a COLMAP model, the image size and the model's parameters.

    Attributes:
        model: a name of :data:`CAMERA_MODELS`.
        width, height: image size in pixels.
        params: the model's parameters in COLMAP's order and pixel convention (float64 array).
        has_prior_focal_length: the focal length is known (given, calibrated, EXIF), as COLMAP's
            flag of the same name; ``False`` for :meth:`from_prior`'s guess. Two-view geometry
            estimates an essential matrix only when both cameras have it.
    """

    model: str
    width: int
    height: int
    params: np.ndarray
    has_prior_focal_length: bool = True

    def __post_init__(self):
        model = str(self.model).upper()
        if model not in CAMERA_MODELS:
            raise CameraError(f"camera model {self.model!r} is not supported ({', '.join(CAMERA_MODELS)})")
        self.model = model
        try:
            params = np.asarray(self.params, np.float64).reshape(-1)
            width, height = int(self.width), int(self.height)
        except (TypeError, ValueError):
            raise CameraError(f"camera {model}: size and parameters must be numbers") from None
        if width <= 0 or height <= 0 or width != self.width or height != self.height:
            raise CameraError(f"camera {model}: image size must be positive integers, got {self.width} x {self.height}")
        n = len(CAMERA_MODELS[model])
        if params.size != n:
            raise CameraError(
                f"camera {model} takes {n} parameters ({', '.join(CAMERA_MODELS[model])}), got {params.size}"
            )
        if not np.all(np.isfinite(params)):
            raise CameraError(f"camera {model}: parameters must be finite, got {params.tolist()}")
        self.width, self.height, self.params = width, height, params
        fx, fy = self.focal_lengths
        if fx <= 0 or fy <= 0:
            raise CameraError(f"camera {model}: focal length must be positive, got {fx:g}, {fy:g}")

    def __eq__(self, other) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        return (self.model, self.width, self.height, self.has_prior_focal_length) == (
            other.model,
            other.width,
            other.height,
            other.has_prior_focal_length,
        ) and np.array_equal(self.params, other.params)

    # ------------------------------------------------------------------ construction
    @classmethod
    def parse(cls, text: str, has_prior_focal_length: bool = True) -> "Camera":
        """A camera from one ``cameras.txt`` line: ``[CAMERA_ID] MODEL WIDTH HEIGHT PARAMS...``.

        Comment lines (``#``) and blank lines are skipped; exactly one camera line is expected.
        """
        lines = [ln.strip() for ln in str(text).splitlines() if ln.strip() and not ln.strip().startswith("#")]
        if len(lines) != 1:
            raise CameraError(f"expected one camera line 'MODEL WIDTH HEIGHT PARAMS...', got {len(lines)} lines")
        tok = lines[0].replace(",", " ").split()
        if tok and tok[0].isdigit():  # cameras.txt: CAMERA_ID first
            tok = tok[1:]
        if len(tok) < 4:
            raise CameraError(f"camera line {lines[0]!r}: expected 'MODEL WIDTH HEIGHT PARAMS...'")
        try:
            width, height = int(tok[1]), int(tok[2])
            params = [float(v) for v in tok[3:]]
        except ValueError:
            raise CameraError(f"camera line {lines[0]!r}: width, height and parameters must be numbers") from None
        return cls(tok[0], width, height, params, has_prior_focal_length)

    @classmethod
    def from_pycolmap(cls, camera) -> "Camera":
        """A camera from a ``pycolmap.Camera`` (its model name, size, parameters and
        ``has_prior_focal_length``, which COLMAP leaves False for a guessed focal length: set it on
        the pycolmap camera, or on the result, for a camera whose intrinsics are known)."""
        model = getattr(camera.model, "name", str(camera.model)).split(".")[-1]
        return cls(
            model,
            camera.width,
            camera.height,
            np.array(camera.params, np.float64),
            bool(getattr(camera, "has_prior_focal_length", True)),
        )

    @classmethod
    def from_dict(cls, d: dict) -> "Camera":
        """A camera from ``{"model", "width", "height", "params"[, "has_prior_focal_length"]}``."""
        if not isinstance(d, dict):
            raise CameraError("a camera must be a JSON object with model, width, height, params")
        missing = [k for k in ("model", "width", "height", "params") if k not in d]
        if missing:
            raise CameraError(f"camera is missing {', '.join(missing)}")
        return cls(d["model"], d["width"], d["height"], d["params"], bool(d.get("has_prior_focal_length", True)))

    @classmethod
    def from_prior(cls, width: int, height: int, model: str = "SIMPLE_RADIAL") -> "Camera":
        """COLMAP's default: ``f = 1.2 * max(W, H)``, principal point at the centre, no distortion
        (``has_prior_focal_length`` False: the focal length is a guess)."""
        f = PRIOR_FOCAL_FACTOR * max(width, height)
        return cls._simple(model, width, height, f, has_prior_focal_length=False)

    @classmethod
    def from_focal(cls, width: int, height: int, focal: float, model: str = "SIMPLE_PINHOLE") -> "Camera":
        """A known focal length (pixels), principal point at the centre, no distortion."""
        return cls._simple(model, width, height, focal, has_prior_focal_length=True)

    @classmethod
    def _simple(cls, model, width, height, f, has_prior_focal_length):
        model = str(model).upper()
        base = {"SIMPLE_PINHOLE": [f, width / 2, height / 2], "PINHOLE": [f, f, width / 2, height / 2]}
        base["SIMPLE_RADIAL"] = base["SIMPLE_PINHOLE"] + [0.0]
        base["RADIAL"] = base["SIMPLE_PINHOLE"] + [0.0, 0.0]
        base["OPENCV"] = base["PINHOLE"] + [0.0] * 4
        base["FULL_OPENCV"] = base["PINHOLE"] + [0.0] * 8
        if model not in base:
            raise CameraError(f"camera model {model!r} is not supported ({', '.join(CAMERA_MODELS)})")
        return cls(model, width, height, base[model], has_prior_focal_length)

    @classmethod
    def from_exif(
        cls, image_path: Union[str, Path], model: str = "SIMPLE_RADIAL", fallback_prior: bool = True
    ) -> "Camera":
        """A camera from an image's EXIF focal length, as COLMAP's feature extractor does.

        ``FocalLengthIn35mmFilm`` gives ``f_px = f_35 / 43.27 mm * diag(W, H)`` (35 mm equivalent
        over the full-frame diagonal, as the EXIF standard defines it; for 3:2 images the same as
        ``f_35 / 36 mm * W``); without it, ``FocalLength`` times ``FocalPlaneXResolution`` (pixels
        per unit on the sensor, rescaled from ``PixelXDimension`` to the image's width). The size is
        the image's after EXIF orientation. Without a usable tag: :meth:`from_prior` when
        ``fallback_prior``, else :class:`CameraError`.
        """
        try:
            from PIL import Image
        except ImportError:
            raise CameraError("reading EXIF needs Pillow (pip install pillow)") from None
        path = Path(image_path)
        try:
            with Image.open(path) as im:
                exif = im.getexif()
                raw_w, raw_h = im.size
                orientation = exif.get(0x0112, 1)
                width, height = (raw_h, raw_w) if orientation in (5, 6, 7, 8) else (raw_w, raw_h)
                sub = exif.get_ifd(0x8769) if hasattr(exif, "get_ifd") else {}
        except FileNotFoundError:
            raise CameraError(f"image {path} does not exist") from None
        except OSError as e:
            raise CameraError(f"cannot read image {path}: {e}") from None
        f = _exif_focal_pixels(sub, raw_w, raw_h)
        if f is None:
            if not fallback_prior:
                raise CameraError(f"image {path} has no usable EXIF focal length")
            return cls.from_prior(width, height, model)
        return cls._simple(model, width, height, f, has_prior_focal_length=True)

    # ------------------------------------------------------------------ matrices
    @property
    def focal_lengths(self) -> Tuple[float, float]:
        """``(fx, fy)`` in pixels."""
        p = self.params
        if self.model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
            return float(p[0]), float(p[0])
        return float(p[0]), float(p[1])

    @property
    def principal_point(self) -> Tuple[float, float]:
        """``(cx, cy)`` in COLMAP's convention (continuous pixel coordinates)."""
        p = self.params
        if self.model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
            return float(p[1]), float(p[2])
        return float(p[2]), float(p[3])

    def K_colmap(self) -> np.ndarray:
        """``3 x 3`` intrinsics for COLMAP pixel coordinates (top-left pixel's corner at 0)."""
        fx, fy = self.focal_lengths
        cx, cy = self.principal_point
        return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float64)

    def K(self) -> np.ndarray:
        """``3 x 3`` intrinsics for localscale/OpenCV pixel coordinates (top-left pixel's centre at 0)."""
        K = self.K_colmap()
        K[0, 2] -= 0.5
        K[1, 2] -= 0.5
        return K

    def dist(self) -> np.ndarray:
        """OpenCV distortion coefficients: ``(k1, k2, p1, p2)`` (4) or ``(k1, k2, p1, p2, k3, k4, k5, k6)`` (8)."""
        p = self.params
        if self.model in ("SIMPLE_PINHOLE", "PINHOLE"):
            return np.zeros(4)
        if self.model == "SIMPLE_RADIAL":
            return np.array([p[3], 0, 0, 0], np.float64)
        if self.model == "RADIAL":
            return np.array([p[3], p[4], 0, 0], np.float64)
        if self.model == "OPENCV":
            return p[4:8].copy()
        k1, k2, p1, p2, k3, k4, k5, k6 = p[4:12]
        return np.array([k1, k2, p1, p2, k3, k4, k5, k6], np.float64)

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist() != 0))

    # ------------------------------------------------------------------ points
    def normalize(self, points) -> np.ndarray:
        """``N x 2`` pixel points (localscale convention) -> ``N x 2`` undistorted normalised
        coordinates ``(X/Z, Y/Z)`` (``cv2.undistortPoints``)."""
        pts = _points(points)
        if len(pts) == 0:
            return np.zeros((0, 2))
        import cv2

        out = cv2.undistortPoints(pts.reshape(-1, 1, 2), self.K(), self.dist())
        return out.reshape(-1, 2).astype(np.float64)

    def undistort_points(self, points) -> np.ndarray:
        """``N x 2`` pixel points -> ``N x 2`` pixels of the same camera without distortion
        (``K`` kept): what a pinhole camera with this ``K`` would see."""
        xy = self.normalize(points)
        K = self.K()
        return xy * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]

    def project(self, points_cam) -> np.ndarray:
        """``N x 3`` points in camera coordinates -> ``N x 2`` pixels (localscale convention), with
        distortion (``cv2.projectPoints``). Points behind the camera come out mirrored: check ``Z > 0``."""
        X = np.asarray(points_cam, np.float64).reshape(-1, 3)
        if len(X) == 0:
            return np.zeros((0, 2))
        import cv2

        uv, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), self.K(), self.dist())
        return uv.reshape(-1, 2)

    def pixel_threshold_to_normalized(self, max_error: float) -> float:
        """A pixel error as an error in normalised coordinates (``max_error / mean focal``), as
        COLMAP's ``CamFromImgThreshold``."""
        fx, fy = self.focal_lengths
        return float(max_error) * 2.0 / (fx + fy)

    # ------------------------------------------------------------------ conversions
    def scaled(self, sx: float, sy: Optional[float] = None) -> "Camera":
        """The camera of the image resized by ``sx`` (width) and ``sy`` (height; default ``sx``),
        size rounded. Single-focal models become two-focal ones when ``sx != sy``."""
        sy = sx if sy is None else sy
        w, h = int(round(self.width * sx)), int(round(self.height * sy))
        return _with_pinhole(
            self,
            w,
            h,
            self.focal_lengths[0] * sx,
            self.focal_lengths[1] * sy,
            self.principal_point[0] * sx,
            self.principal_point[1] * sy,
            self.dist(),
        )

    def to_dict(self) -> dict:
        """JSON-ready ``{"model", "width", "height", "params", "has_prior_focal_length"}``."""
        return {
            "model": self.model,
            "width": self.width,
            "height": self.height,
            "params": [float(v) for v in self.params],
            "has_prior_focal_length": self.has_prior_focal_length,
        }

    def to_line(self, camera_id: Optional[int] = None) -> str:
        """The ``cameras.txt`` line (``[CAMERA_ID] MODEL W H PARAMS``)."""
        head = f"{camera_id} " if camera_id is not None else ""
        return head + f"{self.model} {self.width} {self.height} " + " ".join(repr(float(v)) for v in self.params)

    def to_pycolmap(self):
        """A ``pycolmap.Camera`` (needs pycolmap: ``pip install localscale[sfm]``)."""
        pycolmap = import_pycolmap()
        cam = pycolmap.Camera(model=self.model, width=self.width, height=self.height, params=self.params.tolist())
        cam.has_prior_focal_length = self.has_prior_focal_length
        return cam


def import_pycolmap():
    """``pycolmap``, or a :class:`CameraError` saying how to install it."""
    try:
        import pycolmap
    except ImportError:
        raise CameraError("this needs pycolmap: pip install 'localscale[sfm]'") from None
    return pycolmap


CameraLike = Union[Camera, str, Path, dict, "pycolmap.Camera"]  # noqa: F821


def as_camera(camera) -> Optional[Camera]:
    """A :class:`Camera` from a :class:`Camera`, a ``pycolmap.Camera``, a dict, a ``cameras.txt``
    line or the path of a file holding one (:func:`read_camera`); ``None`` stays ``None``. All
    but a :class:`Camera` are checked (:func:`~localscale.geometry.camera_checks.check_plausible`)."""
    from .camera_checks import check_plausible

    if camera is None or isinstance(camera, Camera):
        return camera
    if isinstance(camera, dict):
        return check_plausible(Camera.from_dict(camera))
    if isinstance(camera, Path):
        return check_plausible(read_camera(camera), f"camera file {camera}")
    if isinstance(camera, str):
        first = camera.strip().split()[:2]
        if first and (
            first[0].upper() in CAMERA_MODELS
            or (first[0].isdigit() and len(first) > 1 and first[1].upper() in CAMERA_MODELS)
        ):
            return check_plausible(Camera.parse(camera))
        return check_plausible(read_camera(camera), f"camera file {camera}")
    if hasattr(camera, "model") and hasattr(camera, "params") and hasattr(camera, "width"):
        return check_plausible(Camera.from_pycolmap(camera))
    raise CameraError(
        f"cannot use {type(camera).__name__} as a camera (Camera, pycolmap.Camera, cameras.txt line, dict or file)"
    )


def read_camera(path: Union[str, Path]) -> Camera:
    """The camera in a file: JSON (``{"model", "width", "height", "params"}``, or a list holding
    one such object) or text with one ``cameras.txt`` line (comments allowed)."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise CameraError(f"camera file {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as e:
        raise CameraError(f"cannot read camera file {path}: {getattr(e, 'strerror', None) or e}") from None
    stripped = text.lstrip()
    try:
        if stripped.startswith(("{", "[")):
            try:
                data = json.loads(text)
            except json.JSONDecodeError as e:
                raise CameraError(f"not valid JSON ({e.msg}, line {e.lineno})") from None
            if isinstance(data, list):
                if len(data) != 1:
                    raise CameraError(f"expected one camera, found {len(data)}")
                data = data[0]
            return Camera.from_dict(data)
        return Camera.parse(text)
    except CameraError as e:
        raise CameraError(f"camera file {path}: {e}") from None


def read_cameras_txt(path: Union[str, Path]) -> dict:
    """All cameras of a COLMAP ``cameras.txt``: ``{camera_id: Camera}``."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except FileNotFoundError:
        raise CameraError(f"cameras file {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as e:
        raise CameraError(f"cannot read cameras file {path}: {getattr(e, 'strerror', None) or e}") from None
    cams = {}
    for i, ln in enumerate(lines, 1):
        s = ln.strip()
        if not s or s.startswith("#"):
            continue
        tok = s.split()
        if not tok[0].isdigit():
            raise CameraError(f"{path}, line {i}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...'")
        try:
            cams[int(tok[0])] = Camera.parse(s)
        except CameraError as e:
            raise CameraError(f"{path}, line {i}: {e}") from None
    if not cams:
        raise CameraError(f"cameras file {path} holds no camera")
    return cams


def camera_prior(width: int, height: int) -> Camera:
    """COLMAP's prior camera for an image of ``width x height``: :meth:`Camera.from_prior`."""
    return Camera.from_prior(width, height)


# ---------------------------------------------------------------------- windows and quarter turns
def turn_rotation(turns: int) -> np.ndarray:
    """``3 x 3`` rotation from a camera's frame to the frame of the same camera whose image is
    turned by ``turns`` quarter turns counter-clockwise (as ``np.rot90(image, turns)``):
    ``X_turned = R X``; one turn maps ``(X, Y, Z)`` to ``(Y, -X, Z)``."""
    R1 = np.array([[0, 1, 0], [-1, 0, 0], [0, 0, 1]], np.float64)
    return np.linalg.matrix_power(R1, int(turns) % 4)


def window_camera(
    camera: Camera, window: Sequence[float], out_size: Optional[Sequence[int]] = None, turns: int = 0
) -> Tuple[Camera, np.ndarray]:
    """The camera of a window cut from an image, resized and turned by quarter turns.

    The window ``(x0, y0, w, h)`` (COLMAP pixel coordinates of its top-left corner, i.e. column and
    row of the first pixel, and its size) is resized to ``out_size = (W', H')`` (default: ``(w, h)``)
    and then turned ``turns`` times by 90 degrees counter-clockwise (``np.rot90``). The principal
    point shifts by the corner and scales with the resize, the focal lengths scale, and each turn
    swaps the axes: ``(fx, fy, cx, cy) -> (fy, fx, cy, W - cx)`` with tangential distortion
    ``(p1, p2) -> (-p2, p1)``. A turn is a rotation of the camera about its optical axis, so the
    turned camera's pose is ``R_turn @ cam_from_world`` (``x_turned = R_turn x``).

    Returns:
        ``(camera, R_turn)``: the window's :class:`Camera` (size ``out_size``, swapped by odd
        turns) and the ``3 x 3`` rotation :func:`turn_rotation` ``(turns)``.
    """
    x0, y0, w, h = (float(v) for v in window)
    if w <= 0 or h <= 0:
        raise CameraError(f"window size must be positive, got {w:g} x {h:g}")
    W, H = (int(round(w)), int(round(h))) if out_size is None else (int(out_size[0]), int(out_size[1]))
    if W <= 0 or H <= 0:
        raise CameraError(f"window output size must be positive, got {W} x {H}")
    sx, sy = W / w, H / h
    fx, fy = camera.focal_lengths
    cx, cy = camera.principal_point
    fx, fy, cx, cy = fx * sx, fy * sy, (cx - x0) * sx, (cy - y0) * sy
    dist = camera.dist().copy()
    for _ in range(int(turns) % 4):
        fx, fy, cx, cy = fy, fx, cy, W - cx
        W, H = H, W
        dist[2], dist[3] = -dist[3], dist[2]
    return _with_pinhole(camera, W, H, fx, fy, cx, cy, dist), turn_rotation(turns)


def window_pixels(window: Sequence[float], out_size: Sequence[int], turns: int = 0) -> np.ndarray:
    """``3 x 3`` map from pixels of the image (localscale convention) to pixels of the window
    :func:`window_camera` describes (crop, resize to ``out_size = (W', H')``, ``turns`` quarter turns)."""
    x0, y0, w, h = (float(v) for v in window)
    W, H = float(out_size[0]), float(out_size[1])
    sx, sy = W / w, H / h
    # continuous (COLMAP) coordinates: u = x + 0.5; window: u' = (u - x0) * s
    M = np.array([[sx, 0, (0.5 - x0) * sx], [0, sy, (0.5 - y0) * sy], [0, 0, 1]])
    for _ in range(int(turns) % 4):
        M = np.array([[0, 1, 0], [-1, 0, W], [0, 0, 1]]) @ M  # u' = v, v' = W - u
        W, H = H, W
    return np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1]]) @ M


def cut_window(
    image: np.ndarray, camera: Camera, window: Sequence[int], out_size: Sequence[int], turns: int = 0
) -> Tuple[np.ndarray, Camera, np.ndarray]:
    """Cut the window ``(x0, y0, w, h)`` (integers, inside the image) from ``image`` (``H x W [x C]``),
    resize it to ``out_size = (W', H')`` (``INTER_AREA`` when shrinking, else ``INTER_LINEAR``) and
    turn it by ``turns`` quarter turns (``np.rot90``).

    Returns:
        ``(window image, its Camera, R_turn)`` as :func:`window_camera`.
    """
    import cv2

    x0, y0, w, h = (int(v) for v in window)
    if x0 < 0 or y0 < 0 or w <= 0 or h <= 0 or x0 + w > image.shape[1] or y0 + h > image.shape[0]:
        raise CameraError(f"window {x0, y0, w, h} is not inside the {image.shape[1]} x {image.shape[0]} image")
    if (image.shape[1], image.shape[0]) != (camera.width, camera.height):
        raise CameraError(f"image is {image.shape[1]} x {image.shape[0]}, its camera {camera.width} x {camera.height}")
    W, H = int(out_size[0]), int(out_size[1])
    crop = image[y0 : y0 + h, x0 : x0 + w]
    interp = cv2.INTER_AREA if W * H < w * h else cv2.INTER_LINEAR
    out = np.ascontiguousarray(np.rot90(cv2.resize(crop, (W, H), interpolation=interp), int(turns) % 4))
    cam, R_turn = window_camera(camera, (x0, y0, w, h), (W, H), turns)
    return out, cam, R_turn


# ---------------------------------------------------------------------- helpers
def _with_pinhole(camera: Camera, width, height, fx, fy, cx, cy, dist) -> Camera:
    """``camera``'s model (or the nearest one that can hold two focal lengths / the distortion)
    with new size, intrinsics and distortion."""
    dist = np.asarray(dist, np.float64)
    k1, k2, p1, p2 = dist[:4]
    rest = dist[4:]
    same_f = math.isclose(fx, fy, rel_tol=1e-12)
    if camera.model == "FULL_OPENCV" or np.any(rest != 0):
        full = np.zeros(8)
        full[: dist.size] = dist
        return Camera("FULL_OPENCV", width, height, [fx, fy, cx, cy, *full], camera.has_prior_focal_length)
    if camera.model == "OPENCV" or p1 != 0 or p2 != 0 or (not same_f and (k1 != 0 or k2 != 0)):
        return Camera("OPENCV", width, height, [fx, fy, cx, cy, k1, k2, p1, p2], camera.has_prior_focal_length)
    if not same_f:
        return Camera("PINHOLE", width, height, [fx, fy, cx, cy], camera.has_prior_focal_length)
    if camera.model == "RADIAL" or k2 != 0:
        return Camera("RADIAL", width, height, [fx, cx, cy, k1, k2], camera.has_prior_focal_length)
    if camera.model == "SIMPLE_RADIAL" or k1 != 0:
        return Camera("SIMPLE_RADIAL", width, height, [fx, cx, cy, k1], camera.has_prior_focal_length)
    if camera.model == "PINHOLE":
        return Camera("PINHOLE", width, height, [fx, fy, cx, cy], camera.has_prior_focal_length)
    return Camera("SIMPLE_PINHOLE", width, height, [fx, cx, cy], camera.has_prior_focal_length)


def _points(points) -> np.ndarray:
    try:
        pts = np.asarray(points, np.float64)
    except (TypeError, ValueError):
        raise CameraError("points must be an N x 2 array of numbers") from None
    if pts.size == 0:
        return np.zeros((0, 2))
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise CameraError(f"points must be N x 2, got shape {pts.shape}")
    return pts


def _exif_focal_pixels(sub: dict, raw_w: int, raw_h: int) -> Optional[float]:
    """Focal length in pixels of the stored (unrotated) image from EXIF sub-IFD tags, or ``None``."""

    def num(tag):
        v = sub.get(tag)
        try:
            v = float(v)
        except (TypeError, ValueError, ZeroDivisionError):
            return None
        return v if math.isfinite(v) and v > 0 else None

    f35 = num(0xA405)  # FocalLengthIn35mmFilm
    if f35 is not None:
        return f35 / _FILM_35MM_DIAGONAL * math.hypot(raw_w, raw_h)
    f_mm = num(0x920A)  # FocalLength
    xres = num(0xA20E)  # FocalPlaneXResolution
    if f_mm is not None and xres is not None:
        unit = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}.get(int(sub.get(0xA210, 2) or 2))  # FocalPlaneResolutionUnit
        if unit is not None:
            # the resolution refers to the sensor's pixels: rescale to this image's width
            sensor_w = num(0xA002)  # PixelXDimension, the width the camera wrote
            rescale = raw_w / sensor_w if sensor_w else 1.0
            return f_mm * xres / unit * rescale
    return None
