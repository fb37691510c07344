"""Detect -> scale-corrected patches -> describe -> match, for one image or a pair.

The scale map each image gets for a ``correction`` method (``none``, ``global``, ``local``,
``fused``, ``gt``) comes from :mod:`.correction` (:func:`scale_maps_for_pair`).

Example::

    res = match_pair("a.png", "b.png", correction="gt", H=H, descriptor="sift")
    res.accuracy(5.0), len(res.matches)
    res = match_pair("a.png", "b.png", correction="local", refine=True)   # verify, refine, match again
    res.verification.verified, res.refined_a.scale
    draw_matches("a.png", "b.png", res, "matches.png"); save_matches(res, "matches.npz")
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Union

import cv2
import numpy as np
import torch

from ..errors import LocalScaleError
from ..io import load_image, load_working_image, read_homography
from .correction import (CORRECTIONS, NO_GATE, CorrectionGate, _global_scale, fuse_local_global,  # noqa: F401
                         scale_maps_for_pair)
from .descriptors import PatchDescriptor, get_descriptor
from .detector import HessianDetector, get_detector, image_to_gray_tensor
from .matching import match_descriptors, matching_accuracy, reprojection_errors
from .patches import ScaleCorrectedPatches
from .verification import VerificationConfig, refine_matching, sift_seed_points

#: default working resolution of :func:`match_pair` (longer side, pixels)
MAX_SIDE = 2048


@dataclass
class Features:
    """Local features of one image.

    Attributes:
        keypoints: ``N x 2`` float32 ``(x, y)``; responses: ``N``.
        lafs: ``1 x N x 2 x 3`` (kornia LAFs, radius = scale).
        descriptors: ``N x D`` float32, L2-normalised.
        radii: ``N`` float32 patch radii after scale correction.
        image_shape: ``(H, W)``.
    """

    keypoints: np.ndarray
    responses: np.ndarray
    lafs: torch.Tensor
    descriptors: torch.Tensor
    radii: np.ndarray
    image_shape: tuple

    def __len__(self) -> int:
        return len(self.keypoints)


def extract(image, scale_map=None, num_features: int = 1000, descriptor: Union[str, PatchDescriptor] = "hardnet",
            base_radius: float = 16.0, orientation: str = "upright", detector_sigma: float = 2.0,
            detector: str = "hessian") -> Features:
    """Detect up to ``num_features`` keypoints and describe scale-corrected patches.

    Args:
        image: path, ``H x W x 3`` uint8 array or ``1 x H x W`` float tensor.
        scale_map: ``S_{this->other}`` (``H x W``), a float, or ``None``.
        descriptor: ``"hardnet"``, ``"sift"``, a weights path or a :class:`PatchDescriptor`.
        detector_sigma: detection scale of the ``hessian`` detector.
        detector: a single-scale detector of :data:`localscale.features.detector.DETECTORS`; its
            keypoint positions are used, the patch radii come from ``base_radius`` and ``scale_map``.
    """
    gray = image_to_gray_tensor(image)
    desc = get_descriptor(descriptor)
    det = (HessianDetector(num_features, detector_sigma) if detector == "hessian"
           else get_detector(detector, num_features))
    kps, resp = det(gray)
    patches, lafs, radii = ScaleCorrectedPatches(base_radius, desc.patch_size, orientation)(gray, kps, scale_map)
    return Features(kps.numpy(), resp.numpy(), lafs, desc.describe(patches), radii.numpy(), tuple(gray.shape[-2:]))


@dataclass
class MatchResult:
    """Matches between two images.

    Attributes:
        keypoints_a, keypoints_b: ``N_A x 2``, ``N_B x 2``.
        matches: ``K x 2`` int64 indices (A, B); distances: ``K`` descriptor distances.
        errors: ``K`` reprojection errors ``|H x_A - x_B|`` (pixels of B) when ``H`` was given, else ``None``.
        radii_a, radii_b: patch radii of all keypoints; correction: the method used.
        scale_a, scale_b: the (gated) maps / floats used, for inspection.
        verification: :class:`~.verification.VerificationResult` of the matches (``refine=True``).
        refined_a, refined_b: :class:`~.verification.RefinedScale` of A and B (``refine=True``).
    """

    keypoints_a: np.ndarray
    keypoints_b: np.ndarray
    matches: np.ndarray
    distances: np.ndarray
    errors: Optional[np.ndarray]
    radii_a: np.ndarray
    radii_b: np.ndarray
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
    d, idx = match_descriptors(fa.descriptors, fb.descriptors, ratio)
    m = idx.numpy().astype(np.int64)
    errors = None
    if H is not None:
        H = read_homography(H)
        errors = reprojection_errors(fa.keypoints, fb.keypoints, m, H)
    return MatchResult(fa.keypoints, fb.keypoints, m, d.numpy(), errors, fa.radii, fb.radii, correction, H)


def match_pair(image_a, image_b, correction: str = "none", H=None, local_model=None, global_model=None,
               descriptor: Union[str, PatchDescriptor] = "hardnet", num_features: int = 1000,
               ratio: Optional[float] = None, gate: CorrectionGate = CorrectionGate(),
               base_radius: float = 16.0, orientation: str = "upright", bf16: bool = False,
               detector: str = "hessian", refine: bool = False, verification: Optional[VerificationConfig] = None,
               max_passes: int = 2, sift_seed: bool = True, max_side: Optional[int] = MAX_SIDE) -> MatchResult:
    """Detect, correct, describe and mutually match two images.

    Images larger than ``max_side`` (longer side) are matched at that working resolution (a large
    JPEG is decoded at a reduced size); keypoints, radii and errors are returned in pixels of the
    full images, the maps (``scale_a``, ``refined_a``, ...) stay in the working frame
    (``meta["working_scale"]``: working pixels per full-image pixel of A and B).

    With ``refine``: the matches are verified (:func:`~.verification.verify_matches`), both maps are
    refined by the verified geometry (:func:`~.verification.refine_scale_map`, the correction's maps
    as the prior; 1 where the method gives none), the patches are re-cut with the refined maps and
    matched again, up to ``max_passes`` passes while the inlier count grows; the pass with the most
    inliers is returned, with ``verification``, ``refined_a`` and ``refined_b`` set. With
    ``sift_seed``, a first pass that is not verified is followed by the verification of OpenCV SIFT
    matches (:func:`~.verification.sift_seed_points`), whose geometry, if verified, refines the maps.

    Args:
        image_a, image_b: paths or ``H x W x 3`` uint8 arrays.
        correction: ``"none" | "global" | "local" | "fused" | "gt"`` (module docstring).
        H: homography A -> B (array or file); needed for ``"gt"``, gives reprojection errors.
        local_model, global_model: models for ``"local"`` / ``"global"`` / ``"fused"`` (default: bundled weights).
        gate: gating of predicted maps (``NO_GATE`` to disable; not applied to ``"gt"``).
        bf16: run the scale networks under bfloat16 autocast.
        detector: the keypoint detector (:data:`localscale.features.detector.DETECTORS`).
        refine, verification, max_passes, sift_seed: second pass with verified, refined maps (above);
            ``verification`` holds the thresholds (default :class:`~.verification.VerificationConfig`).
        max_side: working resolution (None: full resolution).
    """
    get_detector(detector, max(1, num_features))
    a, to_work_a = load_working_image(image_a, max_side, "image A")
    b, to_work_b = load_working_image(image_b, max_side, "image B")
    H_full = None if H is None else read_homography(H)
    H = None if H is None else to_work_b @ H_full @ np.linalg.inv(to_work_a)
    res = _match_loaded(a, b, correction, H, local_model, global_model, descriptor, num_features, ratio, gate,
                        base_radius, orientation, bf16, detector, refine, verification, max_passes, sift_seed)
    return _to_full_frame(res, to_work_a, to_work_b, H_full)


def _to_full_frame(res: MatchResult, to_work_a: np.ndarray, to_work_b: np.ndarray, H_full) -> MatchResult:
    """Keypoints, radii and errors of a result computed at a working resolution, in full-image pixels."""
    if np.array_equal(to_work_a, np.eye(3)) and np.array_equal(to_work_b, np.eye(3)):
        return res

    def back(points, S):
        return ((points - S[:2, 2]) / np.diag(S)[:2]).astype(np.float32)

    fa, fb = (float(np.sqrt(S[0, 0] * S[1, 1])) for S in (to_work_a, to_work_b))
    res.keypoints_a, res.keypoints_b = back(res.keypoints_a, to_work_a), back(res.keypoints_b, to_work_b)
    res.radii_a, res.radii_b = res.radii_a / fa, res.radii_b / fb
    res.H = H_full
    if H_full is not None:
        res.errors = reprojection_errors(res.keypoints_a, res.keypoints_b, res.matches, H_full)
    res.meta["working_scale"] = [fa, fb]
    return res


def _match_loaded(a, b, correction, H, local_model, global_model, descriptor, num_features, ratio, gate,
                  base_radius, orientation, bf16, detector, refine, verification, max_passes, sift_seed):
    desc = get_descriptor(descriptor)
    sa, sb = scale_maps_for_pair(a, b, correction, H, local_model, global_model, gate, bf16=bf16)
    if refine:
        return refine_match(a, b, sa, sb, H=H, descriptor=desc, num_features=num_features, ratio=ratio,
                            base_radius=base_radius, orientation=orientation, config=verification,
                            max_passes=max_passes, correction=correction, sift_seed=sift_seed,
                            detector=detector)
    fa = extract(a, sa, num_features, desc, base_radius, orientation, detector=detector)
    fb = extract(b, sb, num_features, desc, base_radius, orientation, detector=detector)
    res = match_features(fa, fb, H, ratio, correction)
    res.scale_a, res.scale_b = sa, sb
    res.meta = {"num_features_a": len(fa), "num_features_b": len(fb), "descriptor": desc.name, "detector": detector}
    return res


def _as_map(scale, shape):
    """A map or float as an ``H x W`` float32 map (``None`` = 1)."""
    if scale is None:
        return np.ones(shape, np.float32)
    if np.isscalar(scale):
        return np.full(shape, float(scale), np.float32)
    return np.asarray(scale, np.float32)


def refine_match(image_a, image_b, scale_a=None, scale_b=None, prior_a=None, prior_b=None, H=None,
                 descriptor: Union[str, PatchDescriptor] = "hardnet", num_features: int = 1000,
                 ratio: Optional[float] = None, base_radius: float = 16.0, orientation: str = "upright",
                 config: Optional[VerificationConfig] = None, max_passes: int = 2,
                 correction: str = "refined", sift_seed: bool = True, detector: str = "hessian") -> MatchResult:
    """Match with given maps, verify, refine the maps and match again (:func:`~.verification.refine_matching`).

    Args:
        image_a, image_b: paths or ``H x W x 3`` uint8 arrays.
        scale_a, scale_b: maps (or floats, or ``None``) of the first pass (e.g. the gated network maps).
        prior_a, prior_b: network maps the refined maps start from (default: ``scale_*``; ``None`` = 1).
        H: ground-truth homography A -> B for reprojection errors (optional).
        sift_seed: when the first pass is not verified, try OpenCV SIFT matches as the geometry's seed.
        detector: the keypoint detector (:data:`localscale.features.detector.DETECTORS`).
    Returns:
        :class:`MatchResult` of the pass with the most inliers; ``scale_a`` / ``scale_b`` are the maps
        that pass used, ``refined_a`` / ``refined_b`` the refined maps, ``verification`` the geometry
        they came from (the seed's when it was used; the best pass's when nothing was verified).
    """
    a = load_image(image_a, "image A")
    b = load_image(image_b, "image B")
    desc = get_descriptor(descriptor)
    ga, gb = image_to_gray_tensor(a), image_to_gray_tensor(b)
    det = get_detector(detector, num_features)
    cutter = ScaleCorrectedPatches(base_radius, desc.patch_size, orientation)
    kps = {0: det(ga)[0], 1: det(gb)[0]}
    history = {0: [], 1: []}   # per image, per pass: (map, radii)

    def describer(i, gray):
        def describe(scale_map):
            patches, _, r = cutter(gray, kps[i], scale_map)
            history[i].append((scale_map, r.numpy()))
            return kps[i].numpy(), desc.describe(patches)
        return describe

    pa = _as_map(scale_a if prior_a is None else prior_a, a.shape[:2])
    pb = _as_map(scale_b if prior_b is None else prior_b, b.shape[:2])
    seed = (lambda: sift_seed_points(a, b, num_features)) if sift_seed else None
    out = refine_matching(describer(0, ga), describer(1, gb), a.shape[:2], b.shape[:2], scale_a, scale_b,
                          pa, pb, config or VerificationConfig(), max_passes, ratio, seed)
    (used_a, radii_a), (used_b, radii_b) = history[0][out.best_pass], history[1][out.best_pass]
    errors = None
    if H is not None:
        H = read_homography(H)
        errors = reprojection_errors(out.keypoints_a, out.keypoints_b, out.matches, H)
    res = MatchResult(out.keypoints_a, out.keypoints_b, out.matches, out.distances, errors, radii_a, radii_b,
                      correction, H, used_a, used_b)
    res.verification, res.refined_a, res.refined_b = out.refined_a.verification, out.refined_a, out.refined_b
    res.meta = {"num_features_a": len(out.keypoints_a), "num_features_b": len(out.keypoints_b),
                "descriptor": desc.name, "passes": out.passes, "best_pass": out.best_pass,
                "inlier_counts": list(out.inlier_counts),
                "seed_inliers": None if out.seed is None else int(out.seed.num_inliers)}
    return res


def draw_matches(image_a, image_b, result: MatchResult, path: Union[str, Path, None] = None,
                 threshold: float = 5.0, max_lines: int = 500, max_side: Optional[int] = MAX_SIDE) -> np.ndarray:
    """Side-by-side picture; with ``H`` inliers (error < ``threshold``) green, outliers red,
    else all matches yellow. Images larger than ``max_side`` are drawn at that size. Returns the
    RGB canvas and writes it to ``path`` if given."""
    a, to_a = load_working_image(image_a, max_side, "image A")
    b, to_b = load_working_image(image_b, max_side, "image B")
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
    if path is not None:
        path = Path(path)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise LocalScaleError(f"cannot create folder {path.parent}: {e.strerror or e}") from None
        from ..outputs import atomic_path

        with atomic_path(path) as tmp:   # complete file or none
            if not cv2.imwrite(str(tmp), canvas[..., ::-1]):
                raise LocalScaleError(f"cannot write picture {path}")
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
                distances=result.distances, radii_a=result.radii_a, radii_b=result.radii_b,
                correction=np.array(result.correction))
    if result.errors is not None:
        data["errors"] = result.errors
    if result.H is not None:
        data["H"] = result.H
    from ..outputs import atomic_path

    with atomic_path(path) as tmp:   # complete file or none
        with open(tmp, "wb") as f:
            np.savez(f, **data)


def models_for_correction(correction: str, local_weights=None, global_weights=None, device: str = "cpu"):
    """``(local_model, global_model)`` that ``correction`` needs (None for the other), loaded with
    :func:`localscale.cli.load_scale_model` (``weights`` None = bundled)."""
    from ..cli import load_scale_model

    if correction not in CORRECTIONS:
        raise LocalScaleError(f"correction must be one of {CORRECTIONS}, got {correction!r}")
    local_model = load_scale_model("local", local_weights, device) if correction in ("local", "fused", "searched") else None
    global_model = load_scale_model("global", global_weights, device) if correction in ("global", "fused") else None
    return local_model, global_model


def run_match(image_a, image_b, out, correction: str = "local", H=None, descriptor: str = "hardnet",
              num_features: int = 1000, ratio: Optional[float] = None, local_weights=None, global_weights=None,
              device: str = "cpu", verbose: bool = True, orientation: str = "upright", bf16: bool = False,
              local_model=None, global_model=None, detector: str = "hessian", refine: bool = False,
              max_passes: int = 2, sift_seed: bool = True, max_side: Optional[int] = MAX_SIDE) -> MatchResult:
    """Match two images and write ``out/matches.npz`` and ``out/matches.png``; returns the result.

    With ``refine`` (:func:`match_pair`): also ``out/refined_scale.npy`` / ``refined_source.npy`` /
    ``refined_scale.png`` for A, the same with ``_b`` for B, and ``out/geometry.json``.

    The models ``correction`` needs are ``local_model`` / ``global_model`` when given, else loaded
    from ``local_weights`` / ``global_weights`` (None = bundled) on ``device``.
    """
    if local_model is None and global_model is None:
        local_model, global_model = models_for_correction(correction, local_weights, global_weights, device)
    H = read_homography(H) if H is not None else None
    res = match_pair(image_a, image_b, correction, H, local_model, global_model, descriptor, num_features, ratio,
                     orientation=orientation, bf16=bf16, detector=detector, refine=refine, max_passes=max_passes,
                     sift_seed=sift_seed, max_side=max_side)
    out = Path(out)
    save_matches(res, out / "matches.npz")
    draw_matches(image_a, image_b, res, out / "matches.png")
    if refine:
        from ..cli import write_refinement
        inputs = [x for x in (image_a, image_b) if isinstance(x, (str, Path))]
        write_refinement(out, "", res.refined_a, res.refined_b,
                         {k: res.meta[k] for k in ("passes", "inlier_counts", "seed_inliers")}, inputs)
    if verbose:
        msg = f"{len(res.matches)} matches ({res.meta['num_features_a']}/{res.meta['num_features_b']} features)"
        if res.errors is not None:
            msg += f", accuracy@5px {res.accuracy(5.0):.3f}"
        print(f"{msg}; wrote {out / 'matches.npz'} and {out / 'matches.png'}")
        if refine:
            v = res.verification
            state = "verified" if v.verified else f"not verified ({'; '.join(v.reasons)}), network maps kept"
            print(f"refine: {v.model} with {v.num_inliers} inliers after {res.meta['passes']} pass(es) "
                  f"{res.meta['inlier_counts']}, {state}; wrote {out / 'refined_scale.npy'}, {out / 'geometry.json'}")
    return res


def add_match_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Deprecated: the options of ``localscale match`` (defined once, in :mod:`localscale.cli`)."""
    from ..cli import add_match_options

    return add_match_options(parser)


def run_match_cli(args: argparse.Namespace) -> int:
    """Deprecated: body of ``localscale match`` (:func:`localscale.cli.cmd_match`) for a namespace
    built by :func:`add_match_arguments`; options it lacks take the parser's defaults."""
    from ..cli import add_match_options, cmd_match

    ns = add_match_options(argparse.ArgumentParser()).parse_args([str(args.image_a), str(args.image_b)])
    for old, new in (("out", "output"), ("local_model", "local_weights"), ("global_model", "global_weights")):
        if getattr(args, old, None) is not None:
            setattr(ns, new, getattr(args, old))
    for k, v in vars(args).items():
        if hasattr(ns, k) and v is not None:
            setattr(ns, k, v)
    return cmd_match(ns)


def match_main(argv=None) -> int:
    """Stand-alone entry: ``python -m localscale.features.pipeline A B -o OUT ...`` (same as ``localscale match``)."""
    from ..cli import main

    return main(["match"] + list(sys.argv[1:] if argv is None else argv))


if __name__ == "__main__":
    raise SystemExit(match_main())
