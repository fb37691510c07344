"""HPatches-style matching evaluation with and without patch-size correction.

Layout: ``<root>/<seq>/1.ppm .. 6.ppm`` (also ``.png`` / ``.jpg``) and ``H_1_2 .. H_1_6``;
``v_*`` (viewpoint) and ``i_*`` (illumination) sequences as in HPatches, or folders
without a prefix (e.g. the Oxford ``bark``, ``boat``...). ``i_*`` sequences are skipped by
default (``--include-illumination``); ``--exclude-hires`` drops the usual high-resolution
sequences :data:`HIGH_RES`.

Protocol (D2-Net's MMA): for each pair ``(1, k)``: the single-scale Hessian detector's
top-K keypoints (default 1000; ``--detector`` swaps in another single-scale detector of
:data:`localscale.features.detector.DETECTORS`) in both images, 32x32 patches with the patch-size
correction of each method, descriptors, mutual nearest neighbours, and the
mean matching accuracy MMA@t = fraction of matches with ``|H x_A - x_B| < t`` px
(t = 1..10), averaged over pairs; plus mean numbers of matches and features.

Methods: ``none``, ``global`` (ScaleNet), ``local`` (Local-ScaleNet, gated), ``gt``
(analytic map of the GT homography), ``gt_gated`` (the GT map through the same gate as
``local``, to measure what gating costs an oracle), ``pyramid`` (optional baseline: no scale maps,
keypoints detected and described on a 4-level image pyramid with step sqrt(2)... 2),
``refined`` (the ``local`` maps, matching, verification with a MAGSAC homography, maps refined by
the verified geometry and a second matching pass; when the first pass is not verified, the
``opencv-sift`` matches are verified instead and their geometry refines the maps;
:func:`localscale.features.verification.refine_matching`),
``opencv-sift`` (baseline: OpenCV's DoG detector, top-K keypoints, OpenCV SIFT descriptors,
mutual nearest neighbours that pass Lowe's ratio test 0.8).

Homography accuracy (every method): a homography estimated from the method's matches with OpenCV
``USAC_MAGSAC`` (3 px), the mean error of A's four corners against the ground truth
(:func:`localscale.features.verification.corner_error`), its AUC at 3 / 5 / 10 px over the pairs
and the share of pairs solved (corner error < 10 px).

Splits, from the GT homography of each pair:

* perspective: ``spread`` = std of ``log2`` of the analytic scale map over the co-visible
  region (:func:`localscale.geometry.perspective_spread`): ``easy`` < 0.1 <= ``medium``
  < 0.25 <= ``hard``;
* global scale: ``g = |log2 global_scale|`` (geometric mean of the map over the co-visible
  region): ``scale<1.4x`` for g < 0.5, ``scale1.4-2.8x`` for 0.5 <= g < 1.5, ``scale>2.8x``.

Predicted maps go through :class:`localscale.features.CorrectionGate` (default pair level 0.25,
chosen on a synthetic selection set; the measurements are in ``docs/RESULTS.md``). Compare gates
with ``--gate-pair X [--no-consistency]``.

Outputs in ``--out``: ``results.json`` (per-pair records, summaries, splits), ``splits.csv``
(the split of every pair), ``results.md`` (tables) and ``mma_<split>.png`` plots.
"""
from __future__ import annotations

import argparse
import csv
import io
import json
import math
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Optional, Sequence

import cv2
import numpy as np
import torch

from ..errors import HomographyError, LocalScaleError
from ..features.correction import GATE_WEIGHTINGS
from ..geometry import covisible_mask, global_scale, orient_homography, perspective_spread
from ..io import load_image, read_homography

HIGH_RES = ("i_contruction", "i_crownnight", "i_dc", "i_pencils", "i_whitebuilding", "v_artisans",
            "v_astronautis", "v_talent")
IMAGE_EXTS = (".ppm", ".png", ".jpg", ".jpeg", ".pgm", ".bmp", ".tif", ".tiff")
METHODS = ("none", "global", "local", "fused", "searched", "gt", "gt_gated", "pyramid", "refined", "opencv-sift")
H_AUC_THRESHOLDS = (3.0, 5.0, 10.0)
SOLVED_PX = 10.0
SIFT_RATIO = 0.8
THRESHOLDS = tuple(range(1, 11))
PERSPECTIVE_EDGES = (0.1, 0.25)
SCALE_EDGES = (0.5, 1.5)


@dataclass
class HSequence:
    name: str
    images: dict                 #: index -> path
    homographies: dict           #: k -> H_1_k
    bad: dict = field(default_factory=dict)   #: k -> why pair (1, k) cannot be evaluated (bad H_1_k)


@dataclass
class PairInfo:
    sequence: str
    k: int
    image_a: Path
    image_b: Path
    H: np.ndarray
    spread: float = 0.0
    log2_scale: float = 0.0
    perspective_split: str = ""
    scale_split: str = ""
    covisible: float = 0.0

    @property
    def name(self) -> str:
        return f"{self.sequence}/1-{self.k}"


def _find_image(folder: Path, index: int) -> Optional[Path]:
    for ext in IMAGE_EXTS:
        for cand in (folder / f"{index}{ext}", folder / f"{index}{ext.upper()}"):
            if cand.is_file():
                return cand
    return None


def load_hpatches(root, include_illumination: bool = False, exclude_hires: bool = False,
                  exclude: Iterable[str] = (), sequences: Optional[Iterable[str]] = None) -> list[HSequence]:
    """Sequences of an HPatches-layout folder (sorted by name).

    A sub-folder counts as a sequence when it has image ``1.*`` and at least one ``H_1_k``
    with image ``k.*``. ``i_*`` are skipped unless ``include_illumination``.
    """
    root = Path(root)
    if not root.is_dir():
        raise LocalScaleError(f"HPatches root not found: {root}")
    exclude = set(exclude) | (set(HIGH_RES) if exclude_hires else set())
    wanted = set(sequences) if sequences is not None else None
    out = []
    for d in sorted(p for p in root.iterdir() if p.is_dir()):
        if d.name in exclude or (wanted is not None and d.name not in wanted):
            continue
        if d.name.startswith("i_") and not include_illumination:
            continue
        first = _find_image(d, 1)
        if first is None:
            continue
        images, Hs, bad = {1: first}, {}, {}
        for hf in sorted(d.glob("H_1_*")):
            m = re.fullmatch(r"H_1_(\d+)", hf.name)
            if not m:
                continue
            k = int(m.group(1))
            img = _find_image(d, k)
            if img is None:
                continue
            images[k] = img
            try:
                Hs[k] = read_homography(hf)
            except HomographyError as e:
                bad[k] = " ".join(str(e).split())
        if Hs or bad:
            out.append(HSequence(d.name, images, Hs, bad))
    if not out:
        raise LocalScaleError(f"no sequences (folders with 1.ppm/png/jpg and H_1_k files) in {root}")
    return out


def _warn(message: str) -> None:
    """One ``warning: ...`` line on stderr (beside a progress bar)."""
    from tqdm import tqdm

    tqdm.write(f"warning: {' '.join(message.split())}", file=sys.stderr)


def perspective_split(spread: float) -> str:
    return "easy" if spread < PERSPECTIVE_EDGES[0] else ("medium" if spread < PERSPECTIVE_EDGES[1] else "hard")


def scale_split(log2_scale: float) -> str:
    g = abs(log2_scale)
    return "scale<1.4x" if g < SCALE_EDGES[0] else ("scale1.4-2.8x" if g < SCALE_EDGES[1] else "scale>2.8x")


def image_size(path: Path) -> tuple[int, int]:
    """``(height, width)`` from the file header (upright, EXIF orientation applied); raises
    :class:`~localscale.errors.ImageError` for a file that cannot be used (unreadable header,
    smaller than :data:`localscale.io.MIN_SIDE` or above :data:`localscale.io.MAX_PIXELS`)."""
    from ..errors import ImageError
    from ..io import _check_size, _header, _stat_file

    _stat_file(Path(path), "image")
    try:
        header = _header(Path(path))
    except OSError as e:
        raise ImageError(f"cannot read {path} ({e.strerror})") from None
    if header is None:
        raise ImageError(f"cannot read the image size of {path} (corrupt, truncated or unsupported format)")
    (w, h), orientation = header
    _check_size(h, w, str(path))
    return (w, h) if orientation in (5, 6, 7, 8) else (h, w)


#: a pair whose GT homography maps less than this fraction of image 1 into image k is warned about
MIN_COVISIBLE = 0.05


def make_pairs(seqs: Sequence[HSequence], skipped: Optional[list] = None) -> list[PairInfo]:
    """All ``(1, k)`` pairs with their perspective / scale splits.

    Pairs that cannot be evaluated (bad ``H_1_k``, an image whose size cannot be read or is too
    small, an ``H`` that maps all of image 1 outside image k) are left out with a warning and
    appended to ``skipped`` as ``{"pair", "reason"}``; a pair where ``H`` maps less than
    :data:`MIN_COVISIBLE` of image 1 into image k is kept with a warning.
    """
    pairs = []
    skipped = [] if skipped is None else skipped

    def skip(name, reason):
        reason = " ".join(str(reason).split())
        _warn(f"pair {name} skipped: {reason}")
        skipped.append({"pair": name, "reason": reason})

    for s in seqs:
        for k, why in sorted(s.bad.items()):
            skip(f"{s.name}/1-{k}", why)
        try:
            sa = image_size(s.images[1])
        except LocalScaleError as e:
            for k in sorted(s.homographies):
                skip(f"{s.name}/1-{k}", e)
            continue
        for k, H in sorted(s.homographies.items()):
            name = f"{s.name}/1-{k}"
            try:
                sb = image_size(s.images[k])
            except LocalScaleError as e:
                skip(name, e)
                continue
            H = orient_homography(H, sa)
            covisible = float(covisible_mask(H, sa, sb, 8).mean())
            if not covisible > 0:
                skip(name, f"H_1_{k} maps all of image 1 outside image {k} ({sb[1]}x{sb[0]}): check that H and "
                           f"the images belong together")
                continue
            if covisible < MIN_COVISIBLE:
                _warn(f"pair {name}: H_1_{k} maps only {covisible:.1%} of image 1 into image {k}; "
                      f"check that H and the image sizes belong together")
            p = PairInfo(s.name, k, s.images[1], s.images[k], H)
            p.spread = perspective_spread(H, sa, sb)
            try:
                p.log2_scale = math.log2(global_scale(H, sa, sb))
            except ValueError:
                p.log2_scale = float("nan")
            p.covisible = covisible
            p.perspective_split, p.scale_split = perspective_split(p.spread), scale_split(p.log2_scale)
            pairs.append(p)
    return pairs


#: :func:`content_agreement` below this is warned about (the Oxford and HPatches pairs of
#: ``docs/RESULTS.md`` give 0.5-1.0; the same pairs with image k at half the size H expects, <= 0.15)
MIN_AGREEMENT = 0.25


def content_agreement(a: np.ndarray, b: np.ndarray, H: np.ndarray, side: int = 192) -> float:
    """Correlation of image-1 gradients with those of image k warped into image 1 by ``H``, over the
    co-visible region, at ``side`` px: near 0 when ``H`` does not belong to the images (e.g. an image
    of another size than the one ``H`` was measured on), 1 for a perfect fit. NaN-free; 1.0 when
    too little is co-visible to tell."""
    f = side / max(a.shape[:2])
    fb = side / max(b.shape[:2])
    S = np.diag([f, f, 1.0]) @ np.asarray(H, np.float64) @ np.diag([1 / f, 1 / f, 1.0])
    S = np.diag([fb / f, fb / f, 1.0]) @ S
    ga = cv2.cvtColor(cv2.resize(a, (max(1, round(a.shape[1] * f)), max(1, round(a.shape[0] * f))),
                                 interpolation=cv2.INTER_AREA), cv2.COLOR_RGB2GRAY).astype(np.float32)
    gb = cv2.cvtColor(cv2.resize(b, (max(1, round(b.shape[1] * fb)), max(1, round(b.shape[0] * fb))),
                                 interpolation=cv2.INTER_AREA), cv2.COLOR_RGB2GRAY).astype(np.float32)
    size = (ga.shape[1], ga.shape[0])
    warped = cv2.warpPerspective(gb, S, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    cover = cv2.warpPerspective(np.ones_like(gb), S, size, flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP)
    mask = cv2.erode(cover, np.ones((5, 5), np.uint8)) > 0.5
    if mask.sum() < 200:
        return 1.0

    def grad(g):
        g = cv2.GaussianBlur(g, (0, 0), 1.0)
        return np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))

    x, y = grad(ga)[mask], grad(warped)[mask]
    x, y = x - x.mean(), y - y.mean()
    den = float(np.sqrt((x * x).sum() * (y * y).sum()))
    return float((x * y).sum() / den) if den > 0 else 1.0


def _resize(img: np.ndarray, max_side: Optional[int]) -> tuple[np.ndarray, float]:
    if not max_side or max(img.shape[:2]) <= max_side:
        return img, 1.0
    f = max_side / max(img.shape[:2])
    return cv2.resize(img, (round(img.shape[1] * f), round(img.shape[0] * f)), interpolation=cv2.INTER_AREA), f


class _Evaluator:
    """Caches images, keypoints, network encodings and descriptors across the methods and pairs of a run.

    Work shared between methods (results are the same as computing each method on its own):

    * keypoints and the local / global networks' encodings of an image are computed once
      (image 1 of a sequence is in every pair of it);
    * the global scale of a pair is predicted once (``global`` and ``fused``), and so are the
      two local maps (``local`` and ``fused``);
    * descriptors: a keypoint's patch depends only on the image, the keypoint and its radius,
      so a keypoint whose corrected radius equals one already described for this image
      (e.g. the base radius of ``none``, kept wherever ``S >= 1``) reuses that descriptor;
      only the keypoints with a new radius are cut and described.
    """

    def __init__(self, descriptor, num_features, local_model, global_model, gate, base_radius, orientation,
                 max_side, levels=4, detector="hessian"):
        from ..features.descriptors import get_descriptor
        from ..features.detector import get_detector
        self.desc = get_descriptor(descriptor)
        get_detector(detector)                      # an unknown name fails before the first pair
        self.detector = detector
        self.num_features, self.local_model, self.global_model = num_features, local_model, global_model
        self.gate, self.base_radius, self.orientation, self.max_side = gate, base_radius, orientation, max_side
        self.levels = levels
        self._keep = set()
        self._img, self._kps, self._enc, self._genc, self._desc = {}, {}, {}, {}, {}
        self._memo = {}
        self.described = 0    #: patches described so far (the rest were reused)
        self.suspicious = {}  #: pair -> content agreement, for pairs below :data:`MIN_AGREEMENT`
        self.refine_passes = 2
        self.sift_seed = True

    def image(self, path):
        if path not in self._img:
            self._img = {k: v for k, v in self._img.items() if k in self._keep}
            self._img[path] = _resize(load_image(path), self.max_side)
        return self._img[path]

    def keypoints(self, path):
        from ..features.detector import get_detector, image_to_gray_tensor
        if path not in self._kps:
            img, _ = self.image(path)
            g = image_to_gray_tensor(img)
            kps, _ = get_detector(self.detector, self.num_features)(g)
            self._kps[path] = (g, kps)
        return self._kps[path]

    def encoding(self, path):
        if path not in self._enc:
            self._enc[path] = self.local_model.encode_image(self.image(path)[0])
        return self._enc[path]

    def global_encoding(self, path, bf16=False):
        if (path, bf16) not in self._genc:
            self._genc[(path, bf16)] = self.global_model.encode_image(self.image(path)[0], "image", bf16)
        return self._genc[(path, bf16)]

    def describe(self, path, scale_map):
        """``(keypoints N x 2, descriptors N x D)`` of an image with the patch radii of ``scale_map``."""
        from ..features.patches import ScaleCorrectedPatches, patch_radii
        g, kps = self.keypoints(path)
        cutter = ScaleCorrectedPatches(self.base_radius, self.desc.patch_size, self.orientation)
        radii = patch_radii(kps, scale_map, self.base_radius, tuple(g.shape[-2:]), cutter.deadzone_log2)
        known = self._desc.setdefault(path, [])
        desc = torch.zeros(len(kps), self.desc.dim)
        todo = torch.ones(len(kps), dtype=torch.bool)
        for r, d in known:
            same = todo & (r == radii)
            desc[same] = d[same]
            todo &= ~same
        if todo.any():
            idx = torch.nonzero(todo).flatten()
            patches, _ = cutter.patches_from_radii(g, kps[idx], radii[idx])
            desc[idx] = self.desc.describe(patches)
            self.described += len(idx)
            known.append((radii, desc))
        return kps.numpy(), desc

    def pyramid(self, path):
        """Keypoints + descriptors on a sqrt(2)-step pyramid, coordinates in level 0."""
        from ..features.detector import get_detector, image_to_gray_tensor
        from ..features.patches import ScaleCorrectedPatches
        img, _ = self.image(path)
        kps_all, desc_all = [], []
        per = max(1, self.num_features // self.levels)
        for lvl in range(self.levels):
            f = 2 ** (-lvl / 2)
            im = img if lvl == 0 else cv2.resize(img, (max(16, round(img.shape[1] * f)), max(16, round(img.shape[0] * f))),
                                                 interpolation=cv2.INTER_AREA)
            g = image_to_gray_tensor(im)
            k, _ = get_detector(self.detector, per)(g)
            p, _, _ = ScaleCorrectedPatches(self.base_radius, 32, self.orientation)(g, k, None)
            fx, fy = img.shape[1] / im.shape[1], img.shape[0] / im.shape[0]
            kps_all.append(k.numpy() * np.array([fx, fy], np.float32) + np.array([(fx - 1) / 2, (fy - 1) / 2], np.float32))
            desc_all.append(self.desc.describe(p))
        return np.concatenate(kps_all), torch.cat(desc_all)

    def refined(self, pair: PairInfo, a, b, H):
        """Keypoints, descriptors' matches and verification of ``refined`` (``local`` maps as the first
        pass and as the prior of the refined maps)."""
        from ..features.verification import VerificationConfig, refine_matching
        sa, sb = self.scale_maps(pair, "local", a, b, H)
        local = _SharedLocal(self, self.local_model)
        ea, eb = self.encoding(pair.image_a), self.encoding(pair.image_b)
        pa = local.predict_from_features(ea, eb, bf16=False).scale
        pb = local.predict_from_features(eb, ea, bf16=False).scale
        def seed():
            (ka, da), (kb, db) = self.opencv_sift(pair.image_a), self.opencv_sift(pair.image_b)
            m = opencv_ratio_matches(da, db, SIFT_RATIO)
            return ka[m[:, 0]], kb[m[:, 1]]

        return refine_matching(lambda s: self.describe(pair.image_a, s), lambda s: self.describe(pair.image_b, s),
                               a.shape[:2], b.shape[:2], sa, sb, pa, pb, VerificationConfig(), self.refine_passes,
                               seed=seed if self.sift_seed else None)

    def opencv_sift(self, path):
        """OpenCV DoG keypoints (top ``num_features``) and SIFT descriptors of an image."""
        if ("sift", path) not in self._memo:
            img, _ = self.image(path)
            gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
            kps, desc = cv2.SIFT_create(nfeatures=self.num_features).detectAndCompute(gray, None)
            xy = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
            self._memo[("sift", path)] = (xy, np.zeros((0, 128), np.float32) if desc is None else desc)
        return self._memo[("sift", path)]

    def _once(self, key, fn):
        if key not in self._memo:
            self._memo[key] = fn()
        return self._memo[key]

    def scale_maps(self, pair: PairInfo, m: str, a, b, H):
        """The maps of method ``m`` for the pair (:func:`scale_maps_for_pair` with shared work)."""
        from ..features.correction import CORRECTIONS, scale_maps_for_pair
        if m == "gt_gated":
            return self.gate.apply_pair(*scale_maps_for_pair(a, b, "gt", H))
        if m not in CORRECTIONS:
            raise LocalScaleError(f"unknown method {m!r}; choose from {METHODS}")
        enc = (self.encoding(pair.image_a), self.encoding(pair.image_b)) if m in ("local", "fused") else None
        # the search makes and drops many encodings: keyed by id(), the shared cache could mix them up
        local = (self.local_model if m == "searched" else _SharedLocal(self, self.local_model)) \
            if self.local_model is not None else None
        glob = _SharedGlobal(self, self.global_model, pair) if self.global_model is not None else None
        return scale_maps_for_pair(a, b, m, H, local, glob, self.gate, enc)

    def run_pair(self, pair: PairInfo, methods, thresholds) -> list[dict]:
        from ..features.matching import match_descriptors, matching_accuracy, reprojection_errors
        self._keep = {pair.image_a, pair.image_b}
        self._memo = {}
        for cache in (self._kps, self._enc, self._desc):
            for p in [p for p in cache if p not in self._keep]:
                del cache[p]
        self._genc = {k: v for k, v in self._genc.items() if k[0] in self._keep}
        a, fa = self.image(pair.image_a)
        b, fb = self.image(pair.image_b)
        H = np.diag([fb, fb, 1.0]) @ pair.H @ np.diag([1 / fa, 1 / fa, 1.0])
        agreement = content_agreement(a, b, H)
        if agreement < MIN_AGREEMENT and pair.name not in self.suspicious:
            self.suspicious[pair.name] = round(agreement, 3)
            _warn(f"pair {pair.name}: image {pair.k} warped by H_1_{pair.k} does not look like image 1 "
                  f"(correlation {agreement:.2f}); check that H and the image sizes belong together")
        recs = []
        for m in methods:
            t0 = time.time()
            extra = {}
            if m == "refined":
                rm = self.refined(pair, a, b, H)
                ka, kb, idx = rm.keypoints_a, rm.keypoints_b, rm.matches
                extra = {"verified": bool(rm.refined_a.verified), "passes": rm.passes,
                         "inlier_counts": list(rm.inlier_counts),
                         "seed_verified": None if rm.seed is None else bool(rm.seed.verified)}
            elif m == "opencv-sift":
                (ka, da), (kb, db) = self.opencv_sift(pair.image_a), self.opencv_sift(pair.image_b)
                idx = opencv_ratio_matches(da, db, SIFT_RATIO)
            else:
                if m == "pyramid":
                    ka, da = self.pyramid(pair.image_a)
                    kb, db = self.pyramid(pair.image_b)
                else:
                    sa, sb = self.scale_maps(pair, m, a, b, H)
                    ka, da = self.describe(pair.image_a, sa)
                    kb, db = self.describe(pair.image_b, sb)
                _, idx = match_descriptors(da, db)
                idx = idx.numpy()
            err = reprojection_errors(ka, kb, idx, H)
            mma = matching_accuracy(err, thresholds)
            recs.append({"pair": pair.name, "method": m, "num_features_a": int(len(ka)), "num_features_b": int(len(kb)),
                         "num_matches": int(len(idx)), "num_correct_5px": int((err < 5).sum()),
                         "mma": [float(v) for v in mma], "corner_error": homography_corner_error(ka, kb, idx, H, a.shape),
                         "seconds": round(time.time() - t0, 2),
                         "perspective_split": pair.perspective_split, "scale_split": pair.scale_split, **extra})
        return recs


def opencv_ratio_matches(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float = SIFT_RATIO) -> np.ndarray:
    """Mutual nearest neighbours that pass Lowe's ratio test
    (:func:`localscale.features.verification.ratio_mutual_matches`); ``K x 2`` int64 indices."""
    from ..features.verification import ratio_mutual_matches
    return ratio_mutual_matches(desc_a, desc_b, ratio)


def homography_corner_error(keypoints_a, keypoints_b, matches, H_true, shape_a) -> float:
    """Corner error (px of B) of the homography estimated from the matches (``USAC_MAGSAC``, 3 px);
    ``inf`` when none can be estimated."""
    from ..features.verification import corner_error, estimate_homography
    m = np.asarray(matches, np.int64).reshape(-1, 2)
    H_est, _ = estimate_homography(np.asarray(keypoints_a)[m[:, 0]], np.asarray(keypoints_b)[m[:, 1]])
    return corner_error(H_est, H_true, shape_a)


class _SharedLocal:
    """The local model for one pair: ``predict_from_features`` of an ordered pair of encodings runs once."""

    def __init__(self, ev: _Evaluator, model):
        self._ev, self._model = ev, model

    def predict_from_features(self, ea, eb, **kw):
        key = ("local", id(ea), id(eb), tuple(sorted(kw.items())))
        return self._ev._once(key, lambda: self._model.predict_from_features(ea, eb, **kw))

    def __getattr__(self, name):
        return getattr(self._model, name)


class _SharedGlobal:
    """The global model for one pair: each image is encoded once per run (while it is in the current
    pair), the pair's prediction is made once. ``predict(a, b)`` is ``predict_from_features`` of the
    two encodings with :meth:`ScaleNet.retry_turned`, as in :meth:`ScaleNet.predict`."""

    def __init__(self, ev: _Evaluator, model, pair: PairInfo):
        self._ev, self._model, self._pair = ev, model, pair

    def predict(self, image_a, image_b, bf16: bool = False):
        ev, pair = self._ev, self._pair
        if image_a is not ev.image(pair.image_a)[0] or image_b is not ev.image(pair.image_b)[0]:
            return self._model.predict(image_a, image_b, bf16=bf16)
        def predict():
            ea, eb = ev.global_encoding(pair.image_a, bf16), ev.global_encoding(pair.image_b, bf16)
            first = self._model.predict_from_features(ea, eb, bf16)
            return self._model.retry_turned(first, image_a, image_b, ea, eb, bf16)

        return ev._once(("global", bf16), predict)

    def __getattr__(self, name):
        return getattr(self._model, name)


def summarise(records: list[dict], pairs: list[PairInfo], methods, thresholds) -> dict:
    """Mean MMA / matches / features per split ('all', perspective splits, scale splits) and method."""
    groups = {"all": [p.name for p in pairs]}
    for p in pairs:
        groups.setdefault(p.perspective_split, []).append(p.name)
        groups.setdefault(p.scale_split, []).append(p.name)
    out = {}
    for g, names in groups.items():
        names = set(names)
        out[g] = {"num_pairs": len(names)}
        for m in methods:
            rs = [r for r in records if r["method"] == m and r["pair"] in names]
            if not rs:
                continue
            out[g][m] = {"mma": [float(np.mean([r["mma"][i] for r in rs])) for i in range(len(thresholds))],
                         "num_matches": float(np.mean([r["num_matches"] for r in rs])),
                         "num_features": float(np.mean([(r["num_features_a"] + r["num_features_b"]) / 2 for r in rs]))}
            ce = [r["corner_error"] for r in rs if "corner_error" in r]
            if ce:
                from ..features.verification import homography_auc
                out[g][m]["h_auc"] = homography_auc(ce, H_AUC_THRESHOLDS)
                out[g][m]["h_solved"] = float(np.mean(np.asarray(ce) < SOLVED_PX))
                out[g][m]["corner_error_median"] = float(np.median(ce))
    return out


SPLIT_ORDER = ("all", "easy", "medium", "hard", "scale<1.4x", "scale1.4-2.8x", "scale>2.8x")


def markdown_table(summary: dict, methods, thresholds, title: str = "") -> str:
    ti = [thresholds.index(t) for t in (1, 3, 5, 10) if t in thresholds]
    head = " | ".join(f"MMA@{thresholds[i]}" for i in ti)
    hh = " | ".join(f"H AUC@{t:g}" for t in H_AUC_THRESHOLDS)
    lines = [f"### {title}" if title else "", "",
             f"| split (pairs) | method | {head} | matches | features | {hh} | solved (<{SOLVED_PX:g} px) |",
             "|---|---|" + "---|" * len(ti) + "---|---|" + "---|" * (len(H_AUC_THRESHOLDS) + 1)]
    for g in [s for s in SPLIT_ORDER if s in summary] + [s for s in summary if s not in SPLIT_ORDER]:
        for m in methods:
            if m not in summary[g]:
                continue
            v = summary[g][m]
            vals = " | ".join(f"{v['mma'][i]:.3f}" for i in ti)
            hv = " | ".join(f"{x:.3f}" for x in v["h_auc"]) + f" | {v['h_solved']:.3f}" if "h_auc" in v \
                else " | ".join("-" for _ in range(len(H_AUC_THRESHOLDS) + 1))
            lines.append(f"| {g} ({summary[g]['num_pairs']}) | {m} | {vals} | {v['num_matches']:.0f} | "
                         f"{v['num_features']:.0f} | {hv} |")
    return "\n".join(lines) + "\n"


def plot_mma(summary: dict, methods, thresholds, out: Path, tag: str = "") -> list[Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    files = []
    for g in summary:
        fig, ax = plt.subplots(figsize=(4.5, 3.5))
        for m in methods:
            if m in summary[g]:
                ax.plot(thresholds, summary[g][m]["mma"], marker="o", ms=3, label=m)
        ax.set_xlabel("threshold [px]")
        ax.set_ylabel("MMA")
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
        ax.set_title(f"{tag} {g} ({summary[g]['num_pairs']} pairs)".strip())
        ax.legend()
        fig.tight_layout()
        safe = re.sub(r"[^A-Za-z0-9_.-]", "_", g.replace("<", "lt").replace(">", "gt"))
        f = out / f"mma_{tag + '_' if tag else ''}{safe}.png"
        from ..outputs import atomic_path

        try:
            with atomic_path(f) as tmp:
                fig.savefig(tmp, dpi=100, format="png")
        finally:
            plt.close(fig)
        files.append(f)
    return files


def evaluate(pairs: list[PairInfo], methods=("none", "gt"), descriptor="sift", num_features: int = 1000,
             local_model=None, global_model=None, gate=None, base_radius: float = 16.0, orientation: str = "upright",
             max_side: Optional[int] = None, thresholds=THRESHOLDS, progress: bool = True,
             detector: str = "hessian") -> dict:
    """Run the protocol on ``pairs``; returns ``{"records": [...], "summary": {...}}``.

    ``detector`` is one of :data:`localscale.features.detector.DETECTORS` (default: the single-scale
    Hessian); patch sizes come from ``base_radius`` and each method's maps whatever the detector."""
    from ..features.pipeline import CorrectionGate
    from tqdm import tqdm
    for m in ("local", "fused", "searched", "refined"):
        if m in methods and local_model is None:
            raise LocalScaleError(f"method '{m}' needs a local model")
    if "global" in methods and global_model is None:
        raise LocalScaleError("method 'global' needs a global model")
    gate = gate if gate is not None else CorrectionGate()
    ev = _Evaluator(descriptor, num_features, local_model, global_model, gate, base_radius, orientation, max_side,
                    detector=detector)
    records, skipped, done = [], [], []
    for p in tqdm(pairs, desc=f"eval {ev.desc.name}", disable=not progress, mininterval=5):
        try:
            records += ev.run_pair(p, methods, list(thresholds))
            done.append(p)
        except LocalScaleError as e:   # e.g. an image that is truncated after its header
            reason = " ".join(str(e).split())
            _warn(f"pair {p.name} skipped: {reason}")
            skipped.append({"pair": p.name, "reason": reason})
    return {"records": records, "summary": summarise(records, done, methods, list(thresholds)),
            "skipped": skipped, "suspicious": ev.suspicious}


def _plain(x):
    """``x`` as strict JSON data: numpy scalars as numbers, NaN/inf (e.g. the log scale of a pair
    without a defined one) as null, unknown objects as strings."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, set)):
        return [_plain(v) for v in x]
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        x = x.item()
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if x is None or isinstance(x, (str, int, bool)):
        return x
    return str(x)


def write_outputs(result: dict, pairs: list[PairInfo], methods, out, thresholds=THRESHOLDS, tag: str = "",
                  extra: Optional[dict] = None) -> dict:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    splits = [{"pair": p.name, "spread_log2": round(p.spread, 4), "log2_global_scale": round(p.log2_scale, 4),
               "covisible": round(p.covisible, 3), "perspective_split": p.perspective_split,
               "scale_split": p.scale_split} for p in pairs]
    from ..outputs import write_text

    buf = io.StringIO(newline="")
    w = csv.DictWriter(buf, fieldnames=list(splits[0]) if splits else ["pair"])
    w.writeheader()
    w.writerows(splits)
    write_text(out / "splits.csv", buf.getvalue())
    doc = {"thresholds": list(thresholds), "methods": list(methods), "splits": splits,
           "split_rules": {"perspective_edges_std_log2": PERSPECTIVE_EDGES, "scale_edges_abs_log2": SCALE_EDGES},
           **(extra or {}), **result}
    name = f"results{'_' + tag if tag else ''}"
    write_text(out / f"{name}.json", json.dumps(_plain(doc), indent=1, allow_nan=False))
    md = markdown_table(result["summary"], methods, list(thresholds), tag)
    write_text(out / f"{name}.md", md)
    plot_mma(result["summary"], methods, list(thresholds), out, tag)
    return doc


def add_arguments(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``localscale eval-hpatches`` (model options shared with the other commands)."""
    from ..cli import add_model_options, positive_float, positive_int

    p.add_argument("root", help="folder of sequences (HPatches layout)")
    p.add_argument("-o", "--output", "--out", dest="out", default="hpatches_eval",
                   help="output folder (results*.json, results*.md, splits.csv, mma_*.png)")
    p.add_argument("--methods", nargs="+", default=["none", "global", "local", "fused", "gt"], choices=METHODS,
                   help="correction methods to compare")
    p.add_argument("--descriptor", nargs="+", default=["hardnet"], help="hardnet | sift | weights path (several ok)")
    p.add_argument("--num-features", type=positive_int, default=1000, help="keypoints per image")
    p.add_argument("--detector", default="hessian", metavar="NAME",
                   help="single-scale keypoint detector: hessian | harris | gftt | dog | sift | orb | akaze "
                        "(results files get a NAME_ prefix unless hessian)")
    add_model_options(p, local=True, global_=True, bf16=False)
    p.add_argument("--include-illumination", action="store_true", help="also evaluate i_* sequences")
    p.add_argument("--exclude-hires", action="store_true", help=f"skip {', '.join(HIGH_RES)}")
    p.add_argument("--exclude", nargs="*", default=[], help="sequence names to skip")
    p.add_argument("--sequences", nargs="*", default=None, help="only these sequences (default: all)")
    p.add_argument("--max-side", type=positive_int, default=None,
                   help="downscale images (and H) to this longer side (default: full size)")
    p.add_argument("--gate-pair", type=float, default=None,
                   help="pair-level gate: correct only if the 90th pct of |log2 S| reaches this "
                        "(default: CorrectionGate's)")
    p.add_argument("--gate-deadzone", type=float, default=None,
                   help="per pixel: |log2 S| below this -> 1 (default: CorrectionGate's)")
    p.add_argument("--no-consistency", action="store_true", help="gate: skip the A<->B median consistency shift")
    p.add_argument("--gate-min-confidence", type=float, default=None,
                   help="per pixel: S -> 1 where the confidence is below this (default: CorrectionGate's)")
    p.add_argument("--gate-weighting", choices=GATE_WEIGHTINGS, default=None,
                   help="gate: weight the maps' medians by the predicted visibility or reliability "
                        "(default: CorrectionGate's)")
    p.add_argument("--orientation", choices=("upright", "gradient"), default="upright", help="patch orientation")
    p.add_argument("--base-radius", type=positive_float, default=16.0, help="patch radius (px) at scale 1")
    return p


def build_parser() -> argparse.ArgumentParser:
    from ..cli import HelpFormatter

    return add_arguments(argparse.ArgumentParser(prog="localscale eval-hpatches", formatter_class=HelpFormatter,
                                                 description="HPatches-style MMA evaluation"))


def load_scale_models(methods: list, local_weights=None, global_weights=None,
                      device: str = "cpu") -> tuple[dict, list]:
    """Load the models the ``methods`` need (:func:`localscale.cli.load_scale_model`); a method whose
    weights cannot be loaded is removed from ``methods`` (in place) with a note.
    Returns ``({"local"|"global": model}, notes)``."""
    from ..cli import load_scale_model, resolve_device
    from ..errors import CheckpointError

    models, notes = {}, []
    needs = {"local": ("local", "fused", "searched", "refined"), "global": ("global", "fused")}
    device = resolve_device(device)
    for m, w in (("local", local_weights), ("global", global_weights)):
        if not any(x in methods for x in needs[m]):
            continue
        try:
            models[m] = load_scale_model(m, w, device)
            if w:
                notes.append(f"{m}: weights {w}")
        except CheckpointError as e:
            if w is not None:   # weights the user named must load
                raise
            removed = [x for x in needs[m] if x in methods]
            for x in removed:
                methods.remove(x)
            notes.append(f"{', '.join(removed)} skipped: {e}")
    return models, notes


def gate_from_args(args):
    """``CorrectionGate`` with the ``--gate-*`` / ``--no-consistency`` options a parser defined."""
    from ..features.pipeline import CorrectionGate

    gate = CorrectionGate()
    if getattr(args, "gate_pair", None) is not None:
        gate.min_pair_log2 = args.gate_pair
    if getattr(args, "gate_deadzone", None) is not None:
        gate.deadzone_log2 = args.gate_deadzone
    if getattr(args, "gate_min_confidence", None) is not None:
        gate.min_confidence = args.gate_min_confidence
    if getattr(args, "gate_weighting", None) is not None:
        gate.weighting = args.gate_weighting
    gate.consistency = not getattr(args, "no_consistency", False)
    return gate


def main(argv=None) -> int:
    """Entry of ``localscale eval-hpatches ROOT [options]``; methods whose default weights are
    missing are skipped with a note."""
    return run(build_parser().parse_args(argv))


def run(args: argparse.Namespace) -> int:
    """Body of ``localscale eval-hpatches`` for parsed :func:`add_arguments` options."""
    from ..cli import check_output_dir
    from ..features.detector import get_detector

    detector = getattr(args, "detector", "hessian")
    get_detector(detector, max(1, args.num_features))
    tags = [Path(d).stem if d not in ("hardnet", "sift") else d for d in args.descriptor]
    tags = tags if detector == "hessian" else [f"{detector}_{t}" for t in tags]
    check_output_dir(args.out, ["splits.csv"] + [f"results_{t}.{e}" for t in tags for e in ("json", "md")]
                     + [f"mma_{t}_scale1.4-2.8x.png" for t in tags])
    seqs = load_hpatches(args.root, args.include_illumination, args.exclude_hires, args.exclude, args.sequences)
    skipped: list = []
    pairs = make_pairs(seqs, skipped)
    if not pairs:
        raise LocalScaleError(f"no pair of {args.root} can be evaluated ({len(skipped)} skipped; first: "
                              f"{skipped[0]['pair']}: {skipped[0]['reason']})" if skipped else
                              f"no pairs in {args.root}")
    methods = list(args.methods)
    models, notes = load_scale_models(methods, args.local_weights, args.global_weights, args.device)
    if not methods:
        raise LocalScaleError(f"none of the methods {list(args.methods)} can run: {'; '.join(notes)}")
    local_model, global_model = models.get("local"), models.get("global")
    gate = gate_from_args(args)
    for n in notes:
        print("note:", n)
    print(f"{len(seqs)} sequences, {len(pairs)} pairs; methods {methods}")
    for d in args.descriptor:
        res = evaluate(pairs, methods, d, args.num_features, local_model, global_model, gate, args.base_radius,
                       args.orientation, args.max_side, detector=detector)
        res["skipped"] = skipped + res["skipped"]
        if res["skipped"]:
            print(f"warning: {len(res['skipped'])} pair(s) skipped (listed under 'skipped' in the results)",
                  file=sys.stderr)
        tag = Path(d).stem if d not in ("hardnet", "sift") else d
        tag = tag if detector == "hessian" else f"{detector}_{tag}"
        write_outputs(res, pairs, methods, args.out, tag=tag,
                      extra={"notes": notes, "gate": vars(gate), "descriptor": d, "detector": detector,
                             "args": {k: v for k, v in vars(args).items() if not callable(v)}})
        print(markdown_table(res["summary"], methods, list(THRESHOLDS), f"{args.root} / {tag}"))
    print(f"wrote {args.out}/")
    return 0
