"""Real training pairs labelled by a 3D model (the paper's real-pair labels, made dense).

A COLMAP model tells which 3D points two photos both see and where each image observed them.
From those co-visible observations ``x_A`` and ``x_B`` (``N x 2`` pixels):

* the **global label** (paper, Sec. 3): the mean, in log space, of ``|x_B(i) - x_B(j)| / |x_A(i) - x_A(j)|``
  over ``R = 200`` random pairs of points (:func:`global_log_scale`);
* the **per-pixel label**: at each point of A, the median in log space of the same ratio over its
  ``k`` nearest co-visible neighbours in A (:func:`point_log_scales`), gathered on the network's
  stride-8 grid of A (median per cell) as a sparse target map with its mask.

Pairs are drawn so that the scales in ``[1/6, 6]`` are all represented (:class:`RealPairs`): where
the photos lack strong zoom, a window of one image is cut out (a close-up, exact for the labels
since they are measured on the pixels the network sees) and B is turned by quarter turns.
Convention: ``S_{A->B} > 1`` means content looks bigger in B.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from .. import scales
from ..core.errors import LocalScaleError
from ..geometry import turn_matrix
from ..io.preprocess import letterbox, to_tensor

#: ``kind`` of a real pair in the training batches (after :data:`localscale.data.PAIR_KINDS`)
REAL_KIND = 100


@dataclass
class CovisiblePair:
    """Two photos and the observations of the 3D points they share: ``xy_a``, ``xy_b`` are ``N x 2``
    float32 pixel coordinates (COLMAP's convention: the centre of the top-left pixel is 0.5)."""

    image_a: Path
    image_b: Path
    xy_a: np.ndarray
    xy_b: np.ndarray
    collection: str = ""


def covisible_pairs(reconstruction, images_dir, min_points: int = 50, collection: str = "") -> list[CovisiblePair]:
    """Every pair of registered images of a ``pycolmap.Reconstruction`` sharing at least ``min_points``
    3D points, with the two images' observations of those points (in image name order)."""
    images_dir = Path(images_dir)
    observed = {}
    for image in reconstruction.images.values():
        if not image.has_pose:
            continue
        obs = {int(p.point3D_id): p.xy for p in image.points2D if p.has_point3D()}
        if obs:
            observed[image.name] = obs
    names = sorted(observed)
    pairs = []
    for i, a in enumerate(names):
        ids_a = observed[a].keys()
        for b in names[i + 1 :]:
            shared = sorted(ids_a & observed[b].keys())
            if len(shared) < min_points:
                continue
            xy_a = np.array([observed[a][k] for k in shared], np.float32)
            xy_b = np.array([observed[b][k] for k in shared], np.float32)
            pairs.append(CovisiblePair(images_dir / a, images_dir / b, xy_a, xy_b, collection))
    return pairs


def save_covisible_pairs(path, pairs: list[CovisiblePair]) -> None:
    """Write ``pairs`` to one ``.npz`` file (atomically)."""
    from ..core.outputs import atomic_path

    counts = np.array([len(p.xy_a) for p in pairs], np.int64)
    with atomic_path(Path(path)) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(
                f,
                image_a=np.array([str(p.image_a) for p in pairs]),
                image_b=np.array([str(p.image_b) for p in pairs]),
                collection=np.array([p.collection for p in pairs]),
                counts=counts,
                xy_a=np.concatenate([p.xy_a for p in pairs]) if pairs else np.zeros((0, 2), np.float32),
                xy_b=np.concatenate([p.xy_b for p in pairs]) if pairs else np.zeros((0, 2), np.float32),
            )


def load_covisible_pairs(path) -> list[CovisiblePair]:
    """The pairs of a file written by :func:`save_covisible_pairs`."""
    try:
        z = np.load(path)
        ends = np.cumsum(z["counts"])
        xa, xb = np.split(z["xy_a"], ends[:-1]), np.split(z["xy_b"], ends[:-1])
        return [
            CovisiblePair(Path(a), Path(b), pa, pb, str(c))
            for a, b, c, pa, pb in zip(z["image_a"], z["image_b"], z["collection"], xa, xb)
        ]
    except (OSError, KeyError, ValueError) as e:
        raise LocalScaleError(f"{path}: not a file of labelled real pairs ({e})") from None


def point_log_scales(xy_a: np.ndarray, xy_b: np.ndarray, k: int = 8, min_distance: float = 4.0) -> np.ndarray:
    """``N``: ln S at each point of A, the median of ``ln(|x_B(i) - x_B(j)| / |x_A(i) - x_A(j)|)`` over its
    ``k`` nearest points ``j`` in A at least ``min_distance`` pixels away (NaN with fewer than 3 such)."""
    n = len(xy_a)
    out = np.full(n, np.nan)
    if n < 4:
        return out
    da = np.linalg.norm(xy_a[:, None] - xy_a[None], axis=-1)
    db = np.linalg.norm(xy_b[:, None] - xy_b[None], axis=-1)
    da = np.where(da >= min_distance, da, np.inf)
    kk = min(k, n - 1)
    nearest = np.argpartition(da, kk - 1, axis=1)[:, :kk]
    dist_a = np.take_along_axis(da, nearest, 1)
    dist_b = np.take_along_axis(db, nearest, 1)
    ok = np.isfinite(dist_a) & (dist_b > 0)
    ratio = np.where(ok, np.log(np.where(ok, dist_b, 1.0) / np.where(ok, dist_a, 1.0)), np.nan)
    enough = ok.sum(1) >= 3
    out[enough] = np.nanmedian(ratio[enough], axis=1)
    return out


def global_log_scale(
    xy_a: np.ndarray, xy_b: np.ndarray, rng: np.random.Generator, num_pairs: int = 200, min_distance: float = 4.0
) -> float:
    """ln S of the pair (the paper's label): the mean of ``ln(|x_B(i) - x_B(j)| / |x_A(i) - x_A(j)|)`` over
    ``num_pairs`` random pairs of points at least ``min_distance`` apart in both images (NaN if none)."""
    n = len(xy_a)
    if n < 2:
        return float("nan")
    i, j = rng.integers(0, n, (2, 4 * num_pairs))
    da = np.linalg.norm(xy_a[i] - xy_a[j], axis=1)
    db = np.linalg.norm(xy_b[i] - xy_b[j], axis=1)
    ok = (da >= min_distance) & (db >= min_distance)
    if not ok.any():
        return float("nan")
    return float(np.log(db[ok][:num_pairs] / da[ok][:num_pairs]).mean())


def _apply(T: np.ndarray, xy: np.ndarray) -> np.ndarray:
    return xy @ T[:2, :2].T + T[:2, 2]


@dataclass
class RealPairConfig:
    """How :class:`RealPairs` draws its samples."""

    image_size: int = 192  #: processing frame (the model's ``image_size``)
    stride: int = 8  #: target grid stride (the model's output stride)
    scale_range: tuple[float, float] = (1 / 6, 6.0)  #: the target scale is drawn log-uniformly from it
    min_window: int = 192  #: smallest side of a cut-out window, in the photo's pixels
    turn_probability: float = 0.5  #: B is turned by 1-3 quarter turns
    swap_probability: float = 0.5  #: A and B exchange roles
    neighbours: int = 8  #: k of :func:`point_log_scales`
    min_points: int = 30  #: fewer co-visible points in the windows: the sample is drawn again
    global_pairs: int = 200  #: R of :func:`global_log_scale`


class RealPairs(Dataset):
    """Samples of labelled real pairs in the batch format of :class:`localscale.data.SyntheticPairs`.

    Item ``i`` is a function of ``(seed, i)``: a pair (roles swapped at random), a target scale drawn
    log-uniformly from ``scale_range`` and reached by cutting a window out of B (zoom in) or A (zoom
    out) around a co-visible point, B turned by quarter turns, both letterboxed. ``scale`` holds
    the per-cell label (median of :func:`point_log_scales` of the points in the cell, exponentiated)
    on labelled cells (``mask``), 1 elsewhere; ``valid`` is all False (co-visibility is unknown
    between the points, so no visibility target); ``global_scale`` is :func:`global_log_scale`
    exponentiated; ``H`` is the identity (no homography).
    """

    def __init__(self, pairs: list[CovisiblePair], length: int, seed: int = 0, config: RealPairConfig | None = None):
        if not pairs:
            raise LocalScaleError("no labelled real pairs")
        self.pairs, self.length, self.seed = pairs, length, seed
        self.cfg = config or RealPairConfig()
        self._images: dict[Path, np.ndarray] = {}
        self._base = [None] * len(pairs)

    def __len__(self) -> int:
        return self.length

    def _image(self, path: Path) -> np.ndarray:
        if path not in self._images:
            bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if bgr is None:
                raise LocalScaleError(f"cannot read {path}")
            if len(self._images) > 256:
                self._images.pop(next(iter(self._images)))
            self._images[path] = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        return self._images[path]

    def _base_log_scale(self, i: int) -> float:
        if self._base[i] is None:
            p = self.pairs[i]
            self._base[i] = float(np.nanmedian(point_log_scales(p.xy_a, p.xy_b, self.cfg.neighbours)))
        return self._base[i]

    def __getitem__(self, index: int) -> dict:
        return self.draw(index)[0]

    def draw(self, index: int) -> tuple[dict, np.ndarray, np.ndarray]:
        """Item ``index`` and the co-visible points it was labelled from, in the processing frames of A and B
        (``N x 2`` each). A draw with too few labelled points is drawn again from ``(seed, index, attempt)``."""
        for attempt in range(20):
            rng = np.random.default_rng([self.seed, int(index), attempt])
            drawn = self._item(rng)
            if drawn is not None:
                return drawn
        raise LocalScaleError(f"real pair item {index}: 20 draws gave too few labelled points")

    def _window(self, rng, shape, centre, zoom) -> tuple[int, int, int, int]:
        """``(x0, y0, w, h)``: a window ``1/zoom`` of the image's size (at least ``min_window``) around ``centre``."""
        H, W = shape
        f = max(1.0 / zoom, self.cfg.min_window / min(H, W))
        w, h = min(W, round(W * f)), min(H, round(H * f))
        x0 = int(np.clip(round(centre[0] - w / 2), 0, W - w))
        y0 = int(np.clip(round(centre[1] - h / 2), 0, H - h))
        return x0, y0, w, h

    def _item(self, rng: np.random.Generator) -> tuple[dict, np.ndarray, np.ndarray] | None:
        cfg = self.cfg
        i = int(rng.integers(len(self.pairs)))
        p = self.pairs[i]
        paths, xy, base = [p.image_a, p.image_b], [p.xy_a, p.xy_b], self._base_log_scale(i)
        if rng.random() < cfg.swap_probability:
            paths, xy, base = paths[::-1], xy[::-1], -base
        if not math.isfinite(base):
            return None
        imgs = [self._image(q) for q in paths]
        lo, hi = math.log(cfg.scale_range[0]), math.log(cfg.scale_range[1])
        zoom = math.exp(rng.uniform(lo, hi) - base)  # > 1: cut B (content bigger in B); < 1: cut A
        side = 1 if zoom > 1 else 0
        centre = xy[side][rng.integers(len(xy[side]))]
        windows = [(0, 0, im.shape[1], im.shape[0]) for im in imgs]
        windows[side] = self._window(rng, imgs[side].shape[:2], centre, max(zoom, 1 / zoom))
        turn = int(rng.integers(1, 4)) if rng.random() < cfg.turn_probability else 0
        procs, pts = [], []
        for s in (0, 1):
            x0, y0, w, h = windows[s]
            crop = imgs[s][y0 : y0 + h, x0 : x0 + w]
            T = np.array([[1.0, 0, -x0], [0, 1.0, -y0], [0, 0, 1]])
            if s == 1 and turn:
                T = turn_matrix(turn, (h, w)) @ T
                crop = np.rot90(crop, turn)
            boxed, lb = letterbox(np.ascontiguousarray(crop), cfg.image_size)
            # COLMAP pixel centres are at +0.5; the letterbox matrix maps pixel-centre coordinates
            pts.append(_apply(lb.matrix() @ T, xy[s] - 0.5))
            procs.append((boxed, lb, crop.shape[:2]))
        keep = np.ones(len(pts[0]), bool)
        for s in (0, 1):
            lb, (h, w) = procs[s][1], procs[s][2]
            inside = _apply(np.linalg.inv(lb.matrix()), pts[s])
            keep &= (inside >= -0.5).all(1) & (inside[:, 0] <= w - 0.5) & (inside[:, 1] <= h - 0.5)
        if keep.sum() < cfg.min_points:
            return None
        pa, pb = pts[0][keep], pts[1][keep]
        item = self._sample(rng, procs[0], procs[1], pa, pb)
        return None if item is None else (item, pa, pb)

    def _sample(self, rng, proc_a, proc_b, pa: np.ndarray, pb: np.ndarray) -> dict | None:
        cfg = self.cfg
        log_s = point_log_scales(pa, pb, cfg.neighbours)
        g = global_log_scale(pa, pb, rng, cfg.global_pairs)
        ok = np.isfinite(log_s)
        if ok.sum() < cfg.min_points or not math.isfinite(g):
            return None
        n = math.ceil(cfg.image_size / cfg.stride)
        cells = np.clip(np.floor((pa[ok] + 0.5) / cfg.stride).astype(int), 0, n - 1)
        flat = cells[:, 1] * n + cells[:, 0]
        target = np.zeros(n * n)
        mask = np.zeros(n * n, bool)
        for c in np.unique(flat):
            target[c] = np.median(log_s[ok][flat == c])
            mask[c] = True
        target = np.where(mask, target, 0.0).reshape(n, n)
        log_lo, log_hi = float(scales.LOG_BINS[0]), float(scales.LOG_BINS[-1])
        target = np.clip(target, log_lo, log_hi)
        return {
            "a": to_tensor(proc_a[0]),
            "b": to_tensor(proc_b[0]),
            "scale": torch.from_numpy(np.exp(target).astype(np.float32)),
            "mask": torch.from_numpy(mask.reshape(n, n)),
            "valid": torch.zeros(n, n, dtype=torch.bool),
            "H": torch.from_numpy(np.eye(3)),
            "global_scale": float(np.exp(np.clip(g, log_lo, log_hi))),
            "perspective": float(np.std(log_s[ok]) / math.log(2)),
            "related": True,
            "kind": REAL_KIND,
            "redrawn": 0,  # (a real sample drawn again had too few points, not a bad photo)
        }


class MixedPairs(Dataset):
    """Item ``i`` from ``real`` with probability ``fraction`` (decided by ``(seed, i)``), else from ``synthetic``."""

    def __init__(self, synthetic: Dataset, real: Dataset, fraction: float, seed: int = 0):
        self.synthetic, self.real, self.fraction, self.seed = synthetic, real, fraction, seed

    def __len__(self) -> int:
        return len(self.synthetic)

    def __getitem__(self, index: int) -> dict:
        pick_real = np.random.default_rng([self.seed, int(index), 7]).random() < self.fraction
        return self.real[index] if pick_real else self.synthetic[index]
