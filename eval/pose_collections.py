"""Relative pose on real photo collections: plain pairs and zoom + quarter-turn pairs.

The SuperGlue/LightGlue protocol the ScaleNet paper uses: for each image pair with a known
relative pose, match, estimate the essential matrix from the matches with the known intrinsics
(:func:`localscale.two_view.estimate_two_view_geometry`: MAGSAC, cheirality, refinement),
error = max(rotation error, translation-direction error) in degrees (180 when no pose), and report
the AUC at 5/10/20 degrees and the share of pairs within 10 degrees. Each pair's record (and the
summary's median) also counts the returned matches that the true pose explains (``correct``:
:func:`localscale.two_view.epipolar_errors` below :data:`EPIPOLAR_THRESHOLD` in normalised coordinates, SuperGlue's
precision), which tells wrong matches from a pose the right matches do not pin down.

Collections (``--root``, default ``/work/shared/data/collections``), each read with its own parser
(no pycolmap needed):

* ``skull_alansartlog``: COLMAP model at the prepared size (``derived/colmap_txt_resized``), 3D point
  tracks from ``colmap_sparse_0/points3D.bin`` (image id k = ``%02d.jpg``);
* ``kermit_bundler``: COLMAP text model derived from Bundler (``derived/colmap_txt``), with tracks;
* ``temple_sparse_ring_middlebury``: calibrated ``K, R, t`` (``derived/templeSR_par_jpgnames.txt``),
  no 3D points;
* any other collection with ``--gt-model NAME=DIR``: a COLMAP model (binary or text, read with
  pycolmap) of ``NAME/images`` as pseudo ground truth, e.g. the ``colmap-sift`` reconstruction of
  ``eval/reconstruct_collections.py`` (``OUT/NAME/colmap-sift/sparse/0``), as MegaDepth's poses come
  from COLMAP.

Pairs (seeded): two registered images sharing at least ``--min-covisible`` 3D points and that share
of the smaller track set; without tracks (temple), optical axes within ``--max-axis-angle`` degrees.
Each plain pair (A, B) also gives a zoom pair (A, B'): B' is a window of B showing 1/z of its width
(z log-uniform in ``--zoom``), centred on a co-visible 3D point's projection (temple: the point the
optical axes meet), resized to B's size and turned by a random quarter turn (1-3); its camera and
pose come from :func:`localscale.cameras.window_camera`.

Methods: ``opencv-sift`` (OpenCV SIFT, 4096 features, ratio 0.8, mutual nearest neighbours) and
``MATCHER:CORRECTION`` for the library's ``match_pair(A, B, correction, matcher=MATCHER)``
(e.g. ``aliked-lightglue:none``, ``aliked-lightglue:auto``); only the returned matches are used.
``MATCHER:truth`` and ``MATCHER:truth-window`` are upper bounds of ``auto``'s choice: the matcher
is given the true zoom and quarter turn as its only hypothesis (B' shrunk, as the matcher rectifies),
and with ``truth-window`` also the part of A that B' shows (the co-visible 3D points that project
into B's window, their box in A grown by a quarter on each side), enlarged instead; temple has no
points, so no window. ``MATCHER:CORRECTION:cameras`` also passes the known cameras (two-view verification with the
essential matrix), ``MATCHER:CORRECTION:two_view`` verifies by COLMAP's homography / fundamental
matrix choice without cameras. ``points:SIGMA`` is no matcher (:class:`PointsOracle`): the shared 3D
points' true projections with ``SIGMA`` pixels of noise, the bound the views' geometry sets
(collections with 3D points only).

Per-pair results go to ``<out>.pairs.jsonl`` (or ``--cache``) as they are computed; a rerun skips the pairs found
there (same collection, pair, kind, method and options). The table (markdown) is printed and the
summary written atomically to ``--out``.

    OMP_NUM_THREADS=1 python eval/pose_collections.py --methods opencv-sift aliked-lightglue:none \\
        aliked-lightglue:auto --pairs 55 --out results/pose_collections.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import random
import struct
import sys
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Tuple

import cv2
import numpy as np
from tqdm import tqdm

from localscale.cameras import Camera, cut_window, read_cameras_txt
from localscale.errors import LocalScaleError
from localscale.matching.auto import auto_options
from localscale.outputs import atomic_path
from localscale.two_view import (
    TwoViewConfig,
    epipolar_errors,
    estimate_two_view_geometry,
    pose_auc,
    relative_pose_error,
)

COLLECTIONS = ("skull_alansartlog", "temple_sparse_ring_middlebury", "kermit_bundler")
THRESHOLDS = (5, 10, 20)


# ---------------------------------------------------------------------------- collections
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


# ---------------------------------------------------------------------------- matching
class SiftMatcher:
    """OpenCV SIFT (4096 features), Lowe's ratio test and mutual nearest neighbours."""

    def __init__(self, num_features=4096, ratio=0.8):
        self.sift = cv2.SIFT_create(num_features)
        self.ratio = ratio
        self.cache = {}

    def features(self, key, img):
        if key not in self.cache:
            gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
            kps, desc = self.sift.detectAndCompute(gray, None)
            xy = np.float64([k.pt for k in kps]).reshape(-1, 2)
            self.cache = {key: (xy, desc)} if len(self.cache) > 64 else {**self.cache, key: (xy, desc)}
        return self.cache[key]

    def match(self, key_a, a, key_b, b, cameras=(None, None)):
        xa, da = self.features(key_a, a)
        xb, db = self.features(key_b, b)
        if da is None or db is None or len(da) < 2 or len(db) < 2:
            return np.zeros((0, 2)), np.zeros((0, 2))
        bf = cv2.BFMatcher(cv2.NORM_L2)
        ab = bf.knnMatch(da, db, k=2)
        ba = {m.queryIdx: m.trainIdx for m in bf.match(db, da)}
        keep = [
            (m.queryIdx, m.trainIdx)
            for m, n2 in (p for p in ab if len(p) == 2)
            if m.distance < self.ratio * n2.distance and ba.get(m.trainIdx) == m.queryIdx
        ]
        idx = np.array(keep, int).reshape(-1, 2)
        return xa[idx[:, 0]], xb[idx[:, 1]]


class LibraryMatcher:
    """``localscale.matching.match_pair(A, B, correction, matcher=...)``; matches only.

    ``given``: ``""`` (images only, the matcher's verification), ``"cameras"`` (the known cameras
    passed: two-view geometry with the essential matrix) or ``"two_view"`` (no cameras, COLMAP's
    choice of homography or fundamental matrix)."""

    def __init__(self, name: str, correction: str, max_side: int, models, given: str = "", auto=None, features=None):
        from localscale.matching import AutoConfig, get_matcher

        options = {"auto": AutoConfig(**auto)} if auto else {}
        if features:
            options["num_features"] = features
        if given == "two_view":
            from localscale.matching import VerificationConfig

            options["verification"] = VerificationConfig(model="two_view")
        self.matcher = get_matcher(name, max_side=max_side, **options)
        self.correction = correction
        self.models = models
        self.given = given

    def match(self, key_a, a, key_b, b, cameras=(None, None)):
        from localscale.matching import match_pair

        self.trials = None

        cam_a, cam_b = cameras if self.given == "cameras" else (None, None)
        res = match_pair(
            a,
            b,
            self.correction,
            local_model=self.models[0],
            global_model=self.models[1],
            matcher=self.matcher,
            camera_a=cam_a,
            camera_b=cam_b,
        )
        self.trials = res.meta.get("auto")
        m = np.asarray(res.matches, int).reshape(-1, 2)
        return np.asarray(res.keypoints_a, np.float64)[m[:, 0]], np.asarray(res.keypoints_b, np.float64)[m[:, 1]]


class TruthMatcher:
    """The matcher given the true relation of the pair as its only hypothesis
    (:func:`localscale.matching.auto_match` without the images as they are, the seed or the networks)."""

    def __init__(self, name: str, max_side: int, window: bool, features=None):
        from localscale.matching import get_matcher

        self.matcher = get_matcher(name, max_side=max_side, **({"num_features": features} if features else {}))
        self.window = window
        self.truth = None
        self.trials = None

    def tell(self, scale: float, turn: int, window_a):
        self.truth = (scale, turn, window_a if self.window else None)

    def match(self, key_a, a, key_b, b, cameras=(None, None)):
        from localscale.matching import Hypothesis, auto_match

        if max(a.shape[:2] + b.shape[:2]) > self.matcher.config.max_side:
            raise LocalScaleError("truth methods need images within --max-side")
        scale, turn, window = self.truth
        h = Hypothesis(scale, turn, "truth", window=None if window is None else (0, *window))
        config = dataclasses.replace(self.matcher.config.auto, locate=False)
        out = auto_match(self.matcher, a, b, config=config, keys=(key_a, key_b), hypotheses=[h], networks=False)
        self.trials = out.to_dict()
        m = np.asarray(out.matches.matches, int).reshape(-1, 2)
        return np.asarray(out.matches.keypoints_a, np.float64)[m[:, 0]], np.asarray(
            out.matches.keypoints_b, np.float64
        )[m[:, 1]]


class PointsOracle:
    """No matcher: the 3D points A and B share that fall in both images (B: the close-up, turned),
    projected with the true cameras, with Gaussian noise of ``sigma`` pixels at ``max_side``
    (each image's pixels scaled as the matchers scale them). What the pose protocol gives for
    correct matches of detector precision, as many as the model's tracks: the bound the views'
    geometry sets (a close-up shows a narrow, shallow part of the scene)."""

    def __init__(self, sigma: float, max_side: int):
        if not (math.isfinite(sigma) and sigma >= 0):
            raise LocalScaleError(f"points:SIGMA takes a noise >= 0 in pixels, got {sigma!r}")
        self.sigma, self.max_side = sigma, max_side
        self.points = None

    def tell_points(self, pa: np.ndarray, pb: np.ndarray, key: str):
        self.points = (pa, pb, key)

    def match(self, key_a, a, key_b, b, cameras=(None, None)):
        pa, pb, key = self.points
        rng = np.random.default_rng(zlib.crc32(key.encode()))  # per pair, the same in every run
        out = []
        for p, img in ((pa, a), (pb, b)):
            pixel = max(1.0, max(img.shape[:2]) / self.max_side)
            out.append(p + rng.normal(0.0, self.sigma * pixel, p.shape))
        return out[0], out[1]


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


def make_method(spec: str, max_side: int, models_cache: dict, auto=None, features=None):
    if spec == "opencv-sift":
        return SiftMatcher()
    if spec.startswith("points:"):
        try:
            sigma = float(spec.split(":", 1)[1])
        except ValueError:
            raise LocalScaleError(f"method {spec!r}: points:SIGMA takes a number of pixels") from None
        return PointsOracle(sigma, max_side)
    if ":" not in spec:
        raise LocalScaleError(f"method {spec!r}: use opencv-sift or MATCHER:CORRECTION (e.g. aliked-lightglue:auto)")
    name, correction, *given = spec.split(":")
    if correction in ("truth", "truth-window") and not given:
        return TruthMatcher(name, max_side, correction == "truth-window", features)
    if len(given) > 1 or (given and given[0] not in ("cameras", "two_view")):
        raise LocalScaleError(f"method {spec!r}: the third part must be cameras or two_view")
    if "models" not in models_cache:
        from localscale import LocalScaleNet, ScaleNet

        models_cache["models"] = (LocalScaleNet.from_pretrained(), ScaleNet.from_pretrained())
    return LibraryMatcher(name, correction, max_side, models_cache["models"], *given, auto=auto, features=features)


# ---------------------------------------------------------------------------- evaluation
def load_rgb(path: Path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise LocalScaleError(f"cannot read image {path}")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


#: a match is correct when its symmetric epipolar distance under the true pose is below this, in
#: normalised coordinates (SuperGlue's matching precision)
EPIPOLAR_THRESHOLD = 5e-4


def evaluate_pair(method, key_a, img_a, cam_a, key_b, img_b, cam_b, R_gt, t_gt, cfg: TwoViewConfig) -> dict:
    t0 = time.perf_counter()
    try:
        pa, pb = method.match(key_a, img_a, key_b, img_b, (cam_a, cam_b))
        error = None
    except LocalScaleError as e:
        pa, pb, error = np.zeros((0, 2)), np.zeros((0, 2)), str(e)
    t_match = time.perf_counter() - t0
    g = estimate_two_view_geometry(pa, pb, cam_a, cam_b, cfg)
    rot, trans = relative_pose_error(g.R_E, g.t_E, R_gt, t_gt)
    rot_c, trans_c = relative_pose_error(g.R, g.t, R_gt, t_gt)
    correct = epipolar_errors(pa, pb, cam_a, cam_b, R_gt, t_gt) < EPIPOLAR_THRESHOLD
    rec = {
        "matches": int(len(pa)),
        "correct": int(correct.sum()),
        "precision": float(correct.mean()) if len(correct) else None,
        "inliers_E": g.num_inliers_E,
        "configuration": g.configuration,
        "err_rot": rot,
        "err_t": trans,
        "err": max(rot, trans),
        "err_colmap": max(rot_c, trans_c),
        "seconds_match": round(t_match, 3),
        "seconds_total": round(time.perf_counter() - t0, 3),
    }
    if error:
        rec["error"] = error
    if getattr(method, "trials", None):
        rec["auto"] = method.trials
    return rec


#: correct matches (:data:`EPIPOLAR_THRESHOLD`) that make a pair's close-up "found"
FOUND_CORRECT = 10


def _found_summary(records: List[dict], pose: str) -> dict:
    """Where the pairs fail: the share with at least :data:`FOUND_CORRECT` correct matches (the
    matcher found the common part), and the share of those within 10 degrees (the pose those
    matches give); empty for records without ``correct``."""
    if any("correct" not in r for r in records):
        return {}
    found = [r for r in records if r["correct"] >= FOUND_CORRECT]
    return {
        "median_correct": float(np.median([r["correct"] for r in records])),
        "found": 100 * len(found) / len(records),
        "within10_of_found": 100 * float(np.mean([r[pose] <= 10 for r in found])) if found else None,
    }


def summarise(records: List[dict], pose: str = "err") -> dict:
    errs = [r[pose] for r in records]
    if not errs:
        return {"pairs": 0}
    auc = pose_auc(errs, THRESHOLDS)
    return {
        "pairs": len(errs),
        **{f"auc@{t}": 100 * a for t, a in zip(THRESHOLDS, auc)},
        "within10": 100 * float(np.mean(np.asarray(errs) <= 10)),
        "median_err": float(np.median(errs)),
        "median_matches": float(np.median([r["matches"] for r in records])),
        **_found_summary(records, pose),
        "seconds_per_pair": float(np.mean([r["seconds_total"] for r in records])),
    }


def _cell(value) -> str:
    return "-" if value is None else f"{value:.0f}"


def markdown(rows: List[dict]) -> str:
    head = (
        "| collection | pairs | method | n | AUC@5 | AUC@10 | AUC@20 | <=10 deg % | med. matches | s/pair "
        "| found % | of found <=10 deg % |"
    )
    out = [head, "|" + "---|" * 12]
    for r in rows:
        s = r["summary"]
        if not s.get("pairs"):
            continue
        out.append(
            f"| {r['collection']} | {r['kind']} | {r['method']} | {s['pairs']} | {s['auc@5']:.1f} | "
            f"{s['auc@10']:.1f} | {s['auc@20']:.1f} | {s['within10']:.1f} | {s['median_matches']:.0f} | "
            f"{s['seconds_per_pair']:.1f} | {_cell(s.get('found'))} | {_cell(s.get('within10_of_found'))} |"
        )
    return "\n".join(out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--root", default="/work/shared/data/collections")
    p.add_argument(
        "--collections", nargs="+", default=list(COLLECTIONS), help=f"{', '.join(COLLECTIONS)}, or one of --gt-model"
    )
    p.add_argument(
        "--gt-model",
        nargs="+",
        default=[],
        metavar="NAME=DIR",
        help="a COLMAP model (binary or text) of collection NAME as its pseudo ground truth",
    )
    p.add_argument("--methods", nargs="+", default=["opencv-sift", "aliked-lightglue:none", "aliked-lightglue:auto"])
    p.add_argument("--pairs", type=int, default=55, help="plain pairs per collection (each also gives a zoom pair)")
    p.add_argument("--kinds", nargs="+", default=["plain", "zoom"], choices=("plain", "zoom"))
    p.add_argument("--max-side", type=int, default=1024)
    p.add_argument("--zoom", type=float, nargs=2, default=(2.5, 6.0), metavar=("MIN", "MAX"))
    p.add_argument("--min-covisible", type=int, default=30, help="3D points two images must share")
    p.add_argument("--min-share", type=float, default=0.1, help="... as a share of the smaller image's points")
    p.add_argument("--max-axis-angle", type=float, default=60.0, help="degrees between the optical axes")
    p.add_argument("--max-error", type=float, default=TwoViewConfig.max_error, help="MAGSAC threshold, pixels")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="results/pose_collections.json")
    p.add_argument("--num-features", type=int, default=None, help="keypoints of the library's matchers (their default)")
    p.add_argument("--auto", nargs="+", default=[], metavar="FIELD=VALUE", help="AutoConfig fields of the auto methods")
    p.add_argument("--cache", default=None, help="per-pair results (JSON lines; default: OUT with .pairs.jsonl)")
    a = p.parse_args(argv)
    if a.pairs < 1 or not 1 <= a.zoom[0] <= a.zoom[1]:
        p.error("--pairs must be >= 1 and 1 <= --zoom MIN <= MAX")
    if any("=" not in g for g in a.gt_model):
        p.error("--gt-model takes NAME=DIR")
    gt_models = dict(g.split("=", 1) for g in a.gt_model)
    unknown = [c for c in a.collections if c not in COLLECTIONS and c not in gt_models]
    if unknown:
        p.error(f"no reader for {', '.join(unknown)}: give its --gt-model NAME=DIR (known: {', '.join(COLLECTIONS)})")
    auto = auto_options(a.auto)
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass

    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cache_path = Path(a.cache) if a.cache else out.with_suffix(".pairs.jsonl")
    options = {"max_side": a.max_side, "max_error": a.max_error, "zoom": list(a.zoom), "seed": a.seed}
    if auto:
        options["auto"] = auto
    if a.num_features:
        options["num_features"] = a.num_features
    if gt_models:
        options["gt_models"] = gt_models
    done = {}
    if cache_path.exists():
        for ln in cache_path.read_text().splitlines():
            try:
                r = json.loads(ln)
            except json.JSONDecodeError:
                continue  # a line cut by an interruption
            if r.get("options") == options:
                done[r["key"]] = r
    cfg = TwoViewConfig(max_error=a.max_error)

    # the pairs and windows, fixed by the seed
    jobs = []
    for name in a.collections:
        col = load_collection(Path(a.root), name, gt_models.get(name))
        pairs = choose_pairs(col, a.pairs, a.seed, a.min_covisible, a.min_share, a.max_axis_angle)
        print(f"{name}: {len(col.views)} registered views, {len(pairs)} pairs", file=sys.stderr)
        for ia, ib in pairs:
            va, vb = col.views[ia], col.views[ib]
            rng = random.Random(f"{a.seed}-{name}-{ia}-{ib}")
            window, turns, z = zoom_window(col, va, vb, rng, a.zoom)
            for kind in a.kinds:
                jobs.append((col, va, vb, kind, window, turns, z))

    t_start = time.time()
    models_cache: dict = {}
    images: Dict[str, np.ndarray] = {}
    with open(cache_path, "a") as log:
        for spec in a.methods:
            todo = [j for j in jobs if f"{j[0].name}|{j[1].name}|{j[2].name}|{j[3]}|{spec}" not in done]
            if not todo:
                continue
            method = make_method(spec, a.max_side, models_cache, auto, a.num_features)
            for col, va, vb, kind, window, turns, z in tqdm(todo, desc=spec):
                key = f"{col.name}|{va.name}|{vb.name}|{kind}|{spec}"
                for v in (va, vb):
                    if str(v.path) not in images:
                        images[str(v.path)] = load_rgb(v.path)
                img_a, img_b = images[str(va.path)], images[str(vb.path)]
                R, t = relative_pose(va, vb)
                cam_b, key_b, R_turn = vb.camera, str(vb.path), np.eye(3)
                if kind == "zoom":
                    img_b, cam_b, R_turn = cut_window(
                        img_b, vb.camera, window, (vb.camera.width, vb.camera.height), turns
                    )
                    R, t = R_turn @ R, R_turn @ t
                    key_b = f"{vb.path}|{window}|{turns}"
                if hasattr(method, "tell_points"):
                    if not col.points:
                        continue  # no 3D points: no oracle
                    method.tell_points(*shared_points_in_view(col, va, vb, cam_b, R_turn), key)
                if hasattr(method, "tell"):
                    if kind == "zoom":
                        method.tell(*true_relation(col, va, vb, window, turns, z))
                    else:
                        method.tell(*true_relation(col, va, vb, None, 0, 1.0))
                rec = evaluate_pair(method, str(va.path), img_a, va.camera, key_b, img_b, cam_b, R, t, cfg)
                rec.update(
                    key=key,
                    collection=col.name,
                    a=va.name,
                    b=vb.name,
                    kind=kind,
                    method=spec,
                    zoom=round(z, 3) if kind == "zoom" else 1.0,
                    turns=turns if kind == "zoom" else 0,
                    window=list(window) if kind == "zoom" else None,
                    options=options,
                )
                log.write(json.dumps(rec) + "\n")
                log.flush()
                done[key] = rec

    wanted = {f"{j[0].name}|{j[1].name}|{j[2].name}|{j[3]}|{spec}" for j in jobs for spec in a.methods}
    current = [r for k, r in done.items() if k in wanted]
    rows = []
    for name in a.collections:
        for kind in a.kinds:
            for spec in a.methods:
                recs = [r for r in current if r["collection"] == name and r["kind"] == kind and r["method"] == spec]
                rows.append(
                    {
                        "collection": name,
                        "kind": kind,
                        "method": spec,
                        "summary": summarise(recs),
                        "summary_colmap_pose": summarise(recs, "err_colmap"),
                    }
                )
    for kind in a.kinds:
        for spec in a.methods:
            recs = [r for r in current if r["kind"] == kind and r["method"] == spec]
            rows.append(
                {
                    "collection": "all",
                    "kind": kind,
                    "method": spec,
                    "summary": summarise(recs),
                    "summary_colmap_pose": summarise(recs, "err_colmap"),
                }
            )
    table = markdown(rows)
    print(table)
    doc = {
        "command": " ".join([Path(sys.argv[0]).name] + (argv if argv is not None else sys.argv[1:])),
        "options": {
            **options,
            "pairs": a.pairs,
            "min_covisible": a.min_covisible,
            "min_share": a.min_share,
            "max_axis_angle": a.max_axis_angle,
            "collections": a.collections,
            "methods": a.methods,
        },
        "protocol": "error = max(rotation, translation direction) in degrees of the essential matrix's pose "
        "(estimate_two_view_geometry with the known cameras), 180 without a pose; AUC in %",
        "wall_seconds_this_run": round(time.time() - t_start, 1),
        "rows": rows,
        "table": table,
    }
    with atomic_path(out) as tmp:
        tmp.write_text(json.dumps(doc, indent=1))
    return 0


def cli(argv=None) -> int:
    """:func:`main` with bad input reported as one ``error:`` line and exit code 2."""
    try:
        return main(argv)
    except (LocalScaleError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(cli())
