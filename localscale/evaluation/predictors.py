"""Named scale-map predictors for the map evaluations (sanity pairs, 3D collections).

A predictor turns a pair ``(A, B)`` into ``S_{A->B}`` on A: an ``H_A x W_A`` map, or one number for
the whole image (a global method). Each is a function of a :class:`PairContext`, which loads the
models once (:class:`ScaleModels`) and computes what several predictors share once per pair
(Local-ScaleNet's encodings and its two maps, ScaleNet's factor).

Built in (:data:`PREDICTORS`):

* ``local``: Local-ScaleNet's one-pass map (``LocalScaleNet.predict(anchor=False)``, soft read-out);
* ``anchored``: the map ``LocalScaleNet.predict`` and ``localscale predict`` give by default, the
  local pass anchored on ScaleNet's scale and quarter turn (:mod:`localscale.models.anchoring`);
* ``scalenet``: ScaleNet's consistency-checked factor, one number;
* ``one``: the constant 1 (the ``none`` correction);
* ``correction:NAME``: the map A gets from the correction method ``NAME`` of
  :mod:`localscale.matching.correction` (``global``, ``local``, ``fused``, ``searched``, ``gt``,
  ``gt_gated``); a gate that switches the correction off gives 1;
* ``refined``: the map ``localscale predict --refine`` writes: the anchored maps of A and B gated,
  hardnet matches verified as COLMAP's two-view geometry chooses (H, F or E), the map refined by the
  geometry (the homography's map, or the dense map of the verified matches), the anchored map where
  nothing verifies or matches are too sparse; OpenCV SIFT as the seed when the first pass fails;
* ``refined:MATCHER`` (``aliked-lightglue``, ``disk-lightglue``, ``xfeat-lightglue``): the map
  ``localscale predict --refine --matcher MATCHER`` writes (:func:`~localscale.matching.pipeline.refine_by_auto`):
  the geometry ``auto`` verifies with that matcher (its hypotheses find the window of a close-up and
  its quarter turn; H, F or E as COLMAP chooses), the map refined from it.

More can be added by name (:func:`register_predictor`), e.g. a system's own map from a function
``f(image_a, image_b, local_model=..., global_model=...)`` (:func:`function_predictor`,
:func:`load_function`).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Callable, Optional, Union

import numpy as np

from ..core.errors import LocalScaleError

Prediction = Union[float, np.ndarray]


@dataclass
class ScaleModels:
    """Local-ScaleNet and ScaleNet, loaded on first use (``*_weights`` None: the bundled ones)."""

    local_weights: Optional[str] = None
    global_weights: Optional[str] = None
    device: str = "cpu"
    _loaded: dict = field(default_factory=dict, repr=False)

    def get(self, kind: str):
        """The ``"local"`` or ``"global"`` model, loaded on the first call."""
        if kind not in self._loaded:
            from ..loading import load_scale_model

            weights = self.local_weights if kind == "local" else self.global_weights
            self._loaded[kind] = load_scale_model(kind, weights, self.device).eval()
        return self._loaded[kind]

    @property
    def local(self):
        return self.get("local")

    @property
    def global_(self):
        return self.get("global")

    def describe(self) -> dict:
        return {"local_weights": self.local_weights or "bundled", "global_weights": self.global_weights or "bundled"}


class PairContext:
    """One pair ``(A, B)`` (``H x W x 3`` uint8 arrays) and what its predictors share, computed once.

    ``H``: the true homography A -> B when there is one (oracle corrections need it).
    """

    def __init__(self, image_a: np.ndarray, image_b: np.ndarray, models: ScaleModels, H=None):
        self.a, self.b, self.models, self.H = image_a, image_b, models, H
        self._cache: dict = {}

    def _once(self, key, make):
        if key not in self._cache:
            self._cache[key] = make()
        return self._cache[key]

    def encodings(self):
        """Local-ScaleNet's encodings of A and B (a gray image makes the pair gray)."""
        return self._once("enc", lambda: self.models.local.encode_pair(self.a, self.b))

    def local_predictions(self):
        """Local-ScaleNet's predictions A->B and B->A from :meth:`encodings`."""

        def make():
            ea, eb = self.encodings()
            m = self.models.local
            return m.predict_from_features(ea, eb), m.predict_from_features(eb, ea)

        return self._once("local", make)

    def anchored_predictions(self):
        """``LocalScaleNet.predict``'s default (anchored) predictions A->B and B->A."""
        m = self.models.local
        return self._once("anchored", lambda: (m.predict(self.a, self.b), m.predict(self.b, self.a)))

    def global_scale(self) -> float:
        """ScaleNet's consistency-checked ``S_{A->B}``."""
        return self._once("global", lambda: float(self.models.global_.predict(self.a, self.b).scale))


Predictor = Callable[[PairContext], Optional[Prediction]]
PREDICTORS: dict[str, Predictor] = {}


def register_predictor(name: str, fn: Predictor) -> None:
    """Make ``fn(context) -> map, number or None (= 1)`` available as the predictor ``name``."""
    if not name or any(c.isspace() for c in name):
        raise LocalScaleError(f"predictor name must be a word, got {name!r}")
    PREDICTORS[name] = fn


def _correction(name: str) -> Predictor:
    def predict(ctx: PairContext):
        from ..matching.correction import get_correction

        c = get_correction(name)
        enc = ctx.encodings() if c.local_encodings else None
        local = ctx.models.local if "local" in c.models else None
        glob = ctx.models.global_ if "global" in c.models else None
        return c.maps(ctx.a, ctx.b, ctx.H, local, glob, encodings=enc)[0]

    return predict


def _refined(ctx: PairContext) -> np.ndarray:
    from ..matching.pipeline import refine_predictions
    from ..matching.verification import VerificationConfig

    pa, pb = ctx.anchored_predictions()
    res = refine_predictions(ctx.a, ctx.b, pa, pb, sift_seed=True, verification=VerificationConfig(model="two_view"))
    return res.refined_a.scale


def _refined_auto(matcher: str) -> Predictor:
    def predict(ctx: PairContext) -> np.ndarray:
        from ..matching.pipeline import refine_by_auto

        return refine_by_auto(ctx.a, ctx.b, matcher, ctx.models.local, ctx.models.global_).refined_a.scale

    return predict


register_predictor("local", lambda ctx: ctx.local_predictions()[0].scale)
register_predictor("anchored", lambda ctx: ctx.anchored_predictions()[0].scale)
register_predictor("scalenet", lambda ctx: ctx.global_scale())
register_predictor("one", lambda ctx: 1.0)
for _name in ("global", "local", "fused", "searched", "gt", "gt_gated"):
    register_predictor(f"correction:{_name}", _correction(_name))
register_predictor("refined", _refined)
for _name in ("aliked-lightglue", "disk-lightglue", "xfeat-lightglue"):
    register_predictor(f"refined:{_name}", _refined_auto(_name))


def function_predictor(fn: Callable) -> Predictor:
    """A predictor from ``fn(image_a, image_b, local_model=..., global_model=...)`` returning a map, a
    number, or an object with a ``scale`` attribute (e.g. a ``LocalScalePrediction``)."""

    def predict(ctx: PairContext):
        out = fn(ctx.a, ctx.b, local_model=ctx.models.local, global_model=ctx.models.global_)
        return getattr(out, "scale", out)

    return predict


def load_function(spec: str) -> Callable:
    """The callable ``MODULE:NAME`` names (e.g. ``mypackage.maps:system_map``)."""
    module, _, name = spec.partition(":")
    if not module or not name:
        raise LocalScaleError(f"--system {spec!r}: give MODULE:FUNCTION")
    try:
        fn = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as e:
        raise LocalScaleError(f"--system {spec!r}: cannot load it ({e})") from None
    if not callable(fn):
        raise LocalScaleError(f"--system {spec!r}: not a function")
    return fn


def check_predictors(names) -> list[str]:
    """``names`` as a list, each a known predictor (:class:`LocalScaleError` otherwise)."""
    unknown = [n for n in names if n not in PREDICTORS]
    if unknown:
        raise LocalScaleError(f"unknown predictor(s) {', '.join(unknown)}; known: {', '.join(PREDICTORS)}")
    if not names:
        raise LocalScaleError("no predictor to evaluate")
    return list(names)


def predict(name: str, ctx: PairContext) -> Prediction:
    """Predictor ``name`` on a pair: an ``H_A x W_A`` float map or a positive number (None -> 1)."""
    out = PREDICTORS[name](ctx)
    if out is None:
        return 1.0
    if np.isscalar(out) or np.ndim(out) == 0:
        return float(out)
    out = np.asarray(out, np.float32)
    if out.shape != ctx.a.shape[:2]:
        raise LocalScaleError(f"predictor {name}: map of shape {out.shape}, image A is {ctx.a.shape[:2]}")
    return out


def prepare(
    names,
    system: Optional[str] = None,
    local_weights: Optional[str] = None,
    global_weights: Optional[str] = None,
    device: str = "cpu",
) -> tuple[ScaleModels, list[str]]:
    """The models and the checked predictor list of an evaluation, before any work: ``system``
    (``MODULE:FUNCTION``, :func:`load_function`) is registered as the predictor ``system`` and
    added to the list; given weights are loaded now, so a bad checkpoint stops the run at once."""
    names = list(names)
    if system is not None:
        register_predictor("system", function_predictor(load_function(system)))
        if "system" not in names:
            names.append("system")
    names = check_predictors(names)
    models = ScaleModels(local_weights, global_weights, device)
    for kind, weights in (("local", local_weights), ("global", global_weights)):
        if weights is not None:
            models.get(kind)
    return models, names
