"""Detect -> scale-corrected patches -> describe -> match, for one image or a pair.

``correction`` selects the scale map each image gets (see :mod:`.patches` for the
convention ``scale_map = S_{this->other}``):

* ``"none"``: no map (base radius everywhere);
* ``"global"``: ``S = global_model.predict(A, B).scale``; A gets ``S``, B gets ``1 / S``;
* ``"local"``: A gets ``local_model.predict(A, B).scale``, B gets
  ``local_model.predict(B, A).scale`` (each image encoded once); gated by
  :class:`CorrectionGate`;
* ``"fused"``: the local maps' *shape* with the global ScaleNet's *level*: each map's median
  ``log2 S`` is replaced by ``log2 S_global`` (A) / ``-log2 S_global`` (B)
  (:func:`fuse_local_global`); gated like ``"local"``. The local map is weakest at its level
  under strong zoom, ScaleNet has no spatial variation; together they do better than either
  on held-out synthetic pairs (README, Results);
* ``"gt"``: A gets ``homography_scale_map(H, h_A, w_A)``, B gets it from ``inv(H)``.

Example::

    res = match_pair("a.png", "b.png", correction="gt", H=H, descriptor="sift")
    res.accuracy(5.0), len(res.matches)
    draw_matches("a.png", "b.png", res, "matches.png"); save_matches(res, "matches.npz")
"""
from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Union

import cv2
import numpy as np
import torch

from ..errors import LocalScaleError
from ..geometry import homography_scale_map
from ..io import load_image, read_homography
from .descriptors import PatchDescriptor, get_descriptor
from .detector import HessianDetector, image_to_gray_tensor
from .matching import match_descriptors, matching_accuracy, reprojection_errors
from .patches import ScaleCorrectedPatches

CORRECTIONS = ("none", "global", "local", "fused", "gt")


@dataclass
class CorrectionGate:
    """Gating of *predicted* scale maps so that a correction cannot hurt easy pairs.

    * ``consistency`` (pair level, first): the two maps of a pair must agree,
      ``median log2 S_{A->B} = -median log2 S_{B->A}``; the disagreement
      ``c = median(log2 S_A) + median(log2 S_B)`` is removed half from each map
      (``log2 S -= c / 2``), the dense analogue of ScaleNet's consistency check
      ``ln S = (ln S_AB - ln S_BA) / 2``. It cancels a bias shared by both directions
      (e.g. a network that predicts "B is smaller" for both A->B and B->A).
    * ``min_pair_log2`` (pair level): the correction is used only when the predicted scale
      change is large somewhere: the 90th percentile of ``|log2 S|`` over A's map or over
      B's map (or ``|log2 S|`` of a global scale) must reach this; otherwise both images
      get no correction. A noisy map around 1 (pairs without scale change) is ignored as
      a whole, which keeps the two sides consistent.
    * ``deadzone_log2`` (per pixel): ``S`` with ``|log2 S| < deadzone_log2`` set to 1.
    * ``min_confidence`` (per pixel): ``S`` set to 1 where the network's confidence
      (``1 - entropy / ln 13``) is below this.

    Defaults: consistency on, pair-level 0.25 (a ~1.2x scale change), no per-pixel rules.
    The pair level was chosen with the stage-1 (GPU) Local-ScaleNet of 2026-11-30 on a
    *selection* set of held-out synthetic pairs (``eval/matching_accuracy.py --seed 1 --sequences ""``,
    HardNet, hard split, local MMA@5: 0.656 at 0.5, 0.677 at 0.25, 0.677 at 0.0); 0.25 keeps a
    guard for near-identity pairs at no cost there. Re-checked for the fine-tuned model shipped
    now, same set: 0.668 at 0.5, 0.690 at 0.25, 0.690 at 0.0, so 0.25 stays. Earlier measurements (older model) are in
    ``localscale/evaluation/hpatches.py``'s docstring (the per-pixel deadzone made things
    worse: it gates the two sides of a match independently). ``NO_GATE`` disables everything.
    """

    min_pair_log2: float = 0.25
    deadzone_log2: float = 0.0
    min_confidence: float = 0.0
    consistency: bool = True

    def apply(self, scale_map, confidence=None):
        """Per-pixel rules (deadzone, confidence) on one map or float."""
        if scale_map is None:
            return None
        if np.isscalar(scale_map):
            return 1.0 if abs(math.log2(float(scale_map))) < self.deadzone_log2 else float(scale_map)
        s = np.asarray(scale_map, np.float32).copy()
        with np.errstate(invalid="ignore", divide="ignore"):
            s[np.abs(np.log2(s)) < self.deadzone_log2] = 1.0
        if confidence is not None and self.min_confidence > 0:
            s[np.asarray(confidence) < self.min_confidence] = 1.0
        return s

    @staticmethod
    def magnitude(scale_map) -> float:
        """Robust size of a map's scale change: 90th percentile of ``|log2 S|`` (``|log2 S|`` for a float)."""
        if scale_map is None:
            return 0.0
        if np.isscalar(scale_map):
            return abs(math.log2(float(scale_map)))
        v = np.abs(np.log2(np.asarray(scale_map, np.float64)))
        v = v[np.isfinite(v)]
        return float(np.percentile(v, 90)) if v.size else 0.0

    def apply_pair(self, scale_a, scale_b, confidence_a=None, confidence_b=None):
        """Gate the two maps of a pair: ``(None, None)`` when the pair-level rule says no correction."""
        if self.consistency and scale_a is not None and scale_b is not None \
                and not np.isscalar(scale_a) and not np.isscalar(scale_b):
            la = np.log2(np.asarray(scale_a, np.float64))
            lb = np.log2(np.asarray(scale_b, np.float64))
            fa, fb = la[np.isfinite(la)], lb[np.isfinite(lb)]
            if fa.size and fb.size:
                c = float(np.median(fa) + np.median(fb))
                scale_a = np.exp2(la - c / 2).astype(np.float32)
                scale_b = np.exp2(lb - c / 2).astype(np.float32)
        if self.min_pair_log2 > 0 and max(self.magnitude(scale_a), self.magnitude(scale_b)) < self.min_pair_log2:
            return None, None
        return self.apply(scale_a, confidence_a), self.apply(scale_b, confidence_b)


NO_GATE = CorrectionGate(0.0, 0.0, 0.0, consistency=False)


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
            base_radius: float = 16.0, orientation: str = "upright", detector_sigma: float = 2.0) -> Features:
    """Detect up to ``num_features`` keypoints and describe scale-corrected patches.

    Args:
        image: path, ``H x W x 3`` uint8 array or ``1 x H x W`` float tensor.
        scale_map: ``S_{this->other}`` (``H x W``), a float, or ``None``.
        descriptor: ``"hardnet"``, ``"sift"``, a weights path or a :class:`PatchDescriptor`.
    """
    gray = image_to_gray_tensor(image)
    desc = get_descriptor(descriptor)
    kps, resp = HessianDetector(num_features, detector_sigma)(gray)
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

    def inliers(self, threshold: float = 5.0) -> np.ndarray:
        if self.errors is None:
            raise LocalScaleError("no homography was given, inliers are unknown")
        return self.errors < threshold

    def accuracy(self, threshold: float = 5.0) -> float:
        if self.errors is None:
            raise LocalScaleError("no homography was given, accuracy is unknown")
        return float(matching_accuracy(self.errors, [threshold])[0])


def scale_maps_for_pair(image_a: np.ndarray, image_b: np.ndarray, correction: str, H=None, local_model=None,
                        global_model=None, gate: CorrectionGate = CorrectionGate(), encodings=None):
    """The maps ``(for A, for B)`` of a correction method (see module docstring).

    ``encodings``: optional cached ``(EncodedImage of A, of B)`` for the local model.
    """
    if correction not in CORRECTIONS:
        raise LocalScaleError(f"correction must be one of {CORRECTIONS}, got {correction!r}")
    if correction == "none":
        return None, None
    if correction == "gt":
        if H is None:
            raise LocalScaleError("correction='gt' needs the homography H (A -> B)")
        H = read_homography(H)   # homography_scale_map orients the sign of H itself
        return (homography_scale_map(H, *image_a.shape[:2]).astype(np.float32),
                homography_scale_map(np.linalg.inv(H), *image_b.shape[:2]).astype(np.float32))
    if correction == "global":
        s = _global_scale(image_a, image_b, global_model)
        return gate.apply_pair(s, 1.0 / s)
    if local_model is None:
        from ..models import LocalScaleNet
        local_model = LocalScaleNet.from_pretrained()
    ea, eb = encodings or (local_model.encode_image(image_a, "image A"), local_model.encode_image(image_b, "image B"))
    pa = local_model.predict_from_features(ea, eb)
    pb = local_model.predict_from_features(eb, ea)
    if correction == "fused":
        s = _global_scale(image_a, image_b, global_model)
        return gate.apply_pair(*fuse_local_global(pa.scale, pb.scale, s), pa.confidence, pb.confidence)
    return gate.apply_pair(pa.scale, pb.scale, pa.confidence, pb.confidence)


def _global_scale(image_a: np.ndarray, image_b: np.ndarray, global_model=None) -> float:
    """Consistency-checked ``S_{A->B}`` of ScaleNet (bundled weights when ``global_model`` is None)."""
    if global_model is None:
        from ..models import ScaleNet
        global_model = ScaleNet.from_pretrained()
    return float(global_model.predict(image_a, image_b).scale)


def fuse_local_global(scale_a: np.ndarray, scale_b: np.ndarray, global_scale: float):
    """Shift two local maps (``S_{A->B}`` on A, ``S_{B->A}`` on B) in log space so that their
    medians become ``global_scale`` and ``1 / global_scale``; the spatial variation is kept.

    Args:
        scale_a: ``H_A x W_A``; scale_b: ``H_B x W_B`` (positive floats); global_scale: ``S_{A->B}``.
    Returns:
        ``(scale_a', scale_b')`` float32, same shapes.
    """
    if not (np.isfinite(global_scale) and global_scale > 0):
        raise LocalScaleError(f"global scale must be a positive finite number, got {global_scale}")
    g = math.log2(global_scale)
    out = []
    for m, level in ((scale_a, g), (scale_b, -g)):
        lm = np.log2(np.asarray(m, np.float64))
        finite = lm[np.isfinite(lm)]
        if not finite.size:
            raise LocalScaleError("local scale map has no finite positive value")
        out.append(np.exp2(lm - np.median(finite) + level).astype(np.float32))
    return out[0], out[1]


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
               base_radius: float = 16.0, orientation: str = "upright") -> MatchResult:
    """Detect, correct, describe and mutually match two images.

    Args:
        image_a, image_b: paths or ``H x W x 3`` uint8 arrays.
        correction: ``"none" | "global" | "local" | "fused" | "gt"`` (module docstring).
        H: homography A -> B (array or file); needed for ``"gt"``, gives reprojection errors.
        local_model, global_model: models for ``"local"`` / ``"global"`` / ``"fused"`` (default: bundled weights).
        gate: gating of predicted maps (``NO_GATE`` to disable; not applied to ``"gt"``).
    """
    a = load_image(image_a, "image A")
    b = load_image(image_b, "image B")
    desc = get_descriptor(descriptor)
    sa, sb = scale_maps_for_pair(a, b, correction, H, local_model, global_model, gate)
    fa = extract(a, sa, num_features, desc, base_radius, orientation)
    fb = extract(b, sb, num_features, desc, base_radius, orientation)
    res = match_features(fa, fb, H, ratio, correction)
    res.scale_a, res.scale_b = sa, sb
    res.meta = {"num_features_a": len(fa), "num_features_b": len(fb), "descriptor": desc.name}
    return res


def draw_matches(image_a, image_b, result: MatchResult, path: Union[str, Path, None] = None,
                 threshold: float = 5.0, max_lines: int = 500) -> np.ndarray:
    """Side-by-side picture; with ``H`` inliers (error < ``threshold``) green, outliers red,
    else all matches yellow. Returns the RGB canvas and writes it to ``path`` if given."""
    a, b = load_image(image_a, "image A"), load_image(image_b, "image B")
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
    for i, (ia, ib) in enumerate(m):
        pa = tuple(int(round(v)) for v in result.keypoints_a[ia])
        pb = result.keypoints_b[ib]
        pb = (int(round(pb[0])) + a.shape[1], int(round(pb[1])))
        colour = (255, 220, 0) if ok is None else ((0, 220, 0) if ok[i] else (230, 0, 0))
        cv2.line(canvas, pa, pb, colour, lw, cv2.LINE_AA)
        cv2.circle(canvas, pa, 2 * lw, colour, -1)
        cv2.circle(canvas, pb, 2 * lw, colour, -1)
    if path is not None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(path), canvas[..., ::-1]):
            raise LocalScaleError(f"cannot write picture {path}")
    return canvas


def save_matches(result: MatchResult, path: Union[str, Path]) -> None:
    """Write the result to ``.npz`` (keypoints_a/b, matches, distances, radii_a/b, correction,
    and errors / H when known)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = dict(keypoints_a=result.keypoints_a, keypoints_b=result.keypoints_b, matches=result.matches,
                distances=result.distances, radii_a=result.radii_a, radii_b=result.radii_b,
                correction=np.array(result.correction))
    if result.errors is not None:
        data["errors"] = result.errors
    if result.H is not None:
        data["H"] = result.H
    np.savez(path, **data)


def add_match_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Arguments of ``localscale match A B -o OUT ...`` (for the package CLI)."""
    parser.add_argument("image_a")
    parser.add_argument("image_b")
    parser.add_argument("-o", "--out", required=True, help="output folder (matches.npz, matches.png)")
    parser.add_argument("--correction", choices=CORRECTIONS, default="local")
    parser.add_argument("--H", default=None, help="homography file A->B (needed for gt; gives inliers)")
    parser.add_argument("--descriptor", default="hardnet", help="hardnet | sift | path to HardNet weights")
    parser.add_argument("--num-features", type=int, default=1000)
    parser.add_argument("--ratio", type=float, default=None, help="Lowe ratio test on top of mutual NN")
    parser.add_argument("--local-weights", default=None)
    parser.add_argument("--global-weights", default=None)
    parser.add_argument("--orientation", choices=("upright", "gradient"), default="upright",
                        help="gradient: dominant-gradient orientation (for in-plane rotations)")
    return parser


def run_match(image_a, image_b, out, correction: str = "local", H=None, descriptor: str = "hardnet",
              num_features: int = 1000, ratio: Optional[float] = None, local_weights=None, global_weights=None,
              device: str = "cpu", verbose: bool = True, orientation: str = "upright") -> MatchResult:
    """Match two images and write ``out/matches.npz`` and ``out/matches.png``; returns the result."""
    local_model = global_model = None
    if correction == "local":
        from ..models import LocalScaleNet
        local_model = LocalScaleNet.from_pretrained(local_weights, device=device)
    elif correction == "global":
        from ..models import ScaleNet
        global_model = ScaleNet.from_pretrained(global_weights, device=device)
    H = read_homography(H) if H is not None else None
    res = match_pair(image_a, image_b, correction, H, local_model, global_model, descriptor, num_features, ratio,
                     orientation=orientation)
    out = Path(out)
    save_matches(res, out / "matches.npz")
    draw_matches(image_a, image_b, res, out / "matches.png")
    if verbose:
        msg = f"{len(res.matches)} matches ({res.meta['num_features_a']}/{res.meta['num_features_b']} features)"
        if res.errors is not None:
            msg += f", accuracy@5px {res.accuracy(5.0):.3f}"
        print(f"{msg}; wrote {out / 'matches.npz'} and {out / 'matches.png'}")
    return res


def run_match_cli(args: argparse.Namespace) -> int:
    """Body of ``localscale match``; returns the exit code 0.

    Reads from ``args``: ``image_a``, ``image_b``, ``out`` or ``output``, ``correction``,
    ``H`` (file or None), ``descriptor``, ``num_features``, and optionally ``ratio``,
    ``local_weights``/``local_model``, ``global_weights``/``global_model`` (checkpoint
    paths, None = bundled), ``device``, ``orientation`` (``upright``/``gradient``).
    Writes ``OUT/matches.npz`` and ``OUT/matches.png``.
    """
    g = lambda *names, default=None: next((getattr(args, n) for n in names if getattr(args, n, None) is not None),
                                          default)
    out = g("out", "output", default="out")
    run_match(args.image_a, args.image_b, out, g("correction", default="local"), g("H"),
              g("descriptor", default="hardnet"), g("num_features", default=1000), g("ratio"),
              g("local_weights", "local_model"), g("global_weights", "global_model"), g("device", default="cpu"),
              orientation=g("orientation", default="upright"))
    return 0


def match_main(argv=None) -> int:
    """Stand-alone entry: ``python -m localscale.features.pipeline A B -o OUT ...``."""
    parser = add_match_arguments(argparse.ArgumentParser(description="match two images"))
    run_match_cli(parser.parse_args(argv))
    return 0


if __name__ == "__main__":
    raise SystemExit(match_main())
