"""Match two images with scale maps: load, correct, extract, match, verify; draw and save the result.

:func:`match_pair` is the whole path for one pair: the images at the matcher's working
resolution, the maps of a ``correction`` method (:mod:`.correction`), a :class:`~.matchers.Matcher`
(named configurations in :data:`~.matchers.MATCHERS`), and optionally verification and
refinement by the verified geometry. Everything in the result is in full-image pixels.

Example::

    res = match_pair("a.png", "b.png", "local")                          # HardNet, scale-corrected patches
    res = match_pair("a.png", "b.png", "global", matcher="aliked-lightglue")  # B or A shrunk by ScaleNet
    res = match_pair("a.png", "b.png", "gt", H=H, descriptor="sift")     # options replace MatchConfig fields
    res = match_pair("a.png", "b.png", "local", refine=True)             # verify, refine, match again
    res.accuracy(5.0), len(res.matches), res.verification.verified, res.refined_a.scale
    draw_matches("a.png", "b.png", res, "matches.png"); save_matches(res, "matches.npz")
"""
from __future__ import annotations

import dataclasses
import functools
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Union

import cv2
import numpy as np

from ..errors import LocalScaleError
from ..io import load_image, load_working_image, read_homography
from .correction import (CORRECTIONS, NO_GATE, CorrectionGate, fuse_local_global, get_correction,  # noqa: F401
                         models_for_correction, scale_maps_for_pair)
from .matchers import MATCHERS, Features, MatchConfig, Matcher, Matches, extract, match_config  # noqa: F401
from .matching import match_descriptors, matching_accuracy, reprojection_errors
from .verification import refine_matching, sift_seed_points

#: default working resolution of the ``hardnet`` matcher and of pictures (longer side, pixels)
MAX_SIDE = 2048
#: file types :func:`draw_matches` writes
PICTURE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")


@dataclass
class MatchResult:
    """Matches between two images.

    Attributes:
        keypoints_a, keypoints_b: ``N_A x 2``, ``N_B x 2`` float32, full-image pixels.
        matches: ``K x 2`` int64 indices (A, B); distances: ``K`` match costs (lower is better).
        errors: ``K`` reprojection errors ``|H x_A - x_B|`` (pixels of B) when ``H`` was given, else ``None``.
        radii_a, radii_b: patch radii of all keypoints (``patches`` extractor; else ``None``).
        correction: the method used; H: the true homography when given.
        scale_a, scale_b: the (gated) maps / floats used, in the working frame, for inspection
            (``auto``: Local-ScaleNet's ungated maps, the hypotheses come from).
        meta: matcher name, feature counts, working scales, resize factors, passes.
        verification: :class:`~.verification.VerificationResult` of the matches (``refine=True``).
        refined_a, refined_b: :class:`~.verification.RefinedScale` of A and B (``refine=True``).
    """

    keypoints_a: np.ndarray
    keypoints_b: np.ndarray
    matches: np.ndarray
    distances: np.ndarray
    errors: Optional[np.ndarray]
    radii_a: Optional[np.ndarray]
    radii_b: Optional[np.ndarray]
    correction: str
    H: Optional[np.ndarray] = None
    scale_a: object = None
    scale_b: object = None
    meta: dict = field(default_factory=dict)
    verification: object = None
    refined_a: object = None
    refined_b: object = None

    def inliers(self, threshold: float = 5.0) -> np.ndarray:
        if self.errors is None:
            raise LocalScaleError("no homography was given, inliers are unknown")
        return self.errors < threshold

    def accuracy(self, threshold: float = 5.0) -> float:
        if self.errors is None:
            raise LocalScaleError("no homography was given, accuracy is unknown")
        return float(matching_accuracy(self.errors, [threshold])[0])


def match_features(fa: Features, fb: Features, H=None, ratio: Optional[float] = None,
                   correction: str = "none") -> MatchResult:
    """Mutual nearest neighbours (with Lowe's ``ratio`` if given) of two feature sets."""
    d, idx = match_descriptors(fa.descriptors, fb.descriptors, ratio)
    m = idx.numpy().astype(np.int64)
    errors = None
    if H is not None:
        H = read_homography(H)
        errors = reprojection_errors(fa.keypoints, fb.keypoints, m, H)
    return MatchResult(fa.keypoints, fb.keypoints, m, d.numpy(), errors, fa.radii, fb.radii, correction, H)


def get_matcher(matcher: Union[str, MatchConfig, Matcher, None] = "hardnet", **options) -> Matcher:
    """A :class:`Matcher` from a name of :data:`MATCHERS`, a :class:`MatchConfig` (``options``
    replace its fields) or a :class:`Matcher` (returned as it is; no options then)."""
    if isinstance(matcher, Matcher):
        if options:
            raise LocalScaleError(f"match options ({', '.join(sorted(options))}) cannot change a built Matcher; "
                                  "give a name or a MatchConfig instead")
        return matcher
    return Matcher(match_config(matcher, **options))


def _check_models(correction: str, local_model, global_model) -> None:
    from ..models import LocalScaleNet, ScaleNet

    needs = get_correction(correction).models
    if "local" in needs and local_model is not None and not isinstance(local_model, LocalScaleNet):
        raise LocalScaleError(f"correction {correction!r}: local_model must be a LocalScaleNet, "
                              f"got {type(local_model).__name__}")
    if "global" in needs and global_model is not None and not isinstance(global_model, ScaleNet):
        raise LocalScaleError(f"correction {correction!r}: global_model must be a ScaleNet, "
                              f"got {type(global_model).__name__}")


def match_pair(image_a, image_b, correction: str = "none", H=None, local_model=None, global_model=None,
               matcher: Union[str, MatchConfig, Matcher] = "hardnet", **options) -> MatchResult:
    """Correct, extract and match two images (optionally verify, refine and match again).

    Images larger than the matcher's ``max_side`` (longer side) are matched at that working
    resolution (a large JPEG is decoded at a reduced size); keypoints, radii and errors are
    returned in pixels of the full images, the maps (``scale_a``, ``refined_a``, ...) stay in the
    working frame (``meta["working_scale"]``: working pixels per full-image pixel of A and B).

    With ``refine`` (or ``correction="refined"``): the matches are verified
    (:func:`~.verification.verify_matches`), both maps are refined by the verified geometry, the
    pair is matched again with the refined maps, up to ``max_passes`` passes while the inlier
    count grows; the pass with the most inliers is returned, with ``verification``,
    ``refined_a`` and ``refined_b`` set. With ``sift_seed``, a first pass that is not verified is
    followed by the verification of OpenCV SIFT matches, whose geometry, if verified, refines the maps.

    Args:
        image_a, image_b: paths or ``H x W x 3`` uint8 arrays.
        correction: a name of :data:`~.correction.CORRECTIONS` (:mod:`.correction`).
        H: homography A -> B (array, nested list or file); needed for ``"gt"``, gives reprojection errors.
        local_model, global_model: the models the correction needs (default: bundled weights).
        matcher: a name of :data:`~.matchers.MATCHERS`, a :class:`~.matchers.MatchConfig` or a
            :class:`~.matchers.Matcher`.
        **options: fields of :class:`~.matchers.MatchConfig` replacing the matcher's
            (``num_features=500``, ``descriptor="sift"``, ``refine=True``, ``max_side=None``, ...).
    """
    method = get_correction(correction)
    _check_models(correction, local_model, global_model)
    m = get_matcher(matcher, **options)
    cfg = m.config
    a, to_work_a = load_working_image(image_a, cfg.max_side, "image A")
    b, to_work_b = load_working_image(image_b, cfg.max_side, "image B")
    H_full = None if H is None else read_homography(H)
    H = None if H is None else to_work_b @ H_full @ np.linalg.inv(to_work_a)
    if method.auto:
        res = _auto(m, a, b, local_model, global_model, H, correction)
        res = _to_full_frame(res, to_work_a, to_work_b, H_full)
        if res.refined_a is not None and not (np.array_equal(to_work_a, np.eye(3)) and np.array_equal(to_work_b, np.eye(3))):
            _refine_full_frame(res, image_a, image_b, to_work_a, to_work_b, m.config)
        return res
    sa, sb = scale_maps_for_pair(a, b, correction, H, local_model, global_model, cfg.gate, bf16=cfg.bf16)
    if cfg.refine or method.refine:
        res = _refined(m, a, b, sa, sb, None, None, H, correction)
    else:
        res = _result(m, match_with_truth(m, a, b, sa, sb, H, correction), H, correction)
    res.scale_a, res.scale_b = sa, sb
    return _to_full_frame(res, to_work_a, to_work_b, H_full)


def match_with_truth(m: Matcher, a, b, scale_a, scale_b, H, correction: str, keys=(None, None)) -> Matches:
    """``m.match`` with the maps of ``correction``; the ground-truth corrections (``gt``,
    ``gt_gated``) also turn B by the quarter turn that undoes the true homography's rotation at
    A's centre (:func:`~.auto.nearest_turn`): the ceiling of scale and rotation rectification."""
    from .auto import match_turned, nearest_turn

    turn = 0
    if H is not None and correction in ("gt", "gt_gated"):
        turn = nearest_turn(np.asarray(H, np.float64), ((a.shape[1] - 1) / 2, (a.shape[0] - 1) / 2), b.shape)
    return match_turned(m, a, b, scale_a, scale_b, turn, keys)


def _result(m: Matcher, found: Matches, H, correction: str) -> MatchResult:
    errors = None if H is None else reprojection_errors(found.keypoints_a, found.keypoints_b, found.matches, H)
    res = MatchResult(found.keypoints_a, found.keypoints_b, found.matches, found.distances, errors,
                      found.radii_a, found.radii_b, correction, H)
    res.meta = {"matcher": m.name, "num_features_a": len(found.keypoints_a),
                "num_features_b": len(found.keypoints_b), "factors": [float(f) for f in found.factors]}
    if m.config.extractor == "patches":
        desc = m.config.descriptor
        res.meta.update(descriptor=desc if isinstance(desc, str) else getattr(desc, "name", "custom"),
                        detector=m.config.detector)
    return res


@functools.lru_cache(maxsize=2)
def _seed_matcher(name: str) -> Matcher:
    """The seed matcher of ``correction="auto"``, built once per process."""
    return Matcher(name)


def _auto(m: Matcher, a, b, local_model, global_model, H, correction: str, keys=(None, None)) -> MatchResult:
    """``correction="auto"``: the hypothesis loop (:func:`~.auto.auto_match`); with ``refine``, the
    maps are refined by the winner's verified geometry (Local-ScaleNet's maps, or 1, elsewhere)."""
    from ..models import LocalScaleNet, ScaleNet
    from .auto import auto_match
    from .verification import refine_pair_maps

    local_model = local_model if local_model is not None else LocalScaleNet.from_pretrained()
    global_model = global_model if global_model is not None else ScaleNet.from_pretrained()
    seed = m.config.auto.seed
    out = auto_match(m, a, b, local_model, global_model, keys=keys,
                     seed_matcher=None if seed is None else _seed_matcher(seed))
    res = _result(m, out.matches, H, correction)
    # unverified: the identity's matches, and no geometry to trust
    res.verification = out.verification if out.verified else dataclasses.replace(out.verification, H=None, F=None)
    res.meta["auto"] = out.to_dict()
    res.meta["seconds"] = out.seconds
    res.scale_a, res.scale_b = out.network_maps or (None, None)     # Local-ScaleNet's maps, ungated
    if m.config.refine:
        if out.network_maps is None and res.verification.H is None:
            # no homography to span the images (the identity settled without the networks):
            # Local-ScaleNet's maps hold away from the inliers
            out.network_maps = (np.asarray(local_model.predict(a, b).scale, np.float32),
                                np.asarray(local_model.predict(b, a).scale, np.float32))
            res.scale_a, res.scale_b = out.network_maps
        prior_a, prior_b = out.network_maps or (None, None)
        res.refined_a, res.refined_b = refine_pair_maps(_as_map(prior_a, a.shape[:2]), _as_map(prior_b, b.shape[:2]),
                                                        res.verification, m.config.verification)
        res.meta.update(passes=len(out.trials), inlier_counts=[t.num_inliers for t in out.trials], seed_inliers=None)
    return res


def _refine_full_frame(res: MatchResult, image_a, image_b, to_a: np.ndarray, to_b: np.ndarray, cfg) -> None:
    """Refined maps at the full resolution of A and B from a result matched at a working resolution:
    the verified geometry and Local-ScaleNet's maps (the priors) taken to full-image pixels."""
    from ..io import image_shape
    from .verification import refine_pair_maps

    shape_a, shape_b = image_shape(image_a, "image A"), image_shape(image_b, "image B")
    fa, fb = (float(np.sqrt(S[0, 0] * S[1, 1])) for S in (to_a, to_b))
    v = res.verification

    def back(points, S):
        return (np.asarray(points, np.float64) - S[:2, 2]) / np.diag(S)[:2]

    full = dataclasses.replace(
        v, H=None if v.H is None else np.linalg.inv(to_b) @ v.H @ to_a,
        F=None if v.F is None else to_b.T @ v.F @ to_a, points_a=back(v.points_a, to_a),
        points_b=back(v.points_b, to_b), local_scales=v.local_scales * fa / fb, shape_a=shape_a, shape_b=shape_b)

    def prior(net, shape, factor):
        if net is None:
            return None
        log = cv2.resize(np.log2(np.clip(net, 1e-6, None)).astype(np.float32), (shape[1], shape[0]),
                         interpolation=cv2.INTER_LINEAR)
        return np.exp2(log + np.log2(factor)).astype(np.float32)

    # the priors: Local-ScaleNet's maps of the working frame, in full-image pixels
    pa = prior(res.scale_a, shape_a, fa / fb)
    pb = prior(res.scale_b, shape_b, fb / fa)
    res.refined_a, res.refined_b = refine_pair_maps(pa, pb, full, cfg.verification)
    res.verification = full


def _refined(m: Matcher, a, b, first_a, first_b, prior_a, prior_b, H, correction: str) -> MatchResult:
    """Match with ``first_*``, verify, refine the maps (from ``prior_*``, default ``first_*``; 1
    where both are None) and match again (:func:`~.verification.refine_matching`)."""
    cfg = m.config
    history = []

    def run(map_a, map_b):
        found = m.match(a, b, map_a, map_b)
        history.append((found, map_a, map_b))
        return found.keypoints_a, found.keypoints_b, found.matches, found.distances

    pa = _as_map(first_a if prior_a is None else prior_a, a.shape[:2])
    pb = _as_map(first_b if prior_b is None else prior_b, b.shape[:2])
    seed = (lambda: sift_seed_points(a, b, max(cfg.num_features, 1000))) if cfg.sift_seed else None
    out = refine_matching(run, a.shape[:2], b.shape[:2], first_a, first_b, pa, pb, cfg.verification,
                          cfg.max_passes, seed)
    found, used_a, used_b = history[out.best_pass]
    res = _result(m, found, H, correction)
    res.scale_a, res.scale_b = used_a, used_b
    res.verification, res.refined_a, res.refined_b = out.refined_a.verification, out.refined_a, out.refined_b
    res.meta.update(passes=out.passes, best_pass=out.best_pass, inlier_counts=list(out.inlier_counts),
                    seed_inliers=None if out.seed is None else int(out.seed.num_inliers))
    return res


def _to_full_frame(res: MatchResult, to_work_a: np.ndarray, to_work_b: np.ndarray, H_full) -> MatchResult:
    """Keypoints, radii and errors of a result computed at a working resolution, in full-image pixels."""
    res.H = H_full
    if np.array_equal(to_work_a, np.eye(3)) and np.array_equal(to_work_b, np.eye(3)):
        return res

    def back(points, S):
        return ((points - S[:2, 2]) / np.diag(S)[:2]).astype(np.float32)

    fa, fb = (float(np.sqrt(S[0, 0] * S[1, 1])) for S in (to_work_a, to_work_b))
    res.keypoints_a, res.keypoints_b = back(res.keypoints_a, to_work_a), back(res.keypoints_b, to_work_b)
    if res.radii_a is not None:
        res.radii_a, res.radii_b = res.radii_a / fa, res.radii_b / fb
    if H_full is not None:
        res.errors = reprojection_errors(res.keypoints_a, res.keypoints_b, res.matches, H_full)
    res.meta["working_scale"] = [fa, fb]
    return res


def _as_map(scale, shape):
    """A map or float as an ``H x W`` float32 map (``None`` = 1)."""
    if scale is None:
        return np.ones(shape, np.float32)
    if np.isscalar(scale):
        return np.full(shape, float(scale), np.float32)
    return np.asarray(scale, np.float32)


def refine_match(image_a, image_b, scale_a=None, scale_b=None, prior_a=None, prior_b=None, H=None,
                 matcher: Union[str, MatchConfig, Matcher] = "hardnet", **options) -> MatchResult:
    """Match with given maps, verify, refine the maps and match again (full resolution).

    Args:
        image_a, image_b: paths or ``H x W x 3`` uint8 arrays.
        scale_a, scale_b: maps (or floats, or ``None``) of the first pass (e.g. the gated network maps).
        prior_a, prior_b: network maps the refined maps start from (default: ``scale_*``; ``None`` = 1).
        H: ground-truth homography A -> B for reprojection errors (optional).
        matcher, options: as in :func:`match_pair`.
    Returns:
        :class:`MatchResult` of the pass with the most inliers; ``scale_a`` / ``scale_b`` are the maps
        that pass used, ``refined_a`` / ``refined_b`` the refined maps, ``verification`` the geometry
        they came from (the seed's when it was used; the best pass's when nothing was verified).
    """
    a = load_image(image_a, "image A")
    b = load_image(image_b, "image B")
    m = get_matcher(matcher, **options)
    H = None if H is None else read_homography(H)
    res = _refined(m, a, b, scale_a, scale_b, prior_a, prior_b, H, "refined")
    res.H = H
    return res


def draw_matches(image_a, image_b, result: MatchResult, path: Union[str, Path, None] = None,
                 threshold: float = 5.0, max_lines: int = 500, max_side: Optional[int] = MAX_SIDE) -> np.ndarray:
    """Side-by-side picture; with ``H`` inliers (error < ``threshold``) green, outliers red,
    else all matches yellow. Images larger than ``max_side`` are drawn at that size. Returns the
    RGB canvas and writes it to ``path`` (``.png``, ``.jpg``, ``.tif``, ``.bmp``, ``.webp``) if given.

    Raises :class:`LocalScaleError` when ``path`` is a folder or has another extension, and when
    the result's keypoints do not fit these images (a result of another pair)."""
    if path is not None:
        path = Path(path)
        if path.is_dir():
            raise LocalScaleError(f"cannot write picture {path}: an existing folder has that name (give a file name)")
        if path.suffix.lower() not in PICTURE_SUFFIXES:
            raise LocalScaleError(f"picture {path}: the name must end in one of {', '.join(PICTURE_SUFFIXES)}")
    a, to_a = load_working_image(image_a, max_side, "image A")
    b, to_b = load_working_image(image_b, max_side, "image B")
    for name, kp, S, img in (("A", result.keypoints_a, to_a, a), ("B", result.keypoints_b, to_b, b)):
        full_w, full_h = (img.shape[1] + 1) / S[0, 0] - 1, (img.shape[0] + 1) / S[1, 1] - 1
        kp = np.asarray(kp, np.float64).reshape(-1, 2)
        if len(kp) and (kp.min() < -2 or kp[:, 0].max() > full_w + 2 or kp[:, 1].max() > full_h + 2):
            raise LocalScaleError(f"the result's keypoints of {name} lie outside image {name} "
                                  f"({full_w + 1:.0f} x {full_h + 1:.0f} px): it belongs to other images")
    h = max(a.shape[0], b.shape[0])
    canvas = np.zeros((h, a.shape[1] + b.shape[1], 3), np.uint8)
    canvas[:a.shape[0], :a.shape[1]] = a
    canvas[:b.shape[0], a.shape[1]:] = b
    canvas = (canvas.astype(np.float32) * 0.7).astype(np.uint8)
    m = result.matches
    if len(m) > max_lines:
        m = m[np.random.default_rng(0).choice(len(m), max_lines, replace=False)]
    ok = None
    if result.errors is not None:
        err = reprojection_errors(result.keypoints_a, result.keypoints_b, m, result.H) if result.H is not None \
            else result.errors[:len(m)]
        ok = err < threshold
    lw = max(1, round(max(canvas.shape) / 800))
    kpa = result.keypoints_a * np.diag(to_a)[:2] + to_a[:2, 2]
    kpb = result.keypoints_b * np.diag(to_b)[:2] + to_b[:2, 2]
    for i, (ia, ib) in enumerate(m):
        pa = tuple(int(round(v)) for v in kpa[ia])
        pb = kpb[ib]
        pb = (int(round(pb[0])) + a.shape[1], int(round(pb[1])))
        colour = (255, 220, 0) if ok is None else ((0, 220, 0) if ok[i] else (230, 0, 0))
        cv2.line(canvas, pa, pb, colour, lw, cv2.LINE_AA)
        cv2.circle(canvas, pa, 2 * lw, colour, -1)
        cv2.circle(canvas, pb, 2 * lw, colour, -1)
    label = " / ".join(str(x) for x in (result.meta.get("matcher"), result.correction) if x)
    if "auto" in result.meta:
        auto = result.meta["auto"]
        label += f" ({auto['chosen']}{'' if auto['verified'] else ', not verified'})"
    cv2.putText(canvas, f"{label}: {len(result.matches)} matches", (8, 8 + 14 * lw), cv2.FONT_HERSHEY_SIMPLEX,
                0.5 * lw, (255, 255, 255), lw, cv2.LINE_AA)
    if path is not None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise LocalScaleError(f"cannot create folder {path.parent}: {e.strerror or e}") from None
        from ..outputs import write_image

        write_image(path, canvas[..., ::-1])
    return canvas


def save_matches(result: MatchResult, path: Union[str, Path]) -> None:
    """Write the result to ``.npz`` (keypoints_a/b, matches, distances, radii_a/b, correction,
    and errors / H when known)."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise LocalScaleError(f"cannot create folder {path.parent}: {e.strerror or e}") from None
    data = dict(keypoints_a=result.keypoints_a, keypoints_b=result.keypoints_b, matches=result.matches,
                distances=result.distances, correction=np.array(result.correction),
                matcher=np.array(str(result.meta.get("matcher", ""))))
    if result.radii_a is not None:
        data.update(radii_a=result.radii_a, radii_b=result.radii_b)
    if result.errors is not None:
        data["errors"] = result.errors
    if result.H is not None:
        data["H"] = result.H
    from ..outputs import atomic_path

    with atomic_path(path) as tmp:   # complete file or none
        with open(tmp, "wb") as f:
            np.savez(f, **data)


def run_match(image_a, image_b, out, correction: str = "local", H=None, local_model=None, global_model=None,
              matcher: Union[str, MatchConfig, Matcher] = "hardnet", verbose: bool = True, **options) -> MatchResult:
    """:func:`match_pair`, then write ``out/matches.npz`` and ``out/matches.png``; returns the result.

    With refinement (``refine=True`` or ``correction="refined"``): also ``out/refined_scale.npy`` /
    ``refined_source.npy`` / ``refined_scale.png`` for A, the same with ``_b`` for B, and
    ``out/geometry.json``. The models ``correction`` needs are ``local_model`` / ``global_model``
    (None: the bundled weights).
    """
    from ..map_files import write_refinement

    res = match_pair(image_a, image_b, correction, H, local_model, global_model, matcher, **options)
    out = Path(out)
    save_matches(res, out / "matches.npz")
    draw_matches(image_a, image_b, res, out / "matches.png")
    inputs = [x for x in (image_a, image_b) if isinstance(x, (str, Path))]
    if res.refined_a is not None:
        extra = {k: res.meta[k] for k in ("passes", "inlier_counts", "seed_inliers")}
        if "auto" in res.meta:
            extra["auto"] = res.meta["auto"]
        write_refinement(out, "", res.refined_a, res.refined_b, extra, inputs)
    elif "auto" in res.meta:
        import json

        from ..outputs import ensure_not_input, write_text

        geo = ensure_not_input(out / "geometry.json", inputs)
        write_text(geo, json.dumps(res.verification.to_dict() | {"auto": res.meta["auto"]}, indent=1) + "\n")
    if verbose:
        msg = (f"{res.meta['matcher']}: {len(res.matches)} matches "
               f"({res.meta['num_features_a']}/{res.meta['num_features_b']} features)")
        if res.errors is not None:
            msg += f", accuracy@5px {res.accuracy(5.0):.3f}"
        print(f"{msg}; wrote {out / 'matches.npz'} and {out / 'matches.png'}")
        if "auto" in res.meta:
            auto = res.meta["auto"]
            tried = "; ".join(f"{t['source']} x{t['scale']:.3g} turn {90 * t['turn']}: {t['num_inliers']} inliers"
                              f"{'' if t['verified'] else ' (not verified)'}" for t in auto["trials"])
            print(f"auto: chose {auto['chosen']} after {len(auto['trials'])} run(s) [{tried}]; wrote {out / 'geometry.json'}")
            if not auto["verified"]:
                print("warning: no hypothesis verified; the matches of the identity are returned unverified",
                      file=sys.stderr)
        if res.refined_a is not None:
            v = res.verification
            state = "verified" if v.verified else f"not verified ({'; '.join(v.reasons)}), network maps kept"
            print(f"refine: {v.model} with {v.num_inliers} inliers after {res.meta['passes']} pass(es) "
                  f"{res.meta['inlier_counts']}, {state}; wrote {out / 'refined_scale.npy'}, {out / 'geometry.json'}")
    return res
