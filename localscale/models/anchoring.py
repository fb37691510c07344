"""The anchored Local-ScaleNet pass: ScaleNet's global scale and quarter turn frame the local pass.

One Local-ScaleNet pass sees both images whole in its 192 px frame. It reads scales near 1 well,
but under a strong zoom the shared content fills a few cells of one image (the map saturates
near 3x) and under a quarter turn its map is wrong (about 0.4 instead of 1). ScaleNet's one
number, with its quarter turns, is robust there. The anchored pass (:func:`anchored_prediction`)

1. turns B upright relative to A by ScaleNet's quarter turns (a turn does not change scale);
2. runs the local pass on the whole pair, and, when ScaleNet's scale ``S`` is beyond
   ``2^window_log2``, on windows that bring the residual scale to about 1: windows of A with
   sides ``1/S`` of A's against all of B when ``S > 1`` (B is a close-up of part of A), windows of
   B with sides ``S`` of B's against all of A when ``S < 1``; the window pair with the best search
   score (:mod:`localscale.search`) that passes :func:`~localscale.models.windows.plausible` is kept (its
   map pasted into the whole pass's map over A's window);
3. blends the map toward ``S`` where the network does not trust it:
   ``log s = w log s_local + (1 - w) log S`` with ``w = r^2``, ``r`` the calibrated reliability
   (the entropy confidence for an uncalibrated model).

Window maps are in the pixels of the original images, so no rescaling is needed to compose them.
How the defaults were chosen: ``docs/decisions/anchored-local-maps.md``.

Example::

    net = LocalScaleNet.from_pretrained()
    pred = net.predict("a.jpg", "b.jpg")          # anchored (the default)
    pred.meta["anchor"]                           # ScaleNet's scale, turns, the window kept
    raw = net.predict("a.jpg", "b.jpg", anchor=False)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..geometry.planar import planarize
from .anchor import Anchor, turned
from .windows import (
    WindowSearchConfig,
    encode_window,
    encode_windows,
    grid_windows,
    pair_scores,
    paste_window,
    plausible,
)


@dataclass
class AnchorConfig:
    """Settings of :func:`anchored_prediction`."""

    #: windows are searched when ``|log2 S_global|`` is at least this
    window_log2: float = 1.0
    #: window pairs checked by :func:`~localscale.models.windows.plausible` (best scores first)
    checked: int = 4
    #: blend the map toward the global scale by the per-pixel reliability ``r``, with weight ``r^p``
    blend: bool = True
    #: the power ``p`` of that weight (higher: closer to the global scale where ``r < 1``)
    blend_power: float = 2.0
    #: B's quarter turn: ScaleNet's (``"global"``), or the one of the four whose whole-pair
    #: search score (:mod:`localscale.search`) is the highest (``"score"``, calibrated models)
    turns: str = "global"


def _window_choice(model, side, rgb, factor, shape, zoom, ea, eb, encode_side, bf16):
    """The best-scoring plausible window of one image (``side`` ``"a"`` or ``"b"``) at ``zoom``, or None."""
    windows = grid_windows(*shape, zoom)
    if not windows:
        return None
    cfg = WindowSearchConfig(zooms=(zoom,), sides=(side,))
    fw, lb = encode_windows(model, rgb, factor, windows, bf16, cfg.batch_size)
    scores = []
    for i in range(0, len(windows), cfg.batch_size):
        part = fw[i : i + cfg.batch_size]
        sc = (
            pair_scores(model, part, eb.features, lb, eb.letterbox, bf16)
            if side == "a"
            else pair_scores(model, ea.features, part, ea.letterbox, lb, bf16)
        )
        scores += sc.tolist()
    for j in np.argsort(scores)[::-1][: max(1, cfg.checked)]:
        ew = encode_side(windows[j])
        x, y = (ew, eb) if side == "a" else (ea, ew)
        fwd, bwd = model.predict_from_features(x, y, bf16=bf16), model.predict_from_features(y, x, bf16=bf16)
        if plausible(fwd, bwd, side, cfg):
            return windows[j], ew
    return None


def _best_turn(model, a, shape_a, b, shape_b, bf16) -> int:
    """The quarter turn of B (0..3) whose whole-pair search score is the highest."""
    fa = shape_a[0] / a.shape[0]
    ea = encode_window(model, a, fa, shape_a, None, "image A", bf16)
    best, turn = -1.0, 0
    for k in range(4):
        bk, sk = turned(b, shape_b, k)
        ek = encode_window(model, bk, sk[0] / bk.shape[0], sk, None, "image B", bf16)
        v = float(pair_scores(model, ea.features, ek.features, ea.letterbox, ek.letterbox, bf16)[0])
        if v > best:
            best, turn = v, k
    return turn


def _blend(pred, anchor_log: float, power: float) -> None:
    """Blend the map of ``pred`` toward ``exp(anchor_log)`` with the weight ``r^power``, ``r`` its
    reliability (or confidence): on the processing grid when the maps are still there (no
    full-resolution copy), else per pixel."""
    name = "reliability" if pred.has("reliability") else "confidence"
    if "scale" not in pred._full and name not in pred._full:
        grid = pred.maps.source  # channel 0: log scale; the weight channel in [0, 1] once clipped
        w = np.clip(grid[pred.channels.index(name)], 0, 1) ** power
        grid[0] = w * grid[0] + (1 - w) * anchor_log
        return
    w = pred.full(name) ** np.float32(power)
    log_s = np.log(pred.full("scale"))
    pred.set_map("scale", np.exp(w * log_s + (1 - w) * np.float32(anchor_log)).astype(np.float32))


@torch.inference_mode()
def anchored_prediction(
    model,
    a: np.ndarray,
    shape_a: tuple[int, int],
    b: np.ndarray,
    shape_b: tuple[int, int],
    anchor: Anchor,
    hard: bool = False,
    bf16: bool = False,
    planar: bool = False,
    cfg: AnchorConfig = AnchorConfig(),
):
    """``S_{A->B}`` of a Local-ScaleNet anchored on ``anchor`` (module docstring); ``a``, ``b``: the
    images as :meth:`~localscale.models.base.ScaleModel.load_pair` gives them, with their full sizes."""
    if cfg.turns == "score" and model.config.calibration:
        anchor = Anchor(anchor.scale, _best_turn(model, a, shape_a, b, shape_b, bf16), anchor.reliable)
    b, shape_b = turned(b, shape_b, anchor.turns)
    fa, fb = shape_a[0] / a.shape[0], shape_b[0] / b.shape[0]
    ea = encode_window(model, a, fa, shape_a, None, "image A", bf16)
    eb = encode_window(model, b, fb, shape_b, None, "image B", bf16)
    pred = model.predict_from_features(ea, eb, hard, bf16)
    log2_s = math.log2(anchor.scale)
    window = None
    if model.config.calibration and abs(log2_s) >= cfg.window_log2:
        side, rgb, factor, shape = ("a", a, fa, shape_a) if log2_s > 0 else ("b", b, fb, shape_b)

        def encode_side(win):
            return encode_window(model, rgb, factor, shape, win, f"image {side.upper()}", bf16)

        found = _window_choice(model, side, rgb, factor, shape, 2.0 ** -abs(log2_s), ea, eb, encode_side, bf16)
        if found is not None:
            window, ew = found
            inner = model.predict_from_features(ew, eb, hard, bf16) if side == "a" else None
            pred = paste_window(pred, inner, window) if side == "a" else model.predict_from_features(ea, ew, hard, bf16)
            window = (side, window)
    if cfg.blend:
        _blend(pred, math.log(anchor.scale), cfg.blend_power)
    if planar:
        pred.scale = planarize(pred.scale, pred.confidence, stride=max(1, round(8 / pred.letterbox_a.factor)))
    pred.meta["anchor"] = anchor.to_dict() | {
        "window": None if window is None else {"image": window[0].upper(), "box": list(window[1])}
    }
    return pred
