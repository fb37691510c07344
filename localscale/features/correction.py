"""Scale maps for patch-size correction: the maps each image of a pair gets, per method.

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
* ``"searched"``: A gets ``search_scale_map(local_model, A, B)``'s map, B that of
  ``search_scale_map(local_model, B, A)`` (:mod:`localscale.search`: the windows of the two
  images that share the most content; for strong zoom and low overlap, ~30x slower); gated
  like ``"local"``;
* ``"gt"``: A gets ``homography_scale_map(H, h_A, w_A)``, B gets it from ``inv(H)``;
* ``"gt_gated"``: the ``"gt"`` maps through the same gate as ``"local"`` (what gating costs an oracle);
* ``"refined"``: the ``"local"`` maps, then the matches are verified, the maps refined by the
  verified geometry and the pair matched again (:func:`~.verification.refine_matching`);
* ``"auto"``: hypotheses of scale and quarter turn from both networks, each matched and verified
  (:mod:`.auto`); it makes no maps here (``None, None``).

:data:`CORRECTION_METHODS` holds each method's needs (models, homography, refinement); the CLI
choices, model loading and the evaluation all come from it.

Example::

    sa, sb = scale_maps_for_pair(a, b, "fused", local_model=LocalScaleNet.from_pretrained(),
                                 global_model=ScaleNet.from_pretrained())
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import LocalScaleError
from ..geometry import homography_scale_map
from ..io import read_homography



@dataclass(frozen=True)
class Correction:
    """A correction method: its name, the scale models it needs (``"local"``, ``"global"``),
    whether it needs the true homography, whether it refines by verified geometry, a help text."""

    name: str
    models: tuple = ()
    needs_H: bool = False
    refine: bool = False
    help: str = ""
    auto: bool = False


#: every correction method, by name
CORRECTION_METHODS = {c.name: c for c in (
    Correction("none", help="no correction"),
    Correction("global", ("global",), help="ScaleNet's consistency-checked factor"),
    Correction("local", ("local",), help="Local-ScaleNet maps, gated"),
    Correction("fused", ("local", "global"), help="local map shape + global ScaleNet level"),
    Correction("searched", ("local",), help="local maps from the windows sharing the most content "
                                            "(strong zoom, low overlap; ~30x slower)"),
    Correction("gt", needs_H=True, help="analytic map of the true homography --H, and B turned by the quarter "
                                        "turn that undoes its rotation (the ceiling of rectification)"),
    Correction("gt_gated", needs_H=True, help="the gt map through the gate of local"),
    Correction("refined", ("local",), refine=True, help="local maps, verified, refined by the geometry, "
                                                         "matched again (as --refine)"),
    Correction("auto", ("local", "global"), auto=True,
               help="the networks propose scales and quarter turns of B, each is matched and verified by "
                    "geometry, the first clear one wins (any matcher)"),
)}
#: the names of :data:`CORRECTION_METHODS`
CORRECTIONS = tuple(CORRECTION_METHODS)
GATE_WEIGHTINGS = ("none", "visible", "reliability")


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

    * ``weighting`` (consistency and pair level): which pixels count in the medians and the
      percentile: ``"none"`` (all of each map), ``"visible"`` (weighted by ``pred.visible``,
      the probability that the pixel is seen in the other image) or ``"reliability"``
      (weighted by ``pred.reliability``, the calibrated probability that the pixel is
      visible and its scale within 1.25x). Pixels the other image does not show have no true
      scale, so their values only add noise to the pair's level. Without the weights (a
      global method, or a model without those outputs) all pixels count.

    Defaults: consistency on, weighting ``"reliability"``, pair-level 0.25 (a ~1.2x scale
    change), no per-pixel rules. The weighting was chosen on held-out synthetic pairs (HardNet
    MMA@5 of ``local``, ``eval/matching_accuracy.py --seed 1 --sequences ""``: 0.617 / 0.693 /
    0.695 with none / visible / reliability; with ``--crop 0.7`` 0.644 / 0.757 / 0.764).
    The pair level was chosen on a selection set of held-out synthetic pairs
    (``eval/matching_accuracy.py --seed 1 --sequences ""``; numbers in ``docs/RESULTS.md``); a
    per-pixel deadzone made matching worse, since it gates the two sides of a match
    independently. ``NO_GATE`` disables everything.
    """

    min_pair_log2: float = 0.25
    deadzone_log2: float = 0.0
    min_confidence: float = 0.0
    consistency: bool = True
    weighting: str = "reliability"

    def __post_init__(self):
        if self.weighting not in GATE_WEIGHTINGS:
            raise LocalScaleError(f"gate weighting must be one of {GATE_WEIGHTINGS}, got {self.weighting!r}")

    def weights_of(self, prediction):
        """The per-pixel weights ``weighting`` names, from a ``LocalScalePrediction`` (None: equal weights)."""
        if self.weighting == "none" or prediction is None:
            return None
        return getattr(prediction, self.weighting, None)

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
    def magnitude(scale_map, weights=None) -> float:
        """Robust size of a map's scale change: (weighted) 90th percentile of ``|log2 S|``
        (``|log2 S|`` for a float)."""
        if scale_map is None:
            return 0.0
        if np.isscalar(scale_map):
            return abs(math.log2(float(scale_map)))
        v, w = _finite_log2(scale_map, weights)
        v = np.abs(v)
        return weighted_quantile(v, w, 0.9) if v.size else 0.0

    def apply_pair(self, scale_a, scale_b, confidence_a=None, confidence_b=None, weights_a=None, weights_b=None):
        """Gate the two maps of a pair: ``(None, None)`` when the pair-level rule says no correction.

        ``weights_a`` / ``weights_b``: per-pixel weights of the medians and the percentile
        (``H x W`` like the maps; e.g. ``self.weights_of(prediction)``); None counts every pixel.
        """
        maps = not (scale_a is None or scale_b is None or np.isscalar(scale_a) or np.isscalar(scale_b))
        if not maps:
            weights_a = weights_b = None
        if self.consistency and maps:
            log_a, log_b = np.log2(np.asarray(scale_a, np.float64)), np.log2(np.asarray(scale_b, np.float64))
            la, wa = _finite(log_a, weights_a)
            lb, wb = _finite(log_b, weights_b)
            if la.size and lb.size:
                c = weighted_quantile(la, wa, 0.5) + weighted_quantile(lb, wb, 0.5)
                scale_a = np.exp2(log_a - c / 2).astype(np.float32)
                scale_b = np.exp2(log_b - c / 2).astype(np.float32)
        if self.min_pair_log2 > 0 and max(self.magnitude(scale_a, weights_a),
                                          self.magnitude(scale_b, weights_b)) < self.min_pair_log2:
            return None, None
        return self.apply(scale_a, confidence_a), self.apply(scale_b, confidence_b)

    def apply_predictions(self, pred_a, pred_b):
        """:meth:`apply_pair` on two ``LocalScalePrediction``s (A->B and B->A): their scale maps,
        confidences and the weights ``weighting`` names."""
        return self.apply_pair(pred_a.scale, pred_b.scale, pred_a.confidence, pred_b.confidence,
                               self.weights_of(pred_a), self.weights_of(pred_b))


def _finite_log2(scale_map, weights=None):
    """``(log2 S, weights)`` over the finite pixels, flattened; weights None stays None."""
    return _finite(np.log2(np.asarray(scale_map, np.float64)), weights)


def _finite(log_map: np.ndarray, weights=None):
    """``(values, weights)`` of a log map over its finite pixels, flattened; weights None stays None."""
    lm = log_map.ravel()
    keep = np.isfinite(lm)
    if weights is None:
        return lm[keep], None
    w = np.asarray(weights, np.float64)
    if w.shape != log_map.shape:
        raise LocalScaleError(f"gate weights have shape {w.shape}, the map {log_map.shape}")
    w = w.ravel()
    keep &= np.isfinite(w)
    return lm[keep], np.clip(w[keep], 0.0, None)


def weighted_quantile(values: np.ndarray, weights: np.ndarray | None, q: float) -> float:
    """The ``q`` quantile of ``values`` (1-D) with non-negative ``weights``; equal weights when
    ``weights`` is None or sums to (almost) nothing."""
    if weights is None or weights.sum() <= 1e-6 * max(1, weights.size):
        return float(np.quantile(values, q))
    order = np.argsort(values)
    c = np.cumsum(weights[order])
    return float(values[order][min(np.searchsorted(c, q * c[-1]), values.size - 1)])


NO_GATE = CorrectionGate(0.0, 0.0, 0.0, consistency=False, weighting="none")


def scale_maps_for_pair(image_a: np.ndarray, image_b: np.ndarray, correction: str, H=None, local_model=None,
                        global_model=None, gate: CorrectionGate = CorrectionGate(), encodings=None,
                        bf16: bool = False):
    """The maps ``(for A, for B)`` of a correction method (see module docstring).

    ``local_model`` / ``global_model``: the models the method needs (bundled weights when None).
    ``encodings``: optional cached ``(EncodedImage of A, of B)`` for the local model.
    ``bf16``: run the networks under bfloat16 autocast.
    """
    method = get_correction(correction)
    if correction == "none" or method.auto:
        return None, None
    if method.needs_H:
        if H is None:
            raise LocalScaleError(f"correction={correction!r} needs the homography H (A -> B)")
        H = read_homography(H)   # homography_scale_map orients the sign of H itself
        maps = (homography_scale_map(H, *image_a.shape[:2]).astype(np.float32),
                homography_scale_map(np.linalg.inv(H), *image_b.shape[:2]).astype(np.float32))
        return gate.apply_pair(*maps) if correction == "gt_gated" else maps
    if correction == "global":
        s = _global_scale(image_a, image_b, global_model, bf16)
        return gate.apply_pair(s, 1.0 / s)
    if local_model is None:
        from ..models import LocalScaleNet
        local_model = LocalScaleNet.from_pretrained()
    if correction == "searched":
        from ..search import search_scale_map

        pa = search_scale_map(local_model, image_a, image_b, bf16=bf16).prediction
        pb = search_scale_map(local_model, image_b, image_a, bf16=bf16).prediction
        return gate.apply_predictions(pa, pb)
    ea, eb = encodings or (local_model.encode_image(image_a, "image A", bf16),
                           local_model.encode_image(image_b, "image B", bf16))
    pa = local_model.predict_from_features(ea, eb, bf16=bf16)
    pb = local_model.predict_from_features(eb, ea, bf16=bf16)
    if correction == "fused":
        s = _global_scale(image_a, image_b, global_model, bf16)
        wa, wb = gate.weights_of(pa), gate.weights_of(pb)
        return gate.apply_pair(*fuse_local_global(pa.scale, pb.scale, s, wa, wb), pa.confidence, pb.confidence,
                               wa, wb)
    return gate.apply_predictions(pa, pb)


def get_correction(name: str) -> Correction:
    """The :class:`Correction` called ``name`` (:class:`LocalScaleError` for an unknown one)."""
    if not isinstance(name, str) or name not in CORRECTION_METHODS:
        raise LocalScaleError(f"correction must be one of {', '.join(CORRECTIONS)}, got {name!r}")
    return CORRECTION_METHODS[name]


def models_for_correction(correction: str, local_weights=None, global_weights=None, device: str = "cpu"):
    """``(local_model, global_model)`` that ``correction`` needs (None for the other), loaded by
    :func:`localscale.loading.load_scale_model` (``weights`` None = bundled)."""
    from ..loading import load_scale_model

    needs = get_correction(correction).models
    return (load_scale_model("local", local_weights, device) if "local" in needs else None,
            load_scale_model("global", global_weights, device) if "global" in needs else None)


def _global_scale(image_a: np.ndarray, image_b: np.ndarray, global_model=None, bf16: bool = False) -> float:
    """Consistency-checked ``S_{A->B}`` of ScaleNet (bundled weights when ``global_model`` is None)."""
    if global_model is None:
        from ..models import ScaleNet
        global_model = ScaleNet.from_pretrained()
    return float(global_model.predict(image_a, image_b, bf16=bf16).scale)


def fuse_local_global(scale_a: np.ndarray, scale_b: np.ndarray, global_scale: float, weights_a=None, weights_b=None):
    """Shift two local maps (``S_{A->B}`` on A, ``S_{B->A}`` on B) in log space so that their
    medians become ``global_scale`` and ``1 / global_scale``; the spatial variation is kept.

    Args:
        scale_a: ``H_A x W_A``; scale_b: ``H_B x W_B`` (positive floats); global_scale: ``S_{A->B}``.
        weights_a, weights_b: optional per-pixel weights of the medians (same shapes as the maps).
    Returns:
        ``(scale_a', scale_b')`` float32, same shapes.
    """
    if not (np.isfinite(global_scale) and global_scale > 0):
        raise LocalScaleError(f"global scale must be a positive finite number, got {global_scale}")
    g = math.log2(global_scale)
    out = []
    for m, w, level in ((scale_a, weights_a, g), (scale_b, weights_b, -g)):
        finite, fw = _finite_log2(m, w)
        if not finite.size:
            raise LocalScaleError("local scale map has no finite positive value")
        lm = np.log2(np.asarray(m, np.float64))
        out.append(np.exp2(lm - weighted_quantile(finite, fw, 0.5) + level).astype(np.float32))
    return out[0], out[1]
