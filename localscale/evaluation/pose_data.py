"""Photo collections with known poses for the relative-pose protocol (:mod:`localscale.evaluation.pose`):
their registered views, the pairs, the zoom windows cut from B, and the truth a pair's matches are
judged against.

Collections (folders of a root such as ``/work/shared/data/collections``), each read with its own
parser (no pycolmap needed):

* ``skull_alansartlog``: COLMAP model at the prepared size (``derived/colmap_txt_resized``), 3D point
  tracks from ``colmap_sparse_0/points3D.bin`` (image id k = ``%02d.jpg``);
* ``kermit_bundler``: COLMAP text model derived from Bundler (``derived/colmap_txt``), with tracks;
* ``temple_sparse_ring_middlebury``: calibrated ``K, R, t`` (``derived/templeSR_par_jpgnames.txt``),
  no 3D points;
* any other collection with a COLMAP model (binary or text, read with pycolmap) of ``NAME/images``
  as pseudo ground truth, e.g. the ``colmap-sift`` reconstruction of
  :mod:`localscale.evaluation.reconstruction`, as MegaDepth's poses come from COLMAP.

Pairs (seeded): two registered images sharing at least ``min_covisible`` 3D points and that share
of the smaller track set; without tracks (temple), optical axes within ``max_axis_angle`` degrees.
Each plain pair (A, B) also gives a zoom pair (A, B'): B' is a window of B showing 1/z of its width
(z log-uniform in the zoom range), centred on a co-visible 3D point's projection (temple: the point
the optical axes meet), resized to B's size and turned by a random quarter turn (1-3); its camera
and pose come from :func:`localscale.geometry.cameras.window_camera`.
"""

from __future__ import annotations

import math
import random
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np

from ..core.errors import LocalScaleError
from ..geometry.cameras import Camera, read_cameras_txt

COLLECTIONS = ("skull_alansartlog", "temple_sparse_ring_middlebury", "kermit_bundler")


@dataclass
class View:
    """One registered image: path, camera, world-to-camera pose ``x_cam = R X + t``, 3D point ids."""

    name: str
    path: Path
    camera: Camera
    R: np.ndarray
    t: np.ndarray
    point_ids: set = field(default_factory=set)

    @property
    def centre(self) -> np.ndarray:
        return -self.R.T @ self.t

    @property
    def axis(self) -> np.ndarray:
        return self.R[2]


@dataclass
class Collection:
    name: str
    views: Dict[str, View]
    points: Dict[int, np.ndarray]  # 3D point id -> xyz (empty without points)


def _qvec_to_R(q) -> np.ndarray:
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * y * y - 2 * z * z, 2 * x * y - 2 * w * z, 2 * x * z + 2 * w * y],
            [2 * x * y + 2 * w * z, 1 - 2 * x * x - 2 * z * z, 2 * y * z - 2 * w * x],
            [2 * x * z - 2 * w * y, 2 * y * z + 2 * w * x, 1 - 2 * x * x - 2 * y * y],
        ]
    )


def _read_images_txt(path: Path):
    """COLMAP images.txt -> ``{image_id: (name, camera_id, R, t, [point3D ids])}``."""
    lines = [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]
    out = {}
    i = 0
    while i < len(lines):
        if not lines[i].strip():
            i += 1
            continue
        tok = lines[i].split()
        image_id, q, t, cam_id, name = (
            int(tok[0]),
            [float(v) for v in tok[1:5]],
            [float(v) for v in tok[5:8]],
            int(tok[8]),
            tok[9],
        )
        pts = lines[i + 1].split() if i + 1 < len(lines) else []
        ids = [int(v) for v in pts[2::3] if int(v) >= 0]
        out[image_id] = (name, cam_id, _qvec_to_R(q), np.array(t), ids)
        i += 2
    return out


def _read_points3d_txt(path: Path):
    """COLMAP points3D.txt -> ``({point_id: xyz}, {image_id: set(point ids)})``."""
    xyz, seen = {}, {}
    for ln in path.read_text().splitlines():
        if ln.startswith("#") or not ln.strip():
            continue
        tok = ln.split()
        pid = int(tok[0])
        xyz[pid] = np.array([float(v) for v in tok[1:4]])
        for img in tok[8::2]:
            seen.setdefault(int(img), set()).add(pid)
    return xyz, seen


def _read_points3d_bin(path: Path):
    """COLMAP points3D.bin -> ``({point_id: xyz}, {image_id: set(point ids)})``."""
    xyz, seen = {}, {}
    with open(path, "rb") as f:
        (n,) = struct.unpack("<Q", f.read(8))
        for _ in range(n):
            pid, x, y, z = struct.unpack("<Qddd", f.read(32))
            f.read(3 + 8)  # colour, error
            (length,) = struct.unpack("<Q", f.read(8))
            track = np.frombuffer(f.read(8 * length), dtype="<u4").reshape(-1, 2)
            xyz[pid] = np.array([x, y, z])
            for img in np.unique(track[:, 0]):
                seen.setdefault(int(img), set()).add(pid)
    return xyz, seen


def load_model_collection(base: Path, name: str, model_dir: Path) -> Collection:
    """The registered views of a COLMAP model (``model_dir``, binary or text) of ``base/images``."""
    import pycolmap

    if not model_dir.is_dir():
        raise LocalScaleError(f"--gt-model {name}: no model folder {model_dir}")
    rec = pycolmap.Reconstruction(model_dir)
    points = {pid: np.asarray(p.xyz) for pid, p in rec.points3D.items()}
    seen: Dict[int, set] = {}
    for pid, p in rec.points3D.items():
        for el in p.track.elements:
            seen.setdefault(el.image_id, set()).add(pid)
    views: Dict[str, View] = {}
    for image_id, im in rec.images.items():
        if not im.has_pose:
            continue
        pose = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
        R, t = np.asarray(pose.rotation.matrix()), np.asarray(pose.translation)
        cam = Camera.from_pycolmap(rec.cameras[im.camera_id])
        cam.has_prior_focal_length = True  # refined by the model: known, as calibrated cameras are
        views[im.name] = View(im.name, base / "images" / im.name, cam, R, t, seen.get(image_id, set()))
    return Collection(name, views, points)


def load_collection(root: Path, name: str, model_dir=None) -> Collection:
    """Registered views (camera, pose, co-visible 3D point ids) of one collection (``model_dir``:
    a COLMAP model as its pseudo ground truth, for a collection without a reader)."""
    base = root / name
    if not base.is_dir():
        raise LocalScaleError(f"collection {base} does not exist")
    views: Dict[str, View] = {}
    points: Dict[int, np.ndarray] = {}
    if model_dir is not None:
        col = load_model_collection(base, name, Path(model_dir))
        views, points = col.views, col.points
    elif name in ("skull_alansartlog", "kermit_bundler"):
        model = base / "derived" / ("colmap_txt_resized" if name == "skull_alansartlog" else "colmap_txt")
        cams = read_cameras_txt(model / "cameras.txt")
        images = _read_images_txt(model / "images.txt")
        if name == "skull_alansartlog":
            points, seen = _read_points3d_bin(base / "colmap_sparse_0" / "points3D.bin")
        else:
            points, seen = _read_points3d_txt(model / "points3D.txt")
        for image_id, (img, cam_id, R, t, _) in images.items():
            views[img] = View(img, base / "images" / img, cams[cam_id], R, t, seen.get(image_id, set()))
    elif name == "temple_sparse_ring_middlebury":
        for ln in (base / "derived" / "templeSR_par_jpgnames.txt").read_text().splitlines()[1:]:
            tok = ln.split()
            if len(tok) != 22:
                continue
            v = np.array([float(x) for x in tok[1:]])
            K, R, t = v[:9].reshape(3, 3), v[9:18].reshape(3, 3), v[18:21]
            # the par file's K is for pixel-centre coordinates; COLMAP's principal point is + 0.5
            cam = Camera("PINHOLE", 640, 480, [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5])
            views[tok[0]] = View(tok[0], base / "images" / tok[0], cam, R, t)
    else:
        raise LocalScaleError(f"collection {name!r}: no reader (known: {', '.join(COLLECTIONS)})")
    views = {k: v for k, v in views.items() if v.path.exists()}
    return Collection(name, views, points)


def axis_angle(a: View, b: View) -> float:
    return math.degrees(math.acos(float(np.clip(a.axis @ b.axis, -1, 1))))


def choose_pairs(
    col: Collection, n: int, seed: int, min_covisible: int, min_share: float, max_axis_angle: float
) -> List[Tuple[str, str]]:
    """Up to ``n`` seeded pairs with enough co-visibility (tracks) or close optical axes (no tracks)."""
    names = sorted(col.views)
    cands = []
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            va, vb = col.views[a], col.views[b]
            if axis_angle(va, vb) > max_axis_angle:
                continue
            if col.points:
                shared = len(va.point_ids & vb.point_ids)
                smaller = max(1, min(len(va.point_ids), len(vb.point_ids)))
                if shared < min_covisible or shared / smaller < min_share:
                    continue
            cands.append((a, b))
    rng = random.Random(seed)
    return sorted(rng.sample(cands, min(n, len(cands))))


def relative_pose(a: View, b: View) -> Tuple[np.ndarray, np.ndarray]:
    """``x_B = R x_A + t`` from the world-to-camera poses."""
    R = b.R @ a.R.T
    return R, b.t - R @ a.t


def _axes_meeting_point(col: Collection) -> np.ndarray:
    """The point closest (least squares) to all optical axes: the object of an object-centred set."""
    A, rhs = np.zeros((3, 3)), np.zeros(3)
    for v in col.views.values():
        P = np.eye(3) - np.outer(v.axis, v.axis)
        A += P
        rhs += P @ v.centre
    return np.linalg.solve(A, rhs)


def covisible_projections(col: Collection, a: View, b: View):
    """``(in_a, in_b, p_a, p_b)`` of the 3D points A and B share: camera coordinates (``N x 3``) and
    pixels (``N x 2``) in each; ``None`` without shared points."""
    shared = sorted(a.point_ids & b.point_ids)
    if not shared:
        return None
    X = np.array([col.points[i] for i in shared])
    in_a, in_b = X @ a.R.T + a.t, X @ b.R.T + b.t
    return in_a, in_b, a.camera.project(in_a), b.camera.project(in_b)


def seen_by_both(in_a: np.ndarray, pa: np.ndarray, size_a, in_b: np.ndarray, pb: np.ndarray, size_b) -> np.ndarray:
    """``N`` bool: the points in front of both cameras (camera coordinates ``in_a``, ``in_b``) whose
    pixels ``pa``, ``pb`` lie inside images of ``size_a``, ``size_b`` (``(W, H)``)."""
    ok = (in_a[:, 2] > 0) & (in_b[:, 2] > 0)
    ok &= (pa >= 0).all(1) & (pa < list(size_a)).all(1)
    return ok & (pb >= 0).all(1) & (pb < list(size_b)).all(1)


def zoom_window(col: Collection, a: View, b: View, rng: random.Random, zoom_range) -> Tuple[tuple, int, float]:
    """A window ``(x0, y0, w, h)`` of B (integer pixels) showing 1/z of it around co-visible content,
    a quarter turn (1-3) and ``z``."""
    W, H = b.camera.width, b.camera.height
    z = math.exp(rng.uniform(math.log(zoom_range[0]), math.log(zoom_range[1])))
    w, h = int(round(W / z)), int(round(H / z))
    projected = covisible_projections(col, a, b)
    centres = []
    if projected is not None:
        in_a, in_b, pa, pb = projected
        ok = seen_by_both(in_a, pa, (a.camera.width, a.camera.height), in_b, pb, (W, H))
        centres = pb[ok].tolist()
    if not centres:
        Xc = _axes_meeting_point(col)
        centres = [b.camera.project((b.R @ Xc + b.t)[None])[0].tolist()]
    cx, cy = centres[rng.randrange(len(centres))]
    x0 = int(np.clip(round(cx - w / 2), 0, W - w))
    y0 = int(np.clip(round(cy - h / 2), 0, H - h))
    return (x0, y0, w, h), rng.randint(1, 3), z


def shared_points_in_view(col: Collection, a: View, b: View, cam_b: Camera, R_turn: np.ndarray):
    """``(p_a, p_b)``: pixels in A and in B's view ``cam_b`` (B's camera cut to a window and turned
    by ``R_turn``) of the 3D points A and B share that lie in front of both and inside both images."""
    projected = covisible_projections(col, a, b)
    if projected is None:
        return np.zeros((0, 2)), np.zeros((0, 2))
    in_a, in_b, pa, _ = projected
    in_b = in_b @ R_turn.T
    pb = cam_b.project(in_b)
    ok = seen_by_both(in_a, pa, (a.camera.width, a.camera.height), in_b, pb, (cam_b.width, cam_b.height))
    return pa[ok], pb[ok]


def true_relation(col: Collection, a: View, b: View, window, turns: int, z: float, margin: float = 0.25):
    """``(S_{A->B'}, the quarter turn that undoes B''s, window of A or None)`` of a pair
    (``window`` None: the plain pair, ``turns`` 0, ``z`` 1). The scale is the median over the
    co-visible 3D points in the window of ``z`` times the ratio of their depths and focal lengths
    (``z`` without points); the window, the box of their projections in A grown by ``margin``."""
    scale, box = z, None
    projected = covisible_projections(col, a, b)
    if projected is not None:
        in_a, in_b, pa, pb = projected
        x0, y0, w, h = window if window is not None else (0, 0, b.camera.width, b.camera.height)
        ok = (in_a[:, 2] > 0) & (in_b[:, 2] > 0) & (pb[:, 0] >= x0) & (pb[:, 0] < x0 + w)
        ok &= (pb[:, 1] >= y0) & (pb[:, 1] < y0 + h)
        if ok.sum() >= 3:
            scale = z * float(np.median(in_a[ok, 2] / in_b[ok, 2])) * b.camera.params[0] / a.camera.params[0]
            (ax0, ay0), (ax1, ay1) = pa[ok].min(0), pa[ok].max(0)
            mx, my = margin * (ax1 - ax0) + 8, margin * (ay1 - ay0) + 8
            box = (
                max(0, int(ax0 - mx)),
                max(0, int(ay0 - my)),
                min(a.camera.width, int(ax1 + mx)),
                min(a.camera.height, int(ay1 + my)),
            )
    return scale, (4 - turns) % 4, box
