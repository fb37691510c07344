"""How far to trust a predicted scale map: per-pixel calibration and a pair-level check.

Per pixel, a Local-ScaleNet with a ``calibration`` in its config returns
``pred.reliability``: the calibrated probability that the pixel is visible in B *and* its
scale is within a factor 1.25 of the truth (logistic regression on the entropy confidence,
the visibility probability and the spread of the distribution, fitted on held-out synthetic
pairs by :func:`fit_calibration`).

Per pair, :func:`check_pair` predicts both directions and combines

* **consistency**: the median ``log2`` scale of A->B over A's visible part should be minus
  that of B->A over B's visible part (a scale map and its inverse),
* **overlap**: the share of A predicted visible in B,
* **reliability**: the mean calibrated reliability over A's visible part,
* **limits**: an image too thin or too small for the network, a median scale outside its
  bins' range (:func:`localscale.model_limits.limit_reasons`),

into one ``reliable`` flag with the reasons when it fires. Thresholds live in
:class:`PairCheckConfig`.

Example::

    check = check_pair(LocalScaleNet.from_pretrained(), "a.jpg", "b.jpg")
    if not check.reliable:
        print("do not trust this map:", "; ".join(check.reasons))
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from .core.errors import LocalScaleError
from .io import ImageLike
from .model_limits import limit_reasons


@dataclass
class PairCheckConfig:
    """Thresholds of the pair-level flag (chosen on held-out synthetic pairs)."""

    max_inconsistency_log2: float = 1.0  #: |median log2 S_AB + median log2 S_BA| above this fires (x2)
    min_visible_fraction: float = 0.05  #: less of A predicted visible in B fires
    min_reliability: float = 0.2  #: lower mean reliability over A's visible part fires
    visible_threshold: float = 0.5  #: a pixel counts as visible above this probability


@dataclass
class PairCheck:
    """Result of :func:`check_pair`.

    Attributes:
        forward, backward: the ``A->B`` and ``B->A`` predictions.
        inconsistency_log2: ``|median log2 S_AB + median log2 S_BA|`` over the visible parts.
        visible_fraction: share of A's pixels predicted visible in B.
        mean_reliability: mean calibrated reliability over A's visible part (NaN if uncalibrated).
        reliable: False when any threshold of the config fires; ``reasons`` says which.
    """

    forward: object
    backward: object
    inconsistency_log2: float
    visible_fraction: float
    mean_reliability: float
    reliable: bool
    reasons: list[str] = field(default_factory=list)


def _map(pred, name: str):
    """A map of a prediction, on a stride that keeps it under a few megapixels (the statistics of
    a pair do not need more, and a huge image's full maps are never made whole for them)."""
    if hasattr(pred, "sampled"):
        return pred.sampled(name) if pred.has(name) else None
    return getattr(pred, name, None)


def _visible(pred, threshold: float) -> np.ndarray:
    vis = _map(pred, "visible")
    if vis is None:
        return np.ones(_map(pred, "scale").shape, bool)
    return vis > threshold


def pair_statistics(forward, backward, cfg: PairCheckConfig = PairCheckConfig()) -> dict:
    """The three pair-level numbers of :class:`PairCheck` from two predictions (maps of images
    above 4 MP are read on a stride)."""
    va, vb = _visible(forward, cfg.visible_threshold), _visible(backward, cfg.visible_threshold)
    visible_fraction = float(va.mean())

    def med(p, m):
        s = _map(p, "scale")
        return float(np.median(np.log2(s[m]))) if m.any() else float(np.median(np.log2(s)))

    inconsistency = abs(med(forward, va) + med(backward, vb))
    rel = _map(forward, "reliability")
    if rel is None:
        mean_rel = float("nan")
    else:
        mean_rel = float(rel[va].mean()) if va.any() else 0.0
    return {"inconsistency_log2": inconsistency, "visible_fraction": visible_fraction, "mean_reliability": mean_rel}


def flag_reasons(stats: dict, cfg: PairCheckConfig = PairCheckConfig()) -> list[str]:
    """Why a pair is not reliable (empty: reliable)."""
    reasons = []
    if stats["inconsistency_log2"] > cfg.max_inconsistency_log2:
        reasons.append(f"A->B and B->A disagree by x{2 ** stats['inconsistency_log2']:.2f}")
    if stats["visible_fraction"] < cfg.min_visible_fraction:
        reasons.append(f"only {100 * stats['visible_fraction']:.0f}% of A is predicted visible in B")
    if math.isfinite(stats["mean_reliability"]) and stats["mean_reliability"] < cfg.min_reliability:
        reasons.append(f"low reliability ({stats['mean_reliability']:.2f})")
    return reasons


def check_pair(
    model,
    image_a: ImageLike,
    image_b: ImageLike,
    cfg: PairCheckConfig = PairCheckConfig(),
    bf16: bool = False,
    **readout,
) -> PairCheck:
    """Predict ``A->B`` and ``B->A`` with a Local-ScaleNet and decide whether to trust the pair.

    ``readout``: options of :meth:`LocalScaleNet.predict_from_features` for the forward map
    (``hard``, ``planar``); the backward map, used only for the check, is the soft one.

    Raises :class:`LocalScaleError` when ``model`` is not a :class:`LocalScaleNet` (the global
    ScaleNet predicts no map to check)."""
    if getattr(model, "arch", None) != "LocalScaleNet":
        raise LocalScaleError(
            f"check_pair needs a LocalScaleNet (a per-pixel scale map model), got {type(model).__name__}"
        )
    ea, eb = model.encode_pair(image_a, image_b, bf16)
    fwd = model.predict_from_features(ea, eb, bf16=bf16, **readout)
    bwd = model.predict_from_features(eb, ea, bf16=bf16)
    stats = pair_statistics(fwd, bwd, cfg)
    median = float(np.median(_map(fwd, "scale")))
    reasons = flag_reasons(stats, cfg) + limit_reasons(ea.letterbox, eb.letterbox, median, "the median scale")
    return PairCheck(fwd, bwd, reliable=not reasons, reasons=reasons, **stats)


def fit_calibration(features: np.ndarray, labels: np.ndarray, iters: int = 200, l2: float = 1e-4) -> tuple[float, ...]:
    """Logistic regression ``P(label) = sigmoid(b + w . f)``; ``features``: ``N x K``, ``labels``: ``N`` in {0, 1}.

    Returns ``(b, w_1, ..., w_K)``, the format of ``LocalScaleNetConfig.calibration``.
    """
    x = torch.as_tensor(np.asarray(features), dtype=torch.float64)
    y = torch.as_tensor(np.asarray(labels), dtype=torch.float64)
    if x.ndim != 2 or len(x) != len(y) or len(x) == 0:
        raise ValueError(
            f"fit_calibration: need N x K features and N labels, got {tuple(x.shape)} and {tuple(y.shape)}"
        )
    w = torch.zeros(x.shape[1] + 1, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS([w], max_iter=iters, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        z = w[0] + x @ w[1:]
        loss = torch.nn.functional.binary_cross_entropy_with_logits(z, y) + l2 * (w[1:] ** 2).sum()
        loss.backward()
        return loss

    opt.step(closure)
    return tuple(float(v) for v in w.detach())


def auroc(scores: np.ndarray, positives: np.ndarray) -> float:
    """Area under the ROC curve of ``scores`` for separating ``positives`` (bool) from the rest."""
    scores = np.asarray(scores, np.float64)
    positives = np.asarray(positives, bool)
    n_pos, n_neg = int(positives.sum()), int((~positives).sum())
    if not n_pos or not n_neg:
        return float("nan")
    _, inverse, counts = np.unique(scores, return_inverse=True, return_counts=True)
    ranks = (np.cumsum(counts) - (counts - 1) / 2.0)[inverse]  # average rank of ties, from 1
    return float((ranks[positives].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))
