"""Relative pose on real photo collections: plain pairs and zoom + quarter-turn pairs.

The SuperGlue/LightGlue protocol the ScaleNet paper uses: for each image pair with a known
relative pose, match, estimate the essential matrix from the matches with the known intrinsics
(:func:`localscale.geometry.two_view.estimate_two_view_geometry`: MAGSAC, cheirality, refinement),
error = max(rotation error, translation-direction error) in degrees (180 when no pose), and report
the AUC at 5/10/20 degrees and the share of pairs within 10 degrees. Each pair's record (and the
summary's median) also counts the returned matches that the true pose explains (``correct``:
:func:`localscale.geometry.two_view.epipolar_errors` below :data:`EPIPOLAR_THRESHOLD` in normalised coordinates,
SuperGlue's precision), which tells wrong matches from a pose the right matches do not pin down.
The collections, pairs and zoom windows: :mod:`localscale.evaluation.pose_data`.

Methods: ``opencv-sift`` (OpenCV SIFT, 4096 features, ratio 0.8, mutual nearest neighbours) and
``MATCHER:CORRECTION`` for the library's ``match_pair(A, B, correction, matcher=MATCHER)``
(e.g. ``aliked-lightglue:none``, ``aliked-lightglue:auto``); only the returned matches are used.
``MATCHER:truth`` and ``MATCHER:truth-window`` are upper bounds of ``auto``'s choice: the matcher
is given the true zoom and quarter turn as its only hypothesis (B' shrunk, as the matcher rectifies),
and with ``truth-window`` also the part of A that B' shows (the co-visible 3D points that project
into B's window, their box in A grown by a quarter on each side), enlarged instead; temple has no
points, so no window. ``MATCHER:CORRECTION:cameras`` also passes the known cameras (two-view
verification with the essential matrix), ``MATCHER:CORRECTION:two_view`` verifies by COLMAP's
homography / fundamental matrix choice without cameras. ``points:SIGMA`` is no matcher
(:class:`PointsOracle`): the shared 3D points' true projections with ``SIGMA`` pixels of noise, the
bound the views' geometry sets (collections with 3D points only).

:func:`run` appends per-pair results to a JSON-lines cache as they are computed and skips the pairs
found there (same collection, pair, kind, method and options); the summary (rows per collection,
kind and method, and a markdown table) is written atomically.
"""

from __future__ import annotations

import dataclasses
import json
import math
import random
import sys
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import cv2
import numpy as np
from tqdm import tqdm

from ..core.errors import LocalScaleError
from ..core.outputs import atomic_path
from ..geometry.cameras import Camera, cut_window
from ..geometry.two_view import (
    TwoViewConfig,
    epipolar_errors,
    estimate_two_view_geometry,
    pose_auc,
    relative_pose_error,
)
from .pose_data import (
    COLLECTIONS,
    View,
    choose_pairs,
    load_collection,
    relative_pose,
    shared_points_in_view,
    true_relation,
    zoom_window,
)
from .report import git_commit

THRESHOLDS = (5, 10, 20)


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

    def __init__(
        self,
        name: str,
        correction: str,
        max_side: int,
        models,
        given: str = "",
        auto=None,
        features=None,
        precision=None,
        confidences=None,
    ):
        from localscale.matching import AutoConfig, get_matcher

        options = {"auto": AutoConfig(**auto)} if auto else {}
        if features:
            options["num_features"] = features
        if precision:
            options["lightglue_precision"] = precision
        if confidences:
            options["depth_confidence"], options["width_confidence"] = confidences
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
    (:func:`localscale.matching.try_hypotheses` without the images as they are, the seed or the networks)."""

    def __init__(self, name: str, max_side: int, window: bool, features=None):
        from localscale.matching import get_matcher

        self.matcher = get_matcher(name, max_side=max_side, **({"num_features": features} if features else {}))
        self.window = window
        self.truth = None
        self.trials = None

    def tell(self, scale: float, turn: int, window_a):
        self.truth = (scale, turn, window_a if self.window else None)

    def match(self, key_a, a, key_b, b, cameras=(None, None)):
        from localscale.matching import Hypothesis, try_hypotheses

        if max(a.shape[:2] + b.shape[:2]) > self.matcher.config.max_side:
            raise LocalScaleError("truth methods need images within --max-side")
        scale, turn, window = self.truth
        h = Hypothesis(scale, turn, "truth", window=None if window is None else (0, *window))
        config = dataclasses.replace(self.matcher.config.auto, locate=False)
        out = try_hypotheses(self.matcher, a, b, config=config, keys=(key_a, key_b), hypotheses=[h], networks=False)
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


def make_method(
    spec: str,
    max_side: int,
    models_cache: dict,
    auto=None,
    features=None,
    precision=None,
    confidences=None,
    local_weights=None,
):
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

        models_cache["models"] = (LocalScaleNet.from_pretrained(local_weights), ScaleNet.from_pretrained())
    return LibraryMatcher(
        name,
        correction,
        max_side,
        models_cache["models"],
        *given,
        auto=auto,
        features=features,
        precision=precision,
        confidences=confidences,
    )


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


# ---------------------------------------------------------------------------- a run
@dataclass
class PoseRun:
    """One evaluation: collections, methods and the protocol's options (the script's flags)."""

    root: str = "/work/shared/data/collections"
    collections: List[str] = field(default_factory=lambda: list(COLLECTIONS))
    gt_models: Dict[str, str] = field(default_factory=dict)  # collection -> COLMAP model folder
    methods: List[str] = field(
        default_factory=lambda: ["opencv-sift", "aliked-lightglue:none", "aliked-lightglue:auto"]
    )
    pairs: int = 55
    kinds: List[str] = field(default_factory=lambda: ["plain", "zoom"])
    max_side: int = 1024
    zoom: tuple = (2.5, 6.0)
    min_covisible: int = 30
    min_share: float = 0.1
    max_axis_angle: float = 60.0
    max_error: float = TwoViewConfig.max_error
    seed: int = 0
    out: str = "results/pose_collections.json"
    num_features: Optional[int] = None
    lightglue_precision: Optional[str] = None  #: the library matchers' (None: their default)
    lightglue_confidence: Optional[tuple] = None  #: LightGlue's (depth, width) confidences (None: kornia's)
    auto: dict = field(default_factory=dict)  # AutoConfig fields of the auto methods
    cache: Optional[str] = None  # per-pair JSON lines (default: out with .pairs.jsonl)
    local_weights: Optional[str] = None  #: Local-ScaleNet weights of the corrections (None: the bundled)

    def cache_options(self) -> dict:
        """The options a cached pair record must match to be reused."""
        options = {"max_side": self.max_side, "max_error": self.max_error, "zoom": list(self.zoom), "seed": self.seed}
        if self.auto:
            options["auto"] = self.auto
        if self.num_features:
            options["num_features"] = self.num_features
        if self.lightglue_precision:
            options["lightglue_precision"] = self.lightglue_precision
        if self.lightglue_confidence:
            options["lightglue_confidence"] = list(self.lightglue_confidence)
        if self.gt_models:
            options["gt_models"] = self.gt_models
        if self.local_weights:
            options["local_weights"] = self.local_weights
        return options


def read_cache(path: Path, options: dict) -> Dict[str, dict]:
    """The cached pair records of ``path`` made with ``options``, by key."""
    done = {}
    if path.exists():
        for ln in path.read_text().splitlines():
            try:
                r = json.loads(ln)
            except json.JSONDecodeError:
                continue  # a line cut by an interruption
            if r.get("options") == options:
                done[r["key"]] = r
    return done


def make_jobs(cfg: PoseRun) -> list:
    """``(collection, view A, view B, kind, window, turns, z)`` of every pair and kind, fixed by the seed."""
    jobs = []
    for name in cfg.collections:
        col = load_collection(Path(cfg.root), name, cfg.gt_models.get(name))
        pairs = choose_pairs(col, cfg.pairs, cfg.seed, cfg.min_covisible, cfg.min_share, cfg.max_axis_angle)
        print(f"{name}: {len(col.views)} registered views, {len(pairs)} pairs", file=sys.stderr)
        for ia, ib in pairs:
            va, vb = col.views[ia], col.views[ib]
            rng = random.Random(f"{cfg.seed}-{name}-{ia}-{ib}")
            window, turns, z = zoom_window(col, va, vb, rng, cfg.zoom)
            for kind in cfg.kinds:
                jobs.append((col, va, vb, kind, window, turns, z))
    return jobs


def job_key(job: tuple, spec: str) -> str:
    col, va, vb, kind = job[:4]
    return f"{col.name}|{va.name}|{vb.name}|{kind}|{spec}"


def load_rgb_cached(images: Dict[str, np.ndarray], view: View) -> np.ndarray:
    if str(view.path) not in images:
        images[str(view.path)] = load_rgb(view.path)
    return images[str(view.path)]


def pair_views(job: tuple, images: Dict[str, np.ndarray]):
    """``(image A, image B', camera of B', key of B', R, t, R_turn)`` of a job: B' is B, or for a
    zoom pair its window turned, with the true pose ``x_B' = R x_A + t``."""
    col, va, vb, kind, window, turns, _ = job
    img_a, img_b = load_rgb_cached(images, va), load_rgb_cached(images, vb)
    R, t = relative_pose(va, vb)
    cam_b, key_b, R_turn = vb.camera, str(vb.path), np.eye(3)
    if kind == "zoom":
        img_b, cam_b, R_turn = cut_window(img_b, vb.camera, window, (vb.camera.width, vb.camera.height), turns)
        R, t = R_turn @ R, R_turn @ t
        key_b = f"{vb.path}|{window}|{turns}"
    return img_a, img_b, cam_b, key_b, R, t, R_turn


def tell_truth(method, job: tuple, cam_b: Camera, R_turn: np.ndarray, key: str) -> bool:
    """Give the oracle and truth methods what they are told; False when the job has nothing to
    give (an oracle on a collection without 3D points)."""
    col, va, vb, kind, window, turns, z = job
    if hasattr(method, "tell_points"):
        if not col.points:
            return False
        method.tell_points(*shared_points_in_view(col, va, vb, cam_b, R_turn), key)
    if hasattr(method, "tell"):
        if kind == "zoom":
            method.tell(*true_relation(col, va, vb, window, turns, z))
        else:
            method.tell(*true_relation(col, va, vb, None, 0, 1.0))
    return True


def evaluate_method(spec: str, method, todo: list, cfg: PoseRun, options: dict, log, images: dict) -> Dict[str, dict]:
    """The records of ``method`` on the jobs ``todo``, each appended to ``log`` as it is made."""
    two_view = TwoViewConfig(max_error=cfg.max_error)
    done = {}
    for job in tqdm(todo, desc=spec):
        col, va, vb, kind, window, turns, z = job
        key = job_key(job, spec)
        img_a, img_b, cam_b, key_b, R, t, R_turn = pair_views(job, images)
        if not tell_truth(method, job, cam_b, R_turn, key):
            continue  # no 3D points: no oracle
        rec = evaluate_pair(method, str(va.path), img_a, va.camera, key_b, img_b, cam_b, R, t, two_view)
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
    return done


def summary_rows(cfg: PoseRun, records: List[dict]) -> List[dict]:
    """A row per collection, kind and method, then per kind and method over all collections."""

    def row(collection, kind, spec):
        recs = [r for r in records if r["kind"] == kind and r["method"] == spec]
        if collection != "all":
            recs = [r for r in recs if r["collection"] == collection]
        return {
            "collection": collection,
            "kind": kind,
            "method": spec,
            "summary": summarise(recs),
            "summary_colmap_pose": summarise(recs, "err_colmap"),
        }

    rows = [row(name, kind, spec) for name in cfg.collections for kind in cfg.kinds for spec in cfg.methods]
    return rows + [row("all", kind, spec) for kind in cfg.kinds for spec in cfg.methods]


def run(cfg: PoseRun, command: str = "") -> dict:
    """Evaluate ``cfg``'s methods on its pairs (resuming from the cache), print the table and write
    the summary to ``cfg.out``; returns the summary."""
    out = Path(cfg.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cache_path = Path(cfg.cache) if cfg.cache else out.with_suffix(".pairs.jsonl")
    options = cfg.cache_options()
    done = read_cache(cache_path, options)
    jobs = make_jobs(cfg)
    t_start = time.time()
    models_cache: dict = {}
    images: Dict[str, np.ndarray] = {}
    with open(cache_path, "a") as log:
        for spec in cfg.methods:
            todo = [j for j in jobs if job_key(j, spec) not in done]
            if todo:
                method = make_method(
                    spec,
                    cfg.max_side,
                    models_cache,
                    cfg.auto,
                    cfg.num_features,
                    cfg.lightglue_precision,
                    cfg.lightglue_confidence,
                    cfg.local_weights,
                )
                done.update(evaluate_method(spec, method, todo, cfg, options, log, images))
    wanted = {job_key(j, spec) for j in jobs for spec in cfg.methods}
    rows = summary_rows(cfg, [r for k, r in done.items() if k in wanted])
    table = markdown(rows)
    print(table)
    doc = {
        "command": command,
        "commit": git_commit(),
        "options": {
            **options,
            "pairs": cfg.pairs,
            "min_covisible": cfg.min_covisible,
            "min_share": cfg.min_share,
            "max_axis_angle": cfg.max_axis_angle,
            "collections": cfg.collections,
            "methods": cfg.methods,
        },
        "protocol": "error = max(rotation, translation direction) in degrees of the essential matrix's pose "
        "(estimate_two_view_geometry with the known cameras), 180 without a pose; AUC in %",
        "wall_seconds_this_run": round(time.time() - t_start, 1),
        "rows": rows,
        "table": table,
    }
    with atomic_path(out) as tmp:
        tmp.write_text(json.dumps(doc, indent=1))
    return doc
