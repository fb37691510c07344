"""Window search: re-estimate the scale map on the part of each image the two views share.

One Local-ScaleNet pass sees both images whole at 192 px. Under a strong zoom the shared content
covers a few cells of one of them (a 6x zoom-out puts all of A in 1/36 of B), and under low
overlap most cells of both are unrelated; the map is then poor, although the same network is
accurate once the shared part fills both inputs. The search tries windows of one image against
the whole other image (in the spirit of MODS' adaptive synthetic views) and scores each pair:

    score = mean calibrated reliability over A's side x sum of the similarities of the mutual
            nearest neighbours between the two feature grids

(the first says how sure the network is, the second how much content the two inputs share).
The best-scoring pairs that beat the whole images are then checked (:func:`plausible`): the
two directions must roughly agree (within 4x), and a window of B must be filled by A's content
as the maps predict it (A's visible pixels, each covering ``S^2`` pixels of B, at least 10 % of
the window). A window that scores well but fails is the network confidently reading unrelated
content as a tiny copy of A, the failure that matters on real low-overlap pairs. The first
pair that passes is kept.
Windows have sides ``z`` of the image's for each ``z`` in :attr:`WindowSearchConfig.zooms`, on a
grid with half-window overlap; each candidate costs one encoding and one head pass (about 120
candidates with the default zooms). The scale units stay those of the original images, so the
map of a window needs no rescaling; where A is searched, pixels of A outside the chosen window
keep the first pass's values.

Example::

    local_model = LocalScaleNet.from_pretrained()
    res = search_scale_map(local_model, "wide.jpg", "zoomed.jpg")
    print(res.window_a, res.window_b, res.score)
    s = res.prediction.scale          # H_A x W_A, S_{A->B}
    g, _ = search_global_scale(local_model, ScaleNet.from_pretrained(), "wide.jpg", "zoomed.jpg")
    g.scale                           # ScaleNet's S_{A->B} on the kept windows
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from .core.errors import LocalScaleError
from .io import ImageLike
from .models.local import LocalScaleNet, LocalScalePrediction
from .models.windows import (
    Window,
    WindowSearchConfig,
    encode_window,
    encode_windows,
    grid_windows,
    pair_scores,
    paste_window,
    plausible,
    unturn_window,
)


@dataclass
class WindowSearchResult:
    """Outcome of :func:`search_scale_map`.

    Attributes:
        prediction: ``S_{A->B}`` over all of A: the chosen pair's map inside ``window_a`` and the
            first pass's map outside it (``visible`` and ``reliability`` likewise; where B was
            windowed they refer to ``window_b``).
        window_a, window_b: the chosen windows (None: the whole image).
        score: the chosen pair's score; ``base_score`` that of the whole images.
        base: the first pass (whole A against whole B).
        candidates: pairs scored.
        quarter_turns_b: B was searched turned by this many quarter turns counter-clockwise
            (``np.rot90(B, k)``); ``window_b`` is given in the pixels of B as it was passed.
    """

    prediction: LocalScalePrediction
    window_a: Window | None
    window_b: Window | None
    score: float
    base_score: float
    base: LocalScalePrediction
    candidates: int = 0
    quarter_turns_b: int = 0
    scores: list[tuple[str, Window | None, float]] = field(default_factory=list, repr=False)

    def kept(self) -> str:
        """What the search kept, in words: the windows (``x0, y0, x1, y1``) or the whole images."""
        where = [f"{n} window {w}" for n, w in (("A", self.window_a), ("B", self.window_b)) if w is not None]
        return ", ".join(where) or "the whole images"


def _window_candidates(model, a, fa, shape_a, ea, views, cfg, bf16, scores, floor) -> list:
    """``(score, side, window, turns)`` of the window pairs scoring above ``floor``: windows of A
    (encoded once) against each view of B, and windows of each view of B against all of A; every
    score is appended to ``scores``."""
    candidates = []
    for zoom in cfg.zooms:
        wins_a = grid_windows(*shape_a, zoom) if "a" in cfg.sides else []
        fw_a, lb_a = encode_windows(model, a, fa, wins_a, bf16, cfg.batch_size) if wins_a else (None, None)
        for k, bk, shape_k, ek, _ in views:
            label = "" if k == 0 else f", B turned {90 * k} deg"
            fb = shape_k[0] / bk.shape[0]
            wins_b = grid_windows(*shape_k, zoom) if "b" in cfg.sides else []
            fw_b, lb_b = encode_windows(model, bk, fb, wins_b, bf16, cfg.batch_size) if wins_b else (None, None)
            for side, wins in (("a", wins_a), ("b", wins_b)):
                for i in range(0, len(wins), cfg.batch_size):
                    sc = (
                        pair_scores(model, fw_a[i : i + cfg.batch_size], ek.features, lb_a, ek.letterbox, bf16)
                        if side == "a"
                        else pair_scores(model, ea.features, fw_b[i : i + cfg.batch_size], ea.letterbox, lb_b, bf16)
                    )
                    for win, v in zip(wins[i : i + cfg.batch_size], sc.tolist()):
                        scores.append((side + label, win, v))
                        if v > floor:
                            candidates.append((v, side, win, k))
    return candidates


@torch.inference_mode()
def search_scale_map(
    model: LocalScaleNet,
    image_a: ImageLike,
    image_b: ImageLike,
    cfg: WindowSearchConfig = WindowSearchConfig(),
    bf16: bool = False,
) -> WindowSearchResult:
    """Per-pixel ``S_{A->B}`` from the best-scoring window pair (see the module docstring).

    Needs a calibrated Local-ScaleNet (``pred.reliability``). A window pair replaces the whole
    pair only when it scores higher; on pairs the first pass already frames well, the result is
    the first pass.
    """
    if not model.config.calibration:
        raise LocalScaleError(
            "the window search needs a calibrated Local-ScaleNet (this checkpoint has no calibration)"
        )
    (a, shape_a), (b, shape_b) = model.load_pair(image_a, image_b)
    fa, fb = shape_a[0] / a.shape[0], shape_b[0] / b.shape[0]

    def encode_a(win=None):
        return encode_window(model, a, fa, shape_a, win, "image A", bf16)

    def encode_b(win=None):
        return encode_window(model, b, fb, shape_b, win, "image B", bf16)

    def score(x, y, lb_x, lb_y):
        return pair_scores(model, x, y, lb_x, lb_y, bf16)

    ea, eb = encode_a(), encode_b()
    base = model.predict_from_features(ea, eb, bf16=bf16)
    base_score = float(score(ea.features, eb.features, ea.letterbox, eb.letterbox)[0])
    scores: list[tuple[str, Window | None, float]] = [("whole", None, base_score)]
    # B as it is and turned by each quarter turn asked for: (turns, B turned, its shape, its encoding, score)
    views = [(0, b, shape_b, eb, base_score)]
    for k in cfg.quarter_turns:
        ek = encode_window(model, b, fb, shape_b, None, "image B", bf16, k)
        v = float(score(ea.features, ek.features, ea.letterbox, ek.letterbox)[0])
        scores.append((f"whole, B turned {90 * k} deg", None, v))
        views.append((k, np.ascontiguousarray(np.rot90(b, k)), shape_b if k % 2 == 0 else shape_b[::-1], ek, v))
    whole = max(views, key=lambda view: view[4])  # the first of equal scores: B as it is
    candidates = _window_candidates(model, a, fa, shape_a, ea, views, cfg, bf16, scores, whole[4])
    chosen, win_a, win_b = whole, None, None
    for v, side, win, k in sorted(candidates, key=lambda c: -c[0])[: cfg.checked]:
        view = next(x for x in views if x[0] == k)
        ew = encode_a(win) if side == "a" else ea
        eo = encode_window(model, view[1], fb, view[2], win, "image B", bf16) if side == "b" else view[3]
        fwd, bwd = model.predict_from_features(ew, eo, bf16=bf16), model.predict_from_features(eo, ew, bf16=bf16)
        if plausible(fwd, bwd, side, cfg):
            chosen = view[:4] + (v,)
            win_a, win_b = (win, None) if side == "a" else (None, win)
            break
    turns, bk, shape_k, ek, best_score = chosen
    if win_a is None and win_b is None:
        pred = base if not turns else model.predict_from_features(ea, ek, bf16=bf16)
    else:
        ew = encode_a(win_a) if win_a is not None else ea
        eo = encode_window(model, bk, fb, shape_k, win_b, "image B", bf16) if win_b is not None else ek
        pred = model.predict_from_features(ew, eo, bf16=bf16)
        if win_a is not None:
            pred = paste_window(model.predict_from_features(ea, ek, bf16=bf16), pred, win_a)
    if win_b is not None and turns:
        win_b = unturn_window(win_b, shape_k, turns)
    if win_b is not None:
        pred.meta["window_b"] = win_b
    pred.meta["quarter_turns_b"] = turns
    return WindowSearchResult(pred, win_a, win_b, best_score, base_score, base, len(scores), turns, scores)


@torch.inference_mode()
def search_global_scale(
    local_model: LocalScaleNet,
    global_model,
    image_a: ImageLike,
    image_b: ImageLike,
    cfg: WindowSearchConfig = WindowSearchConfig(),
    bf16: bool = False,
):
    """ScaleNet's global ``S_{A->B}`` on the window pair :func:`search_scale_map` keeps.

    Returns ``(GlobalScalePrediction, WindowSearchResult)``. With no window kept, this is the
    upright ``global_model.predict(A, B, turns=False)`` (B turned as the search kept it). The windows are cut from the original images; the scale is
    in their pixels, which are the images' own.
    """
    res = search_scale_map(local_model, image_a, image_b, cfg, bf16)
    (a, shape_a), (b, shape_b) = global_model.load_pair(image_a, image_b)
    ea = encode_window(global_model, a, shape_a[0] / a.shape[0], shape_a, res.window_a, "image A", bf16)
    eb = encode_window(
        global_model, b, shape_b[0] / b.shape[0], shape_b, res.window_b, "image B", bf16, res.quarter_turns_b
    )
    return global_model.predict_from_features(ea, eb, bf16), res
