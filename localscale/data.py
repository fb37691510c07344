"""On-the-fly synthetic training pairs from any folder of photos.

Each item: a source crop A, a random homography A->B (paper ranges + perspective), the
target B = A warped by H with its empty region **filled from another random photo**, both
letterboxed into the ``P x P`` processing frame exactly as at inference, and the analytic
ground truth: the per-cell scale map ``S_{A->B}`` on A's stride-8 grid plus the co-visible
mask. Items are a pure function of ``(seed, index)``, so runs are reproducible and resume
exactly, with any number of DataLoader workers.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from .errors import ImageError
from .geometry import HomographyConfig, grid_points, homography_scale_map, project, sample_homography, translation
from .io import load_image
from .preprocess import letterbox, make_letterbox, to_tensor

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".ppm", ".pgm", ".bmp", ".tif", ".tiff")


def list_images(folder: str | Path) -> list[Path]:
    """Sorted image files of a folder (non-recursive)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ImageError(f"image folder not found: {folder}")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise ImageError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in {folder}")
    return files


def split_images(files: Sequence[Path], holdout_every: int = 10) -> tuple[list[Path], list[Path]]:
    """Deterministic train / held-out split: every ``holdout_every``-th file (sorted) is held out."""
    files = sorted(files)
    held = [f for i, f in enumerate(files) if i % holdout_every == 0]
    return [f for i, f in enumerate(files) if i % holdout_every != 0], held


@dataclass
class PairConfig:
    image_size: int = 192                    #: processing frame P
    stride: int = 8                          #: ground-truth grid stride (the model's output stride)
    homography: HomographyConfig = field(default_factory=HomographyConfig)
    crop_fraction: tuple[float, float] = (0.6, 1.0)   #: crop side of A, as a fraction of the photo side
    aspect_range: tuple[float, float] = (0.6, 1.7)    #: width/height of A
    photometric: float = 0.25                #: strength of brightness/contrast/gamma jitter on B
    gray_probability: float = 0.1            #: both images turned gray
    fill: bool = True                        #: fill B's empty region from another photo (else zeros)
    #: render B from the *whole* photo, so that around A's crop B shows the photo's real
    #: surroundings (as a second real view would); the fill photo covers only what lies beyond
    #: the photo. Off: B shows A's crop only, with a sharp edge to the fill (the paper's recipe).
    context: bool = False


class SyntheticPairs(Dataset):
    """Synthetic homography pairs. ``len`` is ``length``; item ``i`` is a function of ``(seed, i)``.

    Returns dicts with ``a``, ``b`` (``3 x P x P`` float in [0, 1]), ``scale`` (``P/8 x P/8``
    float32 analytic ``S_{A->B}`` in the processing frame, 1 where undefined), ``mask``
    (bool, co-visible cells of A's image region), ``H`` (3x3, processing frame),
    ``global_scale`` (exp mean log scale over ``mask``) and ``perspective`` (std of
    ``log2`` scale over ``mask``).
    """

    def __init__(self, images: Sequence[str | Path] | str | Path, length: int = 10**9, seed: int = 0,
                 config: PairConfig | None = None, cache: bool = True):
        if isinstance(images, (str, Path)):
            images = list_images(images)
        self.files = [Path(p) for p in images]
        if len(self.files) < 2:
            raise ImageError(f"need at least 2 images (source + fill), got {len(self.files)}")
        self.length = length
        self.seed = seed
        self.cfg = config or PairConfig()
        self._cache: dict[int, np.ndarray] | None = {} if cache else None

    def __len__(self) -> int:
        return self.length

    def _image(self, i: int) -> np.ndarray:
        if self._cache is not None and i in self._cache:
            return self._cache[i]
        img = load_image(self.files[i], name=str(self.files[i].name))
        if self._cache is not None:
            self._cache[i] = img
        return img

    def _crop(self, rng: np.random.Generator, img: np.ndarray) -> np.ndarray:
        return self._crop_with_offset(rng, img)[0]

    def _crop_with_offset(self, rng: np.random.Generator, img: np.ndarray) -> tuple[np.ndarray, tuple[int, int]]:
        h, w = img.shape[:2]
        frac = rng.uniform(*self.cfg.crop_fraction)
        aspect = math.exp(rng.uniform(*np.log(self.cfg.aspect_range)))
        ch = frac * min(h, w / aspect)
        cw = ch * aspect
        ch, cw = int(max(32, min(h, ch))), int(max(32, min(w, cw)))
        y, x = rng.integers(0, h - ch + 1), rng.integers(0, w - cw + 1)
        return img[y:y + ch, x:x + cw], (int(x), int(y))

    def __getitem__(self, index: int) -> dict:
        rng = np.random.default_rng([self.seed, int(index)])
        cfg = self.cfg
        src, other = rng.choice(len(self.files), 2, replace=False)
        photo = self._image(int(src))
        a_orig, (x0, y0) = self._crop_with_offset(rng, photo)
        ha, wa = a_orig.shape[:2]
        H = sample_homography(rng, (ha, wa), (ha, wa), cfg.homography)

        lb = make_letterbox(ha, wa, cfg.image_size)   # B has A's size, so one letterbox for both
        L = lb.matrix()
        H_proc = L @ H @ np.linalg.inv(L)
        a_proc, _ = letterbox(a_orig, cfg.image_size)
        if cfg.context:   # the whole photo, placed so that A's crop lands where H puts it
            b_proc = self._render_target(rng, photo, L @ H @ translation(-x0, -y0), lb, int(other),
                                         centre=(x0, y0, wa, ha))
        else:
            b_proc = self._render_target(rng, a_orig, L @ H, lb, int(other))

        if rng.random() < cfg.gray_probability:
            a_proc, b_proc = _gray3(a_proc), _gray3(b_proc)
        b_proc = _photometric(rng, b_proc, cfg.photometric, lb)

        P, st = cfg.image_size, cfg.stride
        s = homography_scale_map(H_proc, P, P, st)
        q = project(H_proc, grid_points(P, P, st))
        w = grid_points(P, P, st) @ H_proc[2, :2] + H_proc[2, 2]
        inside_b = ((q[..., 0] >= lb.left - 0.5) & (q[..., 0] <= lb.left + lb.new_width - 0.5)
                    & (q[..., 1] >= lb.top - 0.5) & (q[..., 1] <= lb.top + lb.new_height - 0.5))
        mask = inside_b & (w > 0) & lb.valid_mask(st) & np.isfinite(s)
        s = np.where(mask, s, 1.0)
        ls = np.log(s[mask])
        return {
            "a": to_tensor(a_proc), "b": to_tensor(b_proc),
            "scale": torch.from_numpy(s.astype(np.float32)), "mask": torch.from_numpy(mask),
            "H": torch.from_numpy(H_proc), "global_scale": float(np.exp(ls.mean())) if mask.any() else 1.0,
            "perspective": float(np.log2(s[mask]).std()) if mask.sum() > 1 else 0.0,
        }

    def _render_target(self, rng, a_orig: np.ndarray, H_to_proc: np.ndarray, lb, other: int,
                       centre: tuple[int, int, int, int] | None = None) -> np.ndarray:
        """Warp A (or the whole photo) straight into B's processing frame; fill B's empty image
        region from another photo. ``centre``: ``(x0, y0, w, h)`` of A's crop in ``a_orig``
        (default: all of it); the anti-alias blur is set by the zoom at A's centre."""
        P = self.cfg.image_size
        x0, y0, cw, ch = centre or (0, 0, a_orig.shape[1], a_orig.shape[0])
        centre = np.array([x0 + (cw - 1) / 2, y0 + (ch - 1) / 2])
        wc = H_to_proc[2, :2] @ centre + H_to_proc[2, 2]
        minify = math.sqrt(abs(np.linalg.det(H_to_proc)) / abs(wc) ** 3)
        src = a_orig
        if minify < 1:
            src = cv2.GaussianBlur(a_orig, (0, 0), 0.5 * math.sqrt(1 / minify**2 - 1))
        warped = cv2.warpPerspective(src, H_to_proc, (P, P), flags=cv2.INTER_LINEAR, borderValue=0)
        cover = cv2.warpPerspective(np.ones(src.shape[:2], np.float32), H_to_proc, (P, P),
                                    flags=cv2.INTER_LINEAR, borderValue=0)[..., None]
        region = np.zeros((P, P, 1), np.float32)
        region[lb.top:lb.top + lb.new_height, lb.left:lb.left + lb.new_width] = 1
        fill = np.zeros_like(warped)
        if self.cfg.fill:
            f = self._crop(rng, self._image(other))
            fill[lb.top:lb.top + lb.new_height, lb.left:lb.left + lb.new_width] = cv2.resize(
                f, (lb.new_width, lb.new_height), interpolation=cv2.INTER_AREA)
        out = (warped * cover + fill * (1 - cover)) * region
        return out.round().clip(0, 255).astype(np.uint8)


def _gray3(img: np.ndarray) -> np.ndarray:
    g = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    return np.repeat(g[..., None], 3, 2)


def _photometric(rng, img: np.ndarray, strength: float, lb) -> np.ndarray:
    if strength <= 0:
        return img
    x = img.astype(np.float32) / 255.0
    gain = math.exp(rng.uniform(-strength, strength))
    bias = rng.uniform(-strength, strength) * 0.3
    gamma = math.exp(rng.uniform(-strength, strength))
    x = np.clip(x * gain + bias, 0, 1) ** gamma
    out = (x * 255).round().astype(np.uint8)
    pad = np.ones(img.shape[:2], bool)
    pad[lb.top:lb.top + lb.new_height, lb.left:lb.left + lb.new_width] = False
    out[pad] = 0
    return out


def collate(batch: list[dict]) -> dict:
    out = {}
    for k in batch[0]:
        v = [b[k] for b in batch]
        out[k] = torch.stack(v) if isinstance(v[0], torch.Tensor) else torch.tensor(v)
    return out
