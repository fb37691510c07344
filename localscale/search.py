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
import torch.nn.functional as F

from .errors import LocalScaleError
from .io import ImageLike
from .models.local import LocalScaleNet, LocalScalePrediction, reliability
from .preprocess import Letterbox, letterbox, to_tensor
from .reliability import pair_statistics

#: ``(x0, y0, x1, y1)`` in the pixels of the original image, end exclusive
Window = tuple[int, int, int, int]


@dataclass
class WindowSearchConfig:
    """Window sizes of the search, as fractions of each image's sides (half-window overlap)."""

    zooms: tuple[float, ...] = (0.5, 0.25)
    #: search windows of A (zooms into B), of B (zooms out of B), or both
    sides: tuple[str, ...] = ("a", "b")
    #: quarter turns of B (counter-clockwise) tried on the whole images before the windows; the
    #: best-scoring turn is kept for the window search (the scale map does not depend on it)
    quarter_turns: tuple[int, ...] = ()
    #: candidates per network pass
    batch_size: int = 8
    #: the best-scoring window pairs (at most this many, in order) are checked by
    #: :func:`plausible`; the first that passes is kept, the whole images when none does
    checked: int = 8
    #: a kept pair's two directions agree within this (median log2 S_AB + median log2 S_BA)
    max_inconsistency_log2: float = 2.0
    #: a kept window of B is filled at least this much by A's visible content (its predicted area)
    min_cover: float = 0.1

    def __post_init__(self):
        if not self.zooms or any(not 0 < z < 1 for z in self.zooms):
            raise ValueError(f"zooms must be fractions in (0, 1), got {self.zooms}")
        if any(k not in (1, 2, 3) for k in self.quarter_turns):
            raise ValueError(f"quarter_turns must be among 1, 2, 3, got {self.quarter_turns}")
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {self.batch_size}")
        if self.checked < 0:
            raise ValueError(f"checked must be >= 0, got {self.checked}")
        if self.min_cover < 0 or self.max_inconsistency_log2 <= 0:
            raise ValueError(
                f"min_cover must be >= 0 and max_inconsistency_log2 > 0, "
                f"got {self.min_cover}, {self.max_inconsistency_log2}"
            )
        if not self.sides or set(self.sides) - {"a", "b"}:
            raise ValueError(f"sides must be a non-empty subset of ('a', 'b'), got {self.sides}")


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


def grid_windows(height: int, width: int, zoom: float, min_side: int = 16) -> list[Window]:
    """Windows with sides ``zoom`` of the image's, on a regular grid with half-window overlap,
    covering the image (``round(2 / zoom) - 1`` positions per axis); none when a side would be
    shorter than ``min_side`` pixels."""
    wh, ww = round(height * zoom), round(width * zoom)
    if min(wh, ww) < min_side or wh >= height or ww >= width:
        return []
    n = max(1, round(2 / zoom) - 1)
    ys = np.linspace(0, height - wh, n).round().astype(int)
    xs = np.linspace(0, width - ww, n).round().astype(int)
    return [(int(x), int(y), int(x) + ww, int(y) + wh) for y in ys for x in xs]


def unturn_window(win: Window, turned_shape: tuple[int, int], turns: int) -> Window:
    """A window given in ``np.rot90(image, turns)`` (of shape ``turned_shape``) in the pixels of ``image``."""
    for _ in range(turns % 4):
        # np.rot90(img, 1)[i, j] == img[j, W - 1 - i], W (img's width) being the turned height
        h, w = turned_shape
        x0, y0, x1, y1 = win
        win, turned_shape = (h - y1, x0, h - y0, x1), (w, h)
    return win


def _inside_cells(lb, grid: int) -> torch.Tensor:
    """Flat mask of the ``grid x grid`` cells whose centre lies on the image, not on the letterbox padding."""
    c = (torch.arange(grid) + 0.5) * (lb.size / grid)
    rows = (c >= lb.top) & (c < lb.top + lb.new_height)
    cols = (c >= lb.left) & (c < lb.left + lb.new_width)
    return (rows[:, None] & cols[None]).flatten()


def mutual_similarity(fa: torch.Tensor, fb: torch.Tensor, cells_a: torch.Tensor, cells_b: torch.Tensor) -> torch.Tensor:
    """Sum of the cosine similarities of the mutual nearest neighbours between feature grids.

    ``fa``, ``fb``: ``B x D x h x w``; ``cells_a``, ``cells_b``: flat masks of the cells to use
    (the image's, not the padding's). Returns ``B`` sums."""
    a = F.normalize(fa.flatten(2)[:, :, cells_a].float(), dim=1)
    b = F.normalize(fb.flatten(2)[:, :, cells_b].float(), dim=1)
    sim = a.transpose(1, 2) @ b  # B x Na x Nb
    best_sim, best_b = sim.max(2)
    best_a = sim.argmax(1)  # B x Nb
    mutual = torch.gather(best_a, 1, best_b) == torch.arange(sim.shape[1], device=sim.device)
    return (best_sim.clamp_min(0) * mutual).sum(1)


def _scores(model: LocalScaleNet, fa: torch.Tensor, fb: torch.Tensor, lb_a, lb_b, bf16: bool) -> torch.Tensor:
    """Scores of ``B`` pairs of encodings (``fa`` or ``fb`` may have batch 1 and is expanded)."""
    n = max(fa.shape[0], fb.shape[0])
    with torch.autocast(model.device.type, dtype=torch.bfloat16, enabled=bf16):
        terms = model.self_terms(fa)  # once for a single A against many B
        terms = tuple(None if t is None else t.expand(n, -1, -1, -1) for t in terms)
        fa, fb = fa.expand(n, -1, -1, -1), fb.expand(n, -1, -1, -1)
        logits, vis = model.forward_features_all(fa, fb, terms)
    probs = F.softmax(logits.float(), 1)
    visible = torch.sigmoid(vis.float())[:, 0] if vis is not None else None
    g = fa.shape[-1]
    cells_a, cells_b = _inside_cells(lb_a, g).to(fa.device), _inside_cells(lb_b, g).to(fa.device)
    rel = reliability(probs, visible, model.config.calibration, 1).flatten(1)[:, cells_a].mean(1)
    return (rel * mutual_similarity(fa, fb, cells_a, cells_b)).cpu()


def _crop(rgb: np.ndarray, win: Window, factor: float) -> np.ndarray:
    """Crop of a (possibly reduced) image by a window in original pixels."""
    x0, y0, x1, y1 = (int(round(v / factor)) for v in win)
    return np.ascontiguousarray(rgb[y0 : max(y1, y0 + 1), x0 : max(x1, x0 + 1)])


def _encode(
    model,
    rgb: np.ndarray,
    factor: float,
    full_shape: tuple[int, int],
    win: Window | None,
    name: str,
    bf16: bool,
    turns: int = 0,
):
    """Encoding of a (possibly reduced, by ``factor``) image or of one window of it, turned by
    ``turns`` quarter turns; scales stay in the pixels of the full image (``full_shape``)."""
    crop, size = (rgb, full_shape) if win is None else (_crop(rgb, win, factor), (win[3] - win[1], win[2] - win[0]))
    return model.encode_image(crop, name, bf16, size, turns)


def _encode_windows(
    model: LocalScaleNet, rgb: np.ndarray, factor: float, windows: list[Window], bf16: bool, batch: int
) -> tuple[torch.Tensor, Letterbox]:
    """Encodings ``N x D x h x w`` of the windows of one image (all of one size, so one placement)."""
    feats, lb = [], None
    for i in range(0, len(windows), batch):
        xs = []
        for win in windows[i : i + batch]:
            boxed, lb = letterbox(_crop(rgb, win, factor), model.config.image_size, (win[3] - win[1], win[2] - win[0]))
            xs.append(to_tensor(boxed))
        with torch.autocast(model.device.type, dtype=torch.bfloat16, enabled=bf16):
            feats.append(model.encode(torch.stack(xs).to(model.device)).float())
    return torch.cat(feats), lb


def plausible(fwd: LocalScalePrediction, bwd: LocalScalePrediction, side: str, cfg: WindowSearchConfig) -> bool:
    """Whether a window pair's maps are believable: ``fwd`` (A side -> B side) and ``bwd`` agree
    within ``cfg.max_inconsistency_log2``; for a window of B (``side == "b"``), A's visible
    content covers at least ``cfg.min_cover`` of it."""
    if pair_statistics(fwd, bwd)["inconsistency_log2"] >= cfg.max_inconsistency_log2:
        return False
    if side == "b":
        scale = fwd.sampled("scale")
        vis = fwd.sampled("visible") if fwd.has("visible") else np.ones_like(scale)
        lb_a, lb_b = fwd.letterbox_a, fwd.letterbox_b
        cover = float((vis * scale.astype(np.float64) ** 2).mean()) * lb_a.height * lb_a.width
        return cover >= cfg.min_cover * lb_b.height * lb_b.width
    return True


def _compose(base: LocalScalePrediction, inner: LocalScalePrediction, win: Window | None) -> LocalScalePrediction:
    """``inner``'s maps pasted into ``base``'s at ``win`` (``inner`` itself when ``win`` is None)."""
    if win is None:
        return inner
    x0, y0, x1, y1 = win
    for name in inner.channels:
        full = base.full(name).copy()
        full[y0:y1, x0:x1] = inner.full(name)
        base.set_map(name, full)
    base.meta["window_a"] = win
    return base


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
        return _encode(model, a, fa, shape_a, win, "image A", bf16)

    def encode_b(win=None):
        return _encode(model, b, fb, shape_b, win, "image B", bf16)

    ea, eb = encode_a(), encode_b()
    base = model.predict_from_features(ea, eb, bf16=bf16)
    base_score = float(_scores(model, ea.features, eb.features, ea.letterbox, eb.letterbox, bf16)[0])
    scores: list[tuple[str, Window | None, float]] = [("whole", None, base_score)]
    turns, turn_score = 0, base_score
    for k in cfg.quarter_turns:
        ek = _encode(model, b, fb, shape_b, None, "image B", bf16, k)
        v = float(_scores(model, ea.features, ek.features, ea.letterbox, ek.letterbox, bf16)[0])
        scores.append((f"whole, B turned {90 * k} deg", None, v))
        if v > turn_score:
            turns, turn_score, eb = k, v, ek
    if turns:
        b, shape_b = np.ascontiguousarray(np.rot90(b, turns)), (shape_b if turns % 2 == 0 else shape_b[::-1])
    candidates: list[tuple[float, str, Window]] = []
    for zoom in cfg.zooms:
        for side, rgb, shape, factor in (("a", a, shape_a, fa), ("b", b, shape_b, fb)):
            windows = grid_windows(*shape, zoom) if side in cfg.sides else []
            if not windows:
                continue
            fw, lb = _encode_windows(model, rgb, factor, windows, bf16, cfg.batch_size)
            for i in range(0, len(windows), cfg.batch_size):
                part = fw[i : i + cfg.batch_size]
                sc = (
                    _scores(model, part, eb.features, lb, eb.letterbox, bf16)
                    if side == "a"
                    else _scores(model, ea.features, part, ea.letterbox, lb, bf16)
                )
                for win, v in zip(windows[i : i + cfg.batch_size], sc.tolist()):
                    scores.append((side, win, v))
                    if v > turn_score:
                        candidates.append((v, side, win))
    best = (turn_score, None, None)
    for v, side, win in sorted(candidates, key=lambda c: -c[0])[: cfg.checked]:
        ew = encode_a(win) if side == "a" else ea
        eo = encode_b(win) if side == "b" else eb
        fwd, bwd = model.predict_from_features(ew, eo, bf16=bf16), model.predict_from_features(eo, ew, bf16=bf16)
        if plausible(fwd, bwd, side, cfg):
            best = (v, win, None) if side == "a" else (v, None, win)
            break
    score, win_a, win_b = best
    if win_a is None and win_b is None:
        pred = base if not turns else model.predict_from_features(ea, eb, bf16=bf16)
    else:
        ew = encode_a(win_a) if win_a is not None else ea
        eo = encode_b(win_b) if win_b is not None else eb
        pred = model.predict_from_features(ew, eo, bf16=bf16)
        if win_a is not None:
            pred = _compose(model.predict_from_features(ea, eb, bf16=bf16), pred, win_a)
    if win_b is not None and turns:
        win_b = unturn_window(win_b, shape_b, turns)
    if win_b is not None:
        pred.meta["window_b"] = win_b
    pred.meta["quarter_turns_b"] = turns
    return WindowSearchResult(pred, win_a, win_b, score, base_score, base, len(scores), turns, scores)


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
    ea = _encode(global_model, a, shape_a[0] / a.shape[0], shape_a, res.window_a, "image A", bf16)
    eb = _encode(global_model, b, shape_b[0] / b.shape[0], shape_b, res.window_b, "image B", bf16, res.quarter_turns_b)
    return global_model.predict_from_features(ea, eb, bf16), res
