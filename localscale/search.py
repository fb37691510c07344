"""Window search: re-estimate the scale map on the part of each image the two views share.

One Local-ScaleNet pass sees both images whole at 192 px. Under a strong zoom the shared content
covers a few cells of one of them (a 6x zoom-out puts all of A in 1/36 of B), and under low
overlap most cells of both are unrelated; the map is then poor, although the same network is
accurate once the shared part fills both inputs. The search tries windows of one image against
the whole other image (in the spirit of MODS' adaptive synthetic views), and keeps the pair that
scores best:

    score = mean calibrated reliability over A's side x sum of the similarities of the mutual
            nearest neighbours between the two feature grids

(the first says how sure the network is, the second how much content the two inputs share).
Windows have sides ``z`` of the image's for each ``z`` in :attr:`WindowSearchConfig.zooms`, on a
grid with half-window overlap; each candidate costs one encoding and one head pass (about 120
candidates with the default zooms). The scale units stay those of the original images, so the
map of a window needs no rescaling; where A is searched, pixels of A outside the chosen window
keep the first pass's values.

Example::

    res = search_scale_map(LocalScaleNet.from_pretrained(), "wide.jpg", "zoomed.jpg")
    print(res.window_a, res.window_b, res.score)
    s = res.prediction.scale          # H_A x W_A, S_{A->B}
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from .io import ImageLike
from .models.base import is_gray, to_gray3
from .models.local import LocalScaleNet, LocalScalePrediction, reliability
from .preprocess import Letterbox, letterbox, to_tensor

#: ``(x0, y0, x1, y1)`` in the pixels of the original image, end exclusive
Window = tuple[int, int, int, int]


@dataclass
class WindowSearchConfig:
    """Window sizes of the search, as fractions of each image's sides (half-window overlap)."""

    zooms: tuple[float, ...] = (0.5, 0.25)
    #: search windows of A (zooms into B), of B (zooms out of B), or both
    sides: tuple[str, ...] = ("a", "b")
    #: candidates per network pass
    batch_size: int = 8

    def __post_init__(self):
        if not self.zooms or any(not 0 < z < 1 for z in self.zooms):
            raise ValueError(f"zooms must be fractions in (0, 1), got {self.zooms}")
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {self.batch_size}")
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
    """

    prediction: LocalScalePrediction
    window_a: Window | None
    window_b: Window | None
    score: float
    base_score: float
    base: LocalScalePrediction
    candidates: int = 0
    scores: list[tuple[str, Window | None, float]] = field(default_factory=list, repr=False)


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
    sim = a.transpose(1, 2) @ b                                    # B x Na x Nb
    best_sim, best_b = sim.max(2)
    best_a = sim.argmax(1)                                         # B x Nb
    mutual = torch.gather(best_a, 1, best_b) == torch.arange(sim.shape[1], device=sim.device)
    return (best_sim.clamp_min(0) * mutual).sum(1)


def _scores(model: LocalScaleNet, fa: torch.Tensor, fb: torch.Tensor, lb_a, lb_b, bf16: bool) -> torch.Tensor:
    """Scores of ``B`` pairs of encodings (``fa`` or ``fb`` may have batch 1 and is expanded)."""
    n = max(fa.shape[0], fb.shape[0])
    fa, fb = fa.expand(n, -1, -1, -1), fb.expand(n, -1, -1, -1)
    with torch.autocast(model.device.type, dtype=torch.bfloat16, enabled=bf16):
        logits, vis = model.forward_features_all(fa, fb)
    probs = F.softmax(logits.float(), 1)
    visible = torch.sigmoid(vis.float())[:, 0] if vis is not None else None
    g = fa.shape[-1]
    cells_a, cells_b = _inside_cells(lb_a, g).to(fa.device), _inside_cells(lb_b, g).to(fa.device)
    rel = reliability(probs, visible, model.config.calibration, 1).flatten(1)[:, cells_a].mean(1)
    return (rel * mutual_similarity(fa, fb, cells_a, cells_b)).cpu()


def _crop(rgb: np.ndarray, win: Window, factor: float) -> np.ndarray:
    """Crop of a (possibly reduced) image by a window in original pixels."""
    x0, y0, x1, y1 = (int(round(v / factor)) for v in win)
    return np.ascontiguousarray(rgb[y0:max(y1, y0 + 1), x0:max(x1, x0 + 1)])


def _encode_windows(model: LocalScaleNet, rgb: np.ndarray, factor: float, windows: list[Window],
                    bf16: bool, batch: int) -> tuple[torch.Tensor, Letterbox]:
    """Encodings ``N x D x h x w`` of the windows of one image (all of one size, so one placement)."""
    feats, lb = [], None
    for i in range(0, len(windows), batch):
        xs = []
        for win in windows[i:i + batch]:
            boxed, lb = letterbox(_crop(rgb, win, factor), model.config.image_size, (win[3] - win[1], win[2] - win[0]))
            xs.append(to_tensor(boxed))
        with torch.autocast(model.device.type, dtype=torch.bfloat16, enabled=bf16):
            feats.append(model.encode(torch.stack(xs).to(model.device)).float())
    return torch.cat(feats), lb


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
def search_scale_map(model: LocalScaleNet, image_a: ImageLike, image_b: ImageLike,
                     cfg: WindowSearchConfig = WindowSearchConfig(), bf16: bool = False) -> WindowSearchResult:
    """Per-pixel ``S_{A->B}`` from the best-scoring window pair (see the module docstring).

    Needs a calibrated Local-ScaleNet (``pred.reliability``). A window pair replaces the whole
    pair only when it scores higher; on pairs the first pass already frames well, the result is
    the first pass.
    """
    if not model.config.calibration:
        raise ValueError("search_scale_map needs a calibrated Local-ScaleNet (config.calibration)")
    (a, shape_a), (b, shape_b) = model.load(image_a, "image A"), model.load(image_b, "image B")
    if is_gray(a) != is_gray(b):
        a, b = to_gray3(a), to_gray3(b)
    fa, fb = shape_a[0] / a.shape[0], shape_b[0] / b.shape[0]

    def encode(rgb, factor, win, name):
        crop = rgb if win is None else _crop(rgb, win, factor)
        shape = (shape_a if name == "image A" else shape_b) if win is None else (win[3] - win[1], win[2] - win[0])
        return model.encode_image(crop, name, bf16, shape)

    ea, eb = encode(a, fa, None, "image A"), encode(b, fb, None, "image B")
    base = model.predict_from_features(ea, eb, bf16=bf16)
    base_score = float(_scores(model, ea.features, eb.features, ea.letterbox, eb.letterbox, bf16)[0])
    best = (base_score, None, None)
    scores: list[tuple[str, Window | None, float]] = [("whole", None, base_score)]
    for zoom in cfg.zooms:
        for side, rgb, shape, factor in (("a", a, shape_a, fa), ("b", b, shape_b, fb)):
            windows = grid_windows(*shape, zoom) if side in cfg.sides else []
            if not windows:
                continue
            fw, lb = _encode_windows(model, rgb, factor, windows, bf16, cfg.batch_size)
            for i in range(0, len(windows), cfg.batch_size):
                part = fw[i:i + cfg.batch_size]
                sc = (_scores(model, part, eb.features, lb, eb.letterbox, bf16) if side == "a" else
                      _scores(model, ea.features, part, ea.letterbox, lb, bf16))
                for win, v in zip(windows[i:i + cfg.batch_size], sc.tolist()):
                    scores.append((side, win, v))
                    if v > best[0]:
                        best = (v, win, None) if side == "a" else (v, None, win)
    score, win_a, win_b = best
    if win_a is None and win_b is None:
        pred = base
    else:
        ew = encode(a, fa, win_a, "image A") if win_a is not None else ea
        eo = encode(b, fb, win_b, "image B") if win_b is not None else eb
        pred = model.predict_from_features(ew, eo, bf16=bf16)
        if win_a is not None:
            pred = _compose(model.predict_from_features(ea, eb, bf16=bf16), pred, win_a)
        if win_b is not None:
            pred.meta["window_b"] = win_b
    return WindowSearchResult(pred, win_a, win_b, score, base_score, base, len(scores), scores)
