"""Match two images with scale maps: load, correct, extract, match, verify; and write the result.

:func:`match_pair` is the whole path for one pair: the images at the matcher's working
resolution, the maps of a correction method (:mod:`.correction`), a :class:`~.matcher.Matcher`
(named configurations in :data:`~.config.MATCHERS`), and optionally verification and
refinement by the verified geometry. Everything in the result is in full-image pixels.
:func:`match_refined_pair` matches with given maps and refines them; :func:`run_match` also writes
the result to a folder.

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
from pathlib import Path
from typing import Optional, Union

import cv2
import numpy as np

from ..io import load_image, load_working_image, read_homography
from .auto.loop import try_hypotheses
from .auto.turns import match_turned, nearest_turn
from .config import MatchConfig, match_config
from .correction import Correction, get_correction
from .matcher import Matcher, Matches, get_matcher
from .metrics import reprojection_errors
from .refinement import refine_pair_maps, refine_passes, sift_seed_points
from .result import MatchResult, save_matches
from .verification import verify_matches
from .viz import draw_matches


def match_pair(
    image_a,
    image_b,
    correction: Union[str, Correction] = "none",
    H=None,
    local_model=None,
    global_model=None,
    matcher: Union[str, MatchConfig, Matcher] = "hardnet",
    *,
    camera_a=None,
    camera_b=None,
    **options,
) -> MatchResult:
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
        correction: a name of :data:`~.correction.CORRECTIONS` or a :class:`~.correction.Correction`.
        H: homography A -> B (array, nested list or file); needed for ``"gt"``, gives reprojection errors.
        local_model, global_model: the models the correction needs (default: bundled weights).
        matcher: a name of :data:`~.config.MATCHERS`, a :class:`~.config.MatchConfig` or a
            :class:`~.matcher.Matcher`.
        camera_a, camera_b: the cameras of A and B (:class:`~localscale.geometry.cameras.Camera`, a
            ``pycolmap.Camera``, a COLMAP ``cameras.txt`` line or a camera file; their size is that of
            the full images). With cameras the matches are verified by two-view geometry
            (``verification.model="two_view"`` unless another non-homography model is set) and
            ``res.verification.two_view`` holds the configuration and, with both cameras, the
            relative pose ``R``, ``t`` (``x_B = R x_A + t``; also :attr:`MatchResult.relative_pose`).
        **options: fields of :class:`~.config.MatchConfig` replacing the matcher's
            (``num_features=500``, ``descriptor="sift"``, ``refine=True``, ``max_side=None``, ...).
    """
    method = get_correction(correction)
    method.check_models(local_model, global_model)
    m = get_matcher(matcher, **options)
    cfg = m.config
    a, to_work_a = load_working_image(image_a, cfg.max_side, "image A")
    b, to_work_b = load_working_image(image_b, cfg.max_side, "image B")
    H_full = None if H is None else read_homography(H)
    H = None if H is None else to_work_b @ H_full @ np.linalg.inv(to_work_a)
    cameras = _working_cameras((camera_a, camera_b), (image_a, image_b), (to_work_a, to_work_b))
    vconf = _verification_for(cfg.verification, cameras)
    if method.auto:
        res = match_auto(m, a, b, local_model, global_model, H, method, cameras=cameras, verification=vconf)
        res = _to_full_frame(res, to_work_a, to_work_b, H_full)
        if res.refined_a is not None and not (
            np.array_equal(to_work_a, np.eye(3)) and np.array_equal(to_work_b, np.eye(3))
        ):
            _refine_full_frame(res, image_a, image_b, to_work_a, to_work_b, m.config)
        return res
    sa, sb = method.maps(a, b, H, local_model, global_model, cfg.gate, bf16=cfg.bf16)
    if cfg.refine or method.refine:
        res = match_refined(m, a, b, sa, sb, None, None, H, method)
    else:
        res = match_result(m, match_with_truth(m, a, b, sa, sb, H, method), H, method)
    res.scale_a, res.scale_b = sa, sb
    if any(c is not None for c in cameras):  # the pair's geometry (and pose) with the cameras given
        k = res.matches
        res.verification = verify_matches(
            res.keypoints_a[k[:, 0]], res.keypoints_b[k[:, 1]], a.shape[:2], b.shape[:2], None, vconf, *cameras
        )
    return _to_full_frame(res, to_work_a, to_work_b, H_full)


def _working_cameras(cameras: tuple, images: tuple, to_work: tuple) -> tuple:
    """The cameras of the full images (``None`` stays ``None``) in the pixels of the working images."""
    from ..core.errors import LocalScaleError
    from ..geometry.camera_checks import check_plausible
    from ..geometry.cameras import as_camera
    from ..io import image_shape

    out = []
    for name, cam, image, S in zip("AB", cameras, images, to_work):
        cam = as_camera(cam)
        if cam is not None:
            check_plausible(cam, f"camera of image {name}")
            h, w = image_shape(image, f"image {name}")
            if abs(cam.width / w - cam.height / h) > 0.01 * max(cam.width / w, cam.height / h):
                raise LocalScaleError(
                    f"camera of image {name} is {cam.width}x{cam.height}, the image {w}x{h}: not the same shape"
                )
            cam = cam.scaled(S[0, 0] * w / cam.width, S[1, 1] * h / cam.height)
        out.append(cam)
    return tuple(out)


def _verification_for(vconf, cameras: tuple):
    """The verification of a pair: with cameras, two-view geometry where the homography was set."""
    if any(c is not None for c in cameras) and vconf.model == "homography":
        return dataclasses.replace(vconf, model="two_view")
    return vconf


def match_with_truth(m: Matcher, a, b, scale_a, scale_b, H, correction: Correction, keys=(None, None)) -> Matches:
    """``m.match`` with the maps of ``correction``; the ground-truth corrections (``gt``,
    ``gt_gated``) also turn B by the quarter turn that undoes the true homography's rotation at
    A's centre (:func:`~.auto.nearest_turn`): the ceiling of scale and rotation rectification."""
    turn = 0
    if H is not None and correction.turns_to_truth:
        turn = nearest_turn(np.asarray(H, np.float64), ((a.shape[1] - 1) / 2, (a.shape[0] - 1) / 2), b.shape)
    return match_turned(m, a, b, scale_a, scale_b, turn, keys)


def match_result(m: Matcher, found: Matches, H, correction: Correction) -> MatchResult:
    """The :class:`MatchResult` of ``m.match``'s output (reprojection errors when ``H`` is given)."""
    errors = None if H is None else reprojection_errors(found.keypoints_a, found.keypoints_b, found.matches, H)
    res = MatchResult(
        found.keypoints_a,
        found.keypoints_b,
        found.matches,
        found.distances,
        errors,
        found.radii_a,
        found.radii_b,
        correction.name,
        H,
    )
    res.meta = {
        "matcher": m.name,
        "num_features_a": len(found.keypoints_a),
        "num_features_b": len(found.keypoints_b),
        "factors": [float(f) for f in found.factors],
    }
    conf = m.config.extractor_conf
    if m.extractor.patch_based and "descriptor" in conf:
        desc = conf["descriptor"]
        res.meta["descriptor"] = desc if isinstance(desc, str) else getattr(desc, "name", "custom")
    if m.extractor.patch_based and "detector" in conf:
        res.meta["detector"] = conf["detector"]
    return res


@functools.lru_cache(maxsize=2)
def _seed_matcher(name: str, num_features: Optional[int] = None) -> Matcher:
    """The seed matcher of ``correction="auto"`` (``num_features``: None, its configuration's), built
    once per process."""
    return Matcher(name if num_features is None else match_config(name, num_features=num_features))


def match_auto(
    m: Matcher,
    a,
    b,
    local_model,
    global_model,
    H,
    correction: Correction,
    keys=(None, None),
    cameras: tuple = (None, None),
    verification=None,
) -> MatchResult:
    """``correction="auto"``: the hypothesis loop (:func:`~.auto.loop.try_hypotheses`); with ``refine``, the
    maps are refined by the winner's verified geometry (Local-ScaleNet's maps, or 1, elsewhere)."""
    from ..models import LocalScaleNet, ScaleNet

    local_model = local_model if local_model is not None else LocalScaleNet.from_pretrained()
    global_model = global_model if global_model is not None else ScaleNet.from_pretrained()
    seed = m.config.auto.seed
    out = try_hypotheses(
        m,
        a,
        b,
        local_model,
        global_model,
        keys=keys,
        seed_matcher=None if seed is None else _seed_matcher(seed, m.config.auto.seed_features),
        cameras=cameras,
        verification=verification,
    )
    res = match_result(m, out.matches, H, correction)
    # unverified: the identity's matches, and no geometry to trust
    res.verification = out.verification if out.verified else dataclasses.replace(out.verification, H=None, F=None)
    res.meta["auto"] = out.to_dict()
    res.meta["seconds"] = out.seconds
    res.scale_a, res.scale_b = out.network_maps or (None, None)  # Local-ScaleNet's maps, ungated
    if m.config.refine:
        if out.network_maps is None and res.verification.H is None:
            # no homography to span the images (the identity settled without the networks):
            # Local-ScaleNet's maps hold away from the inliers
            out.network_maps = (
                np.asarray(local_model.predict(a, b).scale, np.float32),
                np.asarray(local_model.predict(b, a).scale, np.float32),
            )
            res.scale_a, res.scale_b = out.network_maps
        prior_a, prior_b = out.network_maps or (None, None)
        res.refined_a, res.refined_b = refine_pair_maps(
            _as_map(prior_a, a.shape[:2]), _as_map(prior_b, b.shape[:2]), res.verification, m.config.verification
        )
        res.meta.update(passes=len(out.trials), inlier_counts=[t.num_inliers for t in out.trials], seed_inliers=None)
    return res


def _refine_full_frame(res: MatchResult, image_a, image_b, to_a: np.ndarray, to_b: np.ndarray, cfg) -> None:
    """Refined maps at the full resolution of A and B from a result matched at a working resolution:
    the verified geometry and Local-ScaleNet's maps (the priors) taken to full-image pixels."""
    from ..io import image_shape

    shape_a, shape_b = image_shape(image_a, "image A"), image_shape(image_b, "image B")
    fa, fb = (float(np.sqrt(S[0, 0] * S[1, 1])) for S in (to_a, to_b))
    v = res.verification

    def back(points, S):
        return (np.asarray(points, np.float64) - S[:2, 2]) / np.diag(S)[:2]

    full = dataclasses.replace(
        v,
        H=None if v.H is None else np.linalg.inv(to_b) @ v.H @ to_a,
        F=None if v.F is None else to_b.T @ v.F @ to_a,
        points_a=back(v.points_a, to_a),
        points_b=back(v.points_b, to_b),
        local_scales=v.local_scales * fa / fb,
        shape_a=shape_a,
        shape_b=shape_b,
    )

    def prior(net, shape, factor):
        if net is None:
            return None
        log = cv2.resize(
            np.log2(np.clip(net, 1e-6, None)).astype(np.float32), (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR
        )
        return np.exp2(log + np.log2(factor)).astype(np.float32)

    # the priors: Local-ScaleNet's maps of the working frame, in full-image pixels
    pa = prior(res.scale_a, shape_a, fa / fb)
    pb = prior(res.scale_b, shape_b, fb / fa)
    res.refined_a, res.refined_b = refine_pair_maps(pa, pb, full, cfg.verification)
    res.verification = full


def match_refined(m: Matcher, a, b, first_a, first_b, prior_a, prior_b, H, correction: Correction) -> MatchResult:
    """Match with ``first_*``, verify, refine the maps (from ``prior_*``, default ``first_*``; 1
    where both are None) and match again (:func:`~.refinement.refine_passes`)."""
    cfg = m.config
    history = []

    def run(map_a, map_b):
        found = m.match(a, b, map_a, map_b)
        history.append((found, map_a, map_b))
        return found.keypoints_a, found.keypoints_b, found.matches, found.distances

    pa = _as_map(first_a if prior_a is None else prior_a, a.shape[:2])
    pb = _as_map(first_b if prior_b is None else prior_b, b.shape[:2])
    n = cfg.extractor_conf.get("num_features", 1000)
    seed = (lambda: sift_seed_points(a, b, max(n, 1000))) if cfg.sift_seed else None
    out = refine_passes(run, a.shape[:2], b.shape[:2], first_a, first_b, pa, pb, cfg.verification, cfg.max_passes, seed)
    found, used_a, used_b = history[out.best_pass]
    res = match_result(m, found, H, correction)
    res.scale_a, res.scale_b = used_a, used_b
    res.verification, res.refined_a, res.refined_b = out.refined_a.verification, out.refined_a, out.refined_b
    res.meta.update(
        passes=out.passes,
        best_pass=out.best_pass,
        inlier_counts=list(out.inlier_counts),
        seed_inliers=None if out.seed is None else int(out.seed.num_inliers),
    )
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


def match_refined_pair(
    image_a,
    image_b,
    scale_a=None,
    scale_b=None,
    prior_a=None,
    prior_b=None,
    H=None,
    matcher: Union[str, MatchConfig, Matcher] = "hardnet",
    **options,
) -> MatchResult:
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
    res = match_refined(m, a, b, scale_a, scale_b, prior_a, prior_b, H, get_correction("refined"))
    res.H = H
    return res


def refine_predictions(image_a, image_b, pred_ab, pred_ba, **options) -> MatchResult:
    """:func:`match_refined_pair` from two scale predictions (A->B and B->A, e.g. of
    ``LocalScaleNet.predict``): the first pass uses their maps gated by :class:`CorrectionGate`,
    the refined maps start from their maps; ``options`` as in :func:`match_refined_pair`."""
    from .correction import CorrectionGate

    first_a, first_b = CorrectionGate().apply_predictions(pred_ab, pred_ba)
    return match_refined_pair(image_a, image_b, first_a, first_b, pred_ab.scale, pred_ba.scale, **options)


#: what :func:`default_refine_matcher` picks when its weight files are installed
REFINE_MATCHER = "aliked-lightglue"


def default_refine_matcher(weights=None) -> str:
    """The matcher ``predict --refine`` uses unless told: ``aliked-lightglue`` (geometry verified by
    ``auto``) when its weight files are found (``weights``: a folder; ``None``: the installed weight
    packages), else ``hardnet`` (the bundled patch matcher)."""
    from ..core.errors import CheckpointError
    from ..features.pretrained import find_weights
    from .config import match_config

    conf = match_config(REFINE_MATCHER)
    cls = conf.extractor_class
    try:
        for f in (*cls.weight_files(conf.extractor_conf), cls.lightglue_weights):
            find_weights(f, weights)
    except CheckpointError:
        return "hardnet"
    return REFINE_MATCHER


def refine_by_auto(
    image_a, image_b, matcher: str = "aliked-lightglue", local_model=None, global_model=None, **options
) -> MatchResult:
    """The maps refined by the geometry ``auto`` verifies with ``matcher`` (what ``localscale predict
    --refine --matcher M`` writes): :func:`match_pair` with ``correction="auto"`` and ``refine``, the
    matches verified as COLMAP's two-view geometry chooses (the homography's map where a plane
    explains them, the dense map of the verified matches of a 3D scene); ``options`` as in
    :func:`match_pair` (e.g. ``weights``)."""
    from .config import match_config

    verification = dataclasses.replace(match_config(matcher).verification, model="two_view")
    options = {"verification": verification} | options
    return match_pair(image_a, image_b, "auto", None, local_model, global_model, matcher, refine=True, **options)


def refine_match(*args, **kwargs) -> MatchResult:
    """Deprecated name of :func:`match_refined_pair`; goes in the next release."""
    import warnings

    warnings.warn(
        "refine_match is deprecated and goes in the next release: use match_refined_pair", DeprecationWarning, 2
    )
    return match_refined_pair(*args, **kwargs)


def run_match(
    image_a,
    image_b,
    out,
    correction: Union[str, Correction] = "local",
    H=None,
    local_model=None,
    global_model=None,
    matcher: Union[str, MatchConfig, Matcher] = "hardnet",
    verbose: bool = True,
    *,
    camera_a=None,
    camera_b=None,
    **options,
) -> MatchResult:
    """:func:`match_pair`, then write ``out/matches.npz`` and ``out/matches.png``; returns the result.

    With refinement (``refine=True`` or ``correction="refined"``): also ``out/refined_scale.npy`` /
    ``refined_source.npy`` / ``refined_scale.png`` for A, the same with ``_b`` for B, and
    ``out/geometry.json``. The models ``correction`` needs are ``local_model`` / ``global_model``
    (None: the bundled weights).
    """
    res = match_pair(
        image_a,
        image_b,
        correction,
        H,
        local_model,
        global_model,
        matcher,
        camera_a=camera_a,
        camera_b=camera_b,
        **options,
    )
    out = Path(out)
    _write_match_files(res, image_a, image_b, out)
    if verbose:
        _print_match_summary(res, out)
    return res


def _write_match_files(res: MatchResult, image_a, image_b, out: Path) -> None:
    """The files of ``run_match`` (:func:`_write_match_set`), all or none: when one cannot be
    written (a full disk) or the run is stopped, those this call wrote already are removed."""
    before = _stamps(out)
    try:
        _write_match_set(res, image_a, image_b, out)
    except BaseException:
        for name, stamp in _stamps(out).items():
            if before.get(name) != stamp:
                (out / name).unlink(missing_ok=True)
        raise


def _stamps(out: Path) -> dict:
    """``{name: modification time}`` of the files in ``out``."""
    return {p.name: p.stat().st_mtime_ns for p in out.iterdir() if p.is_file()} if out.is_dir() else {}


def _write_match_set(res: MatchResult, image_a, image_b, out: Path) -> None:
    """Matches and their picture; the refined maps, or the verified geometry."""
    from ..maps.files import write_refinement

    save_matches(res, out / "matches.npz")
    draw_matches(image_a, image_b, res, out / "matches.png")
    inputs = [x for x in (image_a, image_b) if isinstance(x, (str, Path))]
    if res.refined_a is not None:
        extra = {k: res.meta[k] for k in ("passes", "inlier_counts", "seed_inliers")}
        if "auto" in res.meta:
            extra["auto"] = res.meta["auto"]
        write_refinement(out, "", res.refined_a, res.refined_b, extra, inputs)
    elif res.verification is not None:  # auto, or cameras given: the verified geometry (and pose)
        import json

        from ..core.outputs import ensure_not_input, write_text

        geo = ensure_not_input(out / "geometry.json", inputs)
        extra = {"auto": res.meta["auto"]} if "auto" in res.meta else {}
        write_text(geo, json.dumps(res.verification.to_dict() | extra, indent=1) + "\n")


def _print_match_summary(res: MatchResult, out: Path) -> None:
    """The lines of ``run_match``: matches and accuracy, ``auto``'s trials, refinement, two-view geometry."""
    msg = (
        f"{res.meta['matcher']}: {len(res.matches)} matches "
        f"({res.meta['num_features_a']}/{res.meta['num_features_b']} features)"
    )
    if res.errors is not None:
        msg += f", accuracy@5px {res.accuracy(5.0):.3f}"
    print(f"{msg}; wrote {out / 'matches.npz'} and {out / 'matches.png'}")
    if "auto" in res.meta:
        _print_auto(res.meta["auto"], out)
    if res.refined_a is not None:
        v = res.verification
        state = "verified" if v.verified else f"not verified ({'; '.join(v.reasons)}), network maps kept"
        print(
            f"refine: {v.model} with {v.num_inliers} inliers after {res.meta['passes']} pass(es) "
            f"{res.meta['inlier_counts']}, {state}; wrote {out / 'refined_scale.npy'}, {out / 'geometry.json'}"
        )
    _print_two_view(res, out)


def _print_auto(auto: dict, out: Path) -> None:
    """The ``auto`` line of ``run_match`` (every trial), with a warning when no hypothesis was verified."""
    tried = "; ".join(
        f"{t['source']} x{t['scale']:.3g} turn {90 * t['turn']}: {t['num_inliers']} inliers"
        f"{'' if t['verified'] else ' (not verified)'}"
        for t in auto["trials"]
    )
    print(f"auto: chose {auto['chosen']} after {len(auto['trials'])} run(s) [{tried}]; wrote {out / 'geometry.json'}")
    if not auto["verified"]:
        print(
            "warning: no hypothesis verified; the matches of the identity are returned unverified",
            file=sys.stderr,
        )


def _print_two_view(res: MatchResult, out: Path) -> None:
    """The two-view geometry line of ``run_match`` (cameras given), with a warning when it is not to be trusted."""
    g = getattr(res.verification, "two_view", None)
    if g is None:
        return
    pose = ""
    if res.relative_pose is not None:
        import math

        R, t = res.relative_pose
        angle = math.degrees(math.acos(max(-1.0, min(1.0, (float(np.trace(R)) - 1) / 2))))
        pose = f", pose: rotation {angle:.2f} deg, t {np.round(t, 3).tolist()} (from {g.pose_source})"
    print(
        f"two-view geometry: {g.configuration} ({g.model}, {g.num_inliers} inliers){pose}; "
        f"wrote {out / 'geometry.json'}"
    )
    if not (res.verification.verified and g.reliable):
        why = list(res.verification.reasons) + list(g.reasons)
        print(f"warning: the two-view geometry is not reliable: {'; '.join(why) or 'not verified'}", file=sys.stderr)
