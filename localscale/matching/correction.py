"""Correction methods: the scale maps each image of a pair gets before matching, per method.

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
  verified geometry and the pair matched again (:func:`~.refinement.refine_passes`);
* ``"auto"``: hypotheses of scale and quarter turn from both networks, each matched and verified
  (:mod:`.auto`); it makes no maps here (``None, None``).

A name is resolved once into a :class:`Correction` (:func:`get_correction`): its needs
(models, homography, refinement), :meth:`Correction.load_models` and :meth:`Correction.maps`.
:data:`CORRECTION_METHODS` holds them all; the CLI choices, model loading and the evaluation
come from it.

Example::

    fused = get_correction("fused")
    local, global_ = fused.load_models()                 # the bundled weights of what it needs
    sa, sb = fused.maps(a, b, local_model=local, global_model=global_)
    sa, sb = scale_maps_for_pair(a, b, "fused")          # the same, functional
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Optional, Union

import numpy as np

from ..core.errors import LocalScaleError
from ..geometry import homography_scale_map
from ..io import read_homography

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
    change), no per-pixel rules (how they were chosen: ``docs/decisions/correction-gate-weighting.md``). ``NO_GATE``
    disables everything.
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
        if (
            self.min_pair_log2 > 0
            and max(self.magnitude(scale_a, weights_a), self.magnitude(scale_b, weights_b)) < self.min_pair_log2
        ):
            return None, None
        return self.apply(scale_a, confidence_a), self.apply(scale_b, confidence_b)

    def apply_predictions(self, pred_a, pred_b):
        """:meth:`apply_pair` on two ``LocalScalePrediction``s (A->B and B->A): their scale maps,
        confidences and the weights ``weighting`` names."""
        return self.apply_pair(
            pred_a.scale,
            pred_b.scale,
            pred_a.confidence,
            pred_b.confidence,
            self.weights_of(pred_a),
            self.weights_of(pred_b),
        )


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


@dataclass(frozen=True)
class Correction:
    """A correction method: its name, the scale models it needs (``"local"``, ``"global"``),
    whether it needs the true homography, refines by verified geometry, is the hypothesis loop
    (``auto``) or turns B by the truth's quarter turn (``gt``), whether its maps come from one
    Local-ScaleNet encoding of each image (``local_encodings``: cached encodings can be given to
    :meth:`maps`), a help text, and how its maps are made."""

    name: str
    models: tuple = ()
    needs_H: bool = False
    refine: bool = False
    help: str = ""
    auto: bool = False
    turns_to_truth: bool = False
    local_encodings: bool = False
    make_maps: Optional[Callable] = field(default=None, repr=False, compare=False)

    def __str__(self) -> str:
        return self.name

    @property
    def as_is(self) -> bool:
        """Whether the images are matched as they are: no maps, no truth, no hypothesis loop."""
        return not (self.models or self.needs_H or self.auto)

    def maps(
        self,
        image_a: np.ndarray,
        image_b: np.ndarray,
        H=None,
        local_model=None,
        global_model=None,
        gate: "CorrectionGate" = None,
        encodings=None,
        bf16: bool = False,
    ):
        """The maps ``(for A, for B)`` (``S_{A->B}`` on A, ``S_{B->A}`` on B; floats, ``H x W``
        maps or None) of ``H x W x 3`` images.

        ``local_model`` / ``global_model``: the models the method needs (bundled weights when None).
        ``gate``: gating of predicted maps (default :class:`CorrectionGate`). ``encodings``: optional
        cached ``(EncodedImage of A, of B)`` of the local model. ``bf16``: networks under bfloat16 autocast.
        """
        if self.make_maps is None:
            return None, None
        if self.needs_H and H is None:
            raise LocalScaleError(f"correction={self.name!r} needs the homography H (A -> B)")
        if "local" in self.models and local_model is None:
            from ..models import LocalScaleNet

            local_model = LocalScaleNet.from_pretrained()
        if "global" in self.models and global_model is None:
            from ..models import ScaleNet

            global_model = ScaleNet.from_pretrained()
        return self.make_maps(
            _Pair(
                image_a,
                image_b,
                H,
                local_model,
                global_model,
                CorrectionGate() if gate is None else gate,
                encodings,
                bf16,
            )
        )

    def load_models(self, local_weights=None, global_weights=None, device: str = "cpu"):
        """``(local_model, global_model)`` this method needs (None for the other), loaded by
        :func:`localscale.loading.load_scale_model` (``weights`` None = bundled)."""
        from ..loading import load_scale_model

        return (
            load_scale_model("local", local_weights, device) if "local" in self.models else None,
            load_scale_model("global", global_weights, device) if "global" in self.models else None,
        )

    def check_models(self, local_model=None, global_model=None) -> None:
        """Raise :class:`LocalScaleError` when a given model is not of the kind this method needs."""
        from ..models import LocalScaleNet, ScaleNet

        for kind, model, cls in (("local", local_model, LocalScaleNet), ("global", global_model, ScaleNet)):
            if kind in self.models and model is not None and not isinstance(model, cls):
                raise LocalScaleError(
                    f"correction {self.name!r}: {kind}_model must be a {cls.__name__}, got {type(model).__name__}"
                )


@dataclass
class _Pair:
    """What a method's map maker gets."""

    a: np.ndarray
    b: np.ndarray
    H: object
    local_model: object
    global_model: object
    gate: "CorrectionGate"
    encodings: object
    bf16: bool

    def global_scale(self) -> float:
        """Consistency-checked ``S_{A->B}`` of ScaleNet."""
        return float(self.global_model.predict(self.a, self.b, bf16=self.bf16).scale)

    def local_predictions(self):
        """Local-ScaleNet's predictions A->B and B->A (each image encoded once)."""
        m = self.local_model
        ea, eb = self.encodings or (
            m.encode_image(self.a, "image A", self.bf16),
            m.encode_image(self.b, "image B", self.bf16),
        )
        return m.predict_from_features(ea, eb, bf16=self.bf16), m.predict_from_features(eb, ea, bf16=self.bf16)


def _global_maps(p: _Pair):
    s = p.global_scale()
    return p.gate.apply_pair(s, 1.0 / s)


def _local_maps(p: _Pair):
    return p.gate.apply_predictions(*p.local_predictions())


def _fused_maps(p: _Pair):
    pa, pb = p.local_predictions()
    wa, wb = p.gate.weights_of(pa), p.gate.weights_of(pb)
    fused = fuse_local_global(pa.scale, pb.scale, p.global_scale(), wa, wb)
    return p.gate.apply_pair(*fused, pa.confidence, pb.confidence, wa, wb)


def _searched_maps(p: _Pair):
    from ..search import search_scale_map

    pa = search_scale_map(p.local_model, p.a, p.b, bf16=p.bf16).prediction
    pb = search_scale_map(p.local_model, p.b, p.a, bf16=p.bf16).prediction
    return p.gate.apply_predictions(pa, pb)


def _truth_maps(p: _Pair):
    H = read_homography(p.H)  # homography_scale_map orients the sign of H itself
    return (
        homography_scale_map(H, *p.a.shape[:2]).astype(np.float32),
        homography_scale_map(np.linalg.inv(H), *p.b.shape[:2]).astype(np.float32),
    )


def _gated_truth_maps(p: _Pair):
    return p.gate.apply_pair(*_truth_maps(p))


#: every correction method, by name
CORRECTION_METHODS = {
    c.name: c
    for c in (
        Correction("none", help="no correction"),
        Correction("global", ("global",), help="ScaleNet's consistency-checked factor", make_maps=_global_maps),
        Correction("local", ("local",), local_encodings=True, help="Local-ScaleNet maps, gated", make_maps=_local_maps),
        Correction(
            "fused",
            ("local", "global"),
            local_encodings=True,
            help="local map shape + global ScaleNet level",
            make_maps=_fused_maps,
        ),
        Correction(
            "searched",
            ("local",),
            help="local maps from the windows sharing the most content (strong zoom, low overlap; ~30x slower)",
            make_maps=_searched_maps,
        ),
        Correction(
            "gt",
            needs_H=True,
            turns_to_truth=True,
            make_maps=_truth_maps,
            help="analytic map of the true homography --H, and B turned by the quarter turn that undoes "
            "its rotation (the ceiling of rectification)",
        ),
        Correction(
            "gt_gated",
            needs_H=True,
            turns_to_truth=True,
            make_maps=_gated_truth_maps,
            help="the gt map through the gate of local",
        ),
        Correction(
            "refined",
            ("local",),
            refine=True,
            local_encodings=True,
            make_maps=_local_maps,
            help="local maps, verified, refined by the geometry, matched again (as --refine)",
        ),
        Correction(
            "auto",
            ("local", "global"),
            auto=True,
            help="the networks propose scales and quarter turns of B, each is matched and verified by "
            "geometry, the first clear one wins (any matcher)",
        ),
    )
}
#: the names of :data:`CORRECTION_METHODS`
CORRECTIONS = tuple(CORRECTION_METHODS)


def get_correction(correction: Union[str, Correction]) -> Correction:
    """The :class:`Correction` called ``correction`` (a :class:`Correction` is returned as it is;
    :class:`LocalScaleError` for an unknown name)."""
    if isinstance(correction, Correction):
        return correction
    if not isinstance(correction, str) or correction not in CORRECTION_METHODS:
        raise LocalScaleError(f"correction must be one of {', '.join(CORRECTIONS)}, got {correction!r}")
    return CORRECTION_METHODS[correction]


def scale_maps_for_pair(
    image_a: np.ndarray,
    image_b: np.ndarray,
    correction: Union[str, Correction],
    H=None,
    local_model=None,
    global_model=None,
    gate: Optional[CorrectionGate] = None,
    encodings=None,
    bf16: bool = False,
):
    """The maps ``(for A, for B)`` of a correction method: :meth:`Correction.maps`."""
    return get_correction(correction).maps(image_a, image_b, H, local_model, global_model, gate, encodings, bf16)


def models_for_correction(
    correction: Union[str, Correction], local_weights=None, global_weights=None, device: str = "cpu"
):
    """``(local_model, global_model)`` that ``correction`` needs: :meth:`Correction.load_models`."""
    return get_correction(correction).load_models(local_weights, global_weights, device)
