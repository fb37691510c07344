"""Windows of an image and the scores of window pairs: what the window search
(:mod:`localscale.search`) and the anchored pass (:mod:`localscale.models.anchoring`) of a
Local-ScaleNet share.

A window pair's score is the mean calibrated reliability over A's side times the sum of the
similarities of the mutual nearest neighbours between the two feature grids
(:func:`pair_scores`); :func:`plausible` checks that a pair's two directions agree and, for a
window of B, that A's content fills it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from ..io.preprocess import Letterbox, letterbox, to_tensor
from ..reliability import pair_statistics
from .local_prediction import LocalScalePrediction, reliability

#: ``(x0, y0, x1, y1)`` in the pixels of the original image, end exclusive
Window = tuple[int, int, int, int]


@dataclass
class WindowSearchConfig:
    """Window sizes of the search, as fractions of each image's sides (half-window overlap)."""

    zooms: tuple[float, ...] = (0.5, 0.25)
    #: search windows of A (zooms into B), of B (zooms out of B), or both
    sides: tuple[str, ...] = ("a", "b")
    #: quarter turns of B (counter-clockwise) tried besides B as it is: the whole images and every
    #: window pair are scored for each, and the turn of the pair kept is B's (each turn costs
    #: another window search)
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


def inside_cells(lb, grid: int) -> torch.Tensor:
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


def pair_scores(model, fa: torch.Tensor, fb: torch.Tensor, lb_a, lb_b, bf16: bool) -> torch.Tensor:
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
    cells_a, cells_b = inside_cells(lb_a, g).to(fa.device), inside_cells(lb_b, g).to(fa.device)
    rel = reliability(probs, visible, model.config.calibration, 1).flatten(1)[:, cells_a].mean(1)
    return (rel * mutual_similarity(fa, fb, cells_a, cells_b)).cpu()


def crop_window(rgb: np.ndarray, win: Window, factor: float) -> np.ndarray:
    """Crop of a (possibly reduced) image by a window in original pixels."""
    x0, y0, x1, y1 = (int(round(v / factor)) for v in win)
    return np.ascontiguousarray(rgb[y0 : max(y1, y0 + 1), x0 : max(x1, x0 + 1)])


def encode_window(
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
    crop, size = (
        (rgb, full_shape) if win is None else (crop_window(rgb, win, factor), (win[3] - win[1], win[2] - win[0]))
    )
    return model.encode_image(crop, name, bf16, size, turns)


def encode_windows(
    model, rgb: np.ndarray, factor: float, windows: list[Window], bf16: bool, batch: int
) -> tuple[torch.Tensor, Letterbox]:
    """Encodings ``N x D x h x w`` of the windows of one image (all of one size, so one placement)."""
    feats, lb = [], None
    for i in range(0, len(windows), batch):
        xs = []
        for win in windows[i : i + batch]:
            boxed, lb = letterbox(
                crop_window(rgb, win, factor), model.config.image_size, (win[3] - win[1], win[2] - win[0])
            )
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


def paste_window(base: LocalScalePrediction, inner: LocalScalePrediction, win: Window | None) -> LocalScalePrediction:
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
