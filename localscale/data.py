"""On-the-fly synthetic training pairs from any folder of photos.

Each item: a source crop A, a random homography A->B (paper ranges + perspective), the
target B = A warped by H with its empty region **filled from another random photo**, both
letterboxed into the ``P x P`` processing frame exactly as at inference, and the analytic
ground truth: the per-cell scale map ``S_{A->B}`` on A's stride-8 grid plus the co-visible
mask.

Beyond the paper's recipe, :class:`PairConfig` can make pairs look like real second views:
B rendered with the photo's real surroundings (``context``), low overlap (A's footprint
shifted far into B's border), rotations over the whole circle, exact and near identity
pairs, unrelated pairs (B another photo: nothing of A is visible), photometric change
on either side (lighting, gamma, colour, gray on one side, blur, noise, JPEG), and pairs
with the roles of A and B swapped. Items are a pure function of ``(seed, index)``, so runs are reproducible and resume
exactly, with any number of DataLoader workers.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from .core.errors import ImageError
from .geometry import HomographyConfig, grid_points, homography_scale_map, project, sample_homography, translation
from .io import load_image
from .io.preprocess import letterbox, make_letterbox, to_tensor

#: the ``kind`` of an item is an index into this tuple
PAIR_KINDS = ("homography", "identity", "near-identity", "rotation", "low-overlap", "unrelated")

#: photos with a side below this cannot give a crop; they are skipped like unreadable ones
MIN_PHOTO_SIDE = 32
#: draws of one item that may hit unreadable photos before the item is an error
MAX_REDRAWS = 50


class _UnreadablePhoto(Exception):
    """A draw touched a photo that cannot be used (already warned about)."""


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
    image_size: int = 192  #: processing frame P
    stride: int = 8  #: ground-truth grid stride (the model's output stride)
    homography: HomographyConfig = field(default_factory=HomographyConfig)
    crop_fraction: tuple[float, float] = (0.6, 1.0)  #: crop side of A, as a fraction of the photo side
    aspect_range: tuple[float, float] = (0.6, 1.7)  #: width/height of A
    photometric: float = 0.25  #: strength of brightness/contrast/gamma jitter on B
    gray_probability: float = 0.1  #: both images turned gray
    fill: bool = True  #: fill B's empty region from another photo (else zeros)
    #: render B from the *whole* photo, so that around A's crop B shows the photo's real
    #: surroundings (as a second real view would); the fill photo covers only what lies beyond
    #: the photo. Off: B shows A's crop only, with a sharp edge to the fill (the paper's recipe).
    context: bool = False
    #: share of pairs whose A is B up to at most +-5% scale, +-3 deg and a few pixels (half of them exactly)
    identity_probability: float = 0.0
    #: share of pairs whose rotation is drawn from the whole circle (else +-``homography.rotation_deg``)
    full_rotation_probability: float = 0.0
    #: share of pairs whose A lands far off B's centre (shift up to ``low_overlap_shift`` of B's size)
    low_overlap_probability: float = 0.0
    low_overlap_shift: float = 0.6
    #: share of pairs where B is a crop of another photo: nothing of A is visible in B
    unrelated_probability: float = 0.0
    #: one side (A or B, at random) turned gray
    gray_one_side_probability: float = 0.0
    #: share of pairs with strong lighting change on B (gain down to 1/5, gamma, colour cast)
    strong_light_probability: float = 0.0
    #: probability of each degradation (blur, noise, JPEG) on each side
    degrade_probability: float = 0.0
    #: share of pairs whose roles are swapped (A the rendered view, B the crop; target from
    #: ``inv(H)``), so that a model cannot tell the direction from which side was rendered
    swap_probability: float = 0.0


class SyntheticPairs(Dataset):
    """Synthetic homography pairs. ``len`` is ``length``; item ``i`` is a function of ``(seed, i)``.

    Returns dicts with ``a``, ``b`` (``3 x P x P`` float in [0, 1]), ``scale`` (``P/8 x P/8``
    float32 analytic ``S_{A->B}`` in the processing frame, 1 where undefined), ``mask``
    (bool, co-visible cells of A's image region), ``valid`` (bool, cells of A's image region,
    not the padding), ``H`` (3x3, processing frame), ``global_scale`` (exp mean log scale
    over ``mask``), ``perspective`` (std of ``log2`` scale over ``mask``), ``related``
    (False when nothing of A is visible in B) and ``kind`` (index into :data:`PAIR_KINDS`).
    """

    def __init__(
        self,
        images: Sequence[str | Path] | str | Path,
        length: int = 10**9,
        seed: int = 0,
        config: PairConfig | None = None,
        cache: bool = True,
        cache_bytes: int | None = 2**30,
    ):
        if isinstance(images, (str, Path)):
            images = list_images(images)
        self.files = [Path(p) for p in images]
        if len(self.files) < 2:
            raise ImageError(f"need at least 2 images (source + fill), got {len(self.files)}")
        self.length = length
        self.seed = seed
        self.cfg = config or PairConfig()
        self._cache: dict[int, np.ndarray] | None = {} if cache else None
        #: bound of the decoded photos kept, in bytes per process (None: all); the oldest is dropped first
        self.cache_bytes: int | None = cache_bytes
        self._cache_bytes = 0
        #: indices of photos that could not be used (skipped with a warning, once each)
        self.unreadable: set[int] = set()

    def __len__(self) -> int:
        return self.length

    def _image(self, i: int) -> np.ndarray:
        if self._cache is not None and i in self._cache:
            return self._cache[i]
        if i in self.unreadable:
            raise _UnreadablePhoto(i)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # 16-bit / alpha notes, once per photo, are not news here
                img = load_image(self.files[i], name=str(self.files[i].name))
            if min(img.shape[:2]) < MIN_PHOTO_SIDE:
                raise ImageError(
                    f"{self.files[i].name}: photo is {img.shape[1]}x{img.shape[0]}, smaller than "
                    f"the smallest crop ({MIN_PHOTO_SIDE} px)"
                )
        except ImageError as e:
            self.unreadable.add(i)
            warnings.warn(f"training photo skipped: {' '.join(str(e).split())}", stacklevel=2)
            raise _UnreadablePhoto(i) from None
        if self._cache is not None:
            self._cache[i] = img
            self._cache_bytes += img.nbytes
            while self.cache_bytes is not None and self._cache_bytes > self.cache_bytes and len(self._cache) > 1:
                self._cache_bytes -= self._cache.pop(next(iter(self._cache))).nbytes  # oldest first
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
        return img[y : y + ch, x : x + cw], (int(x), int(y))

    def _sample_homography(self, rng: np.random.Generator, shape: tuple[int, int]) -> tuple[np.ndarray, str]:
        """A->B homography for a crop of ``shape`` and the kind of pair it makes."""
        cfg = self.cfg
        hcfg = cfg.homography
        if rng.random() < cfg.identity_probability:
            if rng.random() < 0.5:
                return np.eye(3), "identity"
            hcfg = dataclasses.replace(
                hcfg, scale_range=(0.95, 1.05), rotation_deg=3.0, skew=0.01, perspective=0.03, translation=0.02
            )
            return sample_homography(rng, shape, shape, hcfg), "near-identity"
        kind = "homography"
        if rng.random() < cfg.full_rotation_probability:
            hcfg, kind = dataclasses.replace(hcfg, rotation_deg=180.0), "rotation"
        if rng.random() < cfg.low_overlap_probability:
            hcfg, kind = dataclasses.replace(hcfg, translation=cfg.low_overlap_shift), "low-overlap"
        return sample_homography(rng, shape, shape, hcfg), kind

    def __getitem__(self, index: int) -> dict:
        """Item ``index``; a draw that hits an unreadable photo (corrupt, or smaller than a crop) is
        redrawn from ``(seed, index, attempt)``, so items stay a pure function of ``(seed, index)``
        for a given set of readable photos. ``redrawn`` counts such draws."""
        for attempt in range(MAX_REDRAWS):
            try:
                item = self._item(np.random.default_rng([self.seed, int(index)] + ([attempt] if attempt else [])))
            except _UnreadablePhoto:
                continue
            item["redrawn"] = attempt
            return item
        raise ImageError(
            f"item {index}: {MAX_REDRAWS} draws hit unreadable photos "
            f"({len(self.unreadable)} of {len(self.files)} photos are unreadable)"
        )

    def _item(self, rng: np.random.Generator) -> dict:
        cfg = self.cfg
        src, other = rng.choice(len(self.files), 2, replace=False)
        photo = self._image(int(src))
        a_orig, (x0, y0) = self._crop_with_offset(rng, photo)
        ha, wa = a_orig.shape[:2]
        unrelated = rng.random() < cfg.unrelated_probability
        H, kind = self._sample_homography(rng, (ha, wa))

        lb = make_letterbox(ha, wa, cfg.image_size)  # B has A's size, so one letterbox for both
        L = lb.matrix()
        H_proc = L @ H @ np.linalg.inv(L)
        a_proc, _ = letterbox(a_orig, cfg.image_size)
        if unrelated:  # B: another photo, in A's frame; no pixel of A is visible
            kind = "unrelated"
            f = cv2.resize(self._crop(rng, self._image(int(other))), (wa, ha), interpolation=cv2.INTER_AREA)
            b_proc, _ = letterbox(f, cfg.image_size)
        elif kind == "identity":  # the very same pixels, as in predict(A, A)
            b_proc = a_proc.copy()
        elif cfg.context:  # the whole photo, placed so that A's crop lands where H puts it
            b_proc = self._render_target(
                rng, photo, L @ H @ translation(-x0, -y0), lb, int(other), centre=(x0, y0, wa, ha)
            )
        else:
            b_proc = self._render_target(rng, a_orig, L @ H, lb, int(other))

        strong = rng.random() < cfg.strong_light_probability
        b_proc = _photometric(rng, b_proc, cfg.photometric, lb, strong)
        a_proc = _photometric(rng, a_proc, 0.5 * cfg.photometric, lb)
        a_proc = _degrade(rng, a_proc, cfg.degrade_probability, lb)
        b_proc = _degrade(rng, b_proc, cfg.degrade_probability, lb)
        if rng.random() < cfg.gray_probability:
            a_proc, b_proc = _gray3(a_proc), _gray3(b_proc)
        elif rng.random() < cfg.gray_one_side_probability:
            if rng.random() < 0.5:
                a_proc = _gray3(a_proc)
            else:
                b_proc = _gray3(b_proc)

        if cfg.swap_probability > 0 and rng.random() < cfg.swap_probability:
            a_proc, b_proc, H_proc = b_proc, a_proc, np.linalg.inv(H_proc)

        P, st = cfg.image_size, cfg.stride
        valid = lb.valid_mask(st)
        s = homography_scale_map(H_proc, P, P, st)
        q = project(H_proc, grid_points(P, P, st))
        w = grid_points(P, P, st) @ H_proc[2, :2] + H_proc[2, 2]
        inside_b = (
            (q[..., 0] >= lb.left - 0.5)
            & (q[..., 0] <= lb.left + lb.new_width - 0.5)
            & (q[..., 1] >= lb.top - 0.5)
            & (q[..., 1] <= lb.top + lb.new_height - 0.5)
        )
        mask = inside_b & (w > 0) & valid & np.isfinite(s) & (not unrelated)
        s = np.where(mask, s, 1.0)
        ls = np.log(s[mask])
        return {
            "a": to_tensor(a_proc),
            "b": to_tensor(b_proc),
            "scale": torch.from_numpy(s.astype(np.float32)),
            "mask": torch.from_numpy(mask),
            "valid": torch.from_numpy(valid),
            "H": torch.from_numpy(H_proc),
            "global_scale": float(np.exp(ls.mean())) if mask.any() else 1.0,
            "perspective": float(np.log2(s[mask]).std()) if mask.sum() > 1 else 0.0,
            "related": not unrelated and bool(mask.any()),
            "kind": PAIR_KINDS.index(kind),
        }

    def _render_target(
        self,
        rng,
        a_orig: np.ndarray,
        H_to_proc: np.ndarray,
        lb,
        other: int,
        centre: tuple[int, int, int, int] | None = None,
    ) -> np.ndarray:
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
        cover = cv2.warpPerspective(
            np.ones(src.shape[:2], np.float32), H_to_proc, (P, P), flags=cv2.INTER_LINEAR, borderValue=0
        )[..., None]
        region = np.zeros((P, P, 1), np.float32)
        region[lb.top : lb.top + lb.new_height, lb.left : lb.left + lb.new_width] = 1
        fill = np.zeros_like(warped)
        if self.cfg.fill:
            f = self._crop(rng, self._image(other))
            fill[lb.top : lb.top + lb.new_height, lb.left : lb.left + lb.new_width] = cv2.resize(
                f, (lb.new_width, lb.new_height), interpolation=cv2.INTER_AREA
            )
        out = (warped * cover + fill * (1 - cover)) * region
        return out.round().clip(0, 255).astype(np.uint8)


def _gray3(img: np.ndarray) -> np.ndarray:
    g = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    return np.repeat(g[..., None], 3, 2)


def _photometric(rng, img: np.ndarray, strength: float, lb, strong: bool = False) -> np.ndarray:
    """Brightness/contrast/gamma jitter; ``strong``: a large lighting change (gain 1/5 .. 2,
    gamma 0.6 .. 1.6, a colour cast), as between photos taken at different times."""
    if strength <= 0 and not strong:
        return img
    x = img.astype(np.float32) / 255.0
    if strong:
        gain = math.exp(rng.uniform(math.log(0.2), math.log(2.0)))
        gamma = math.exp(rng.uniform(-0.5, 0.5))
        bias = rng.uniform(-0.05, 0.05)
        cast = np.exp(rng.uniform(-0.15, 0.15, 3)).astype(np.float32)
    else:
        gain = math.exp(rng.uniform(-strength, strength))
        bias = rng.uniform(-strength, strength) * 0.3
        gamma = math.exp(rng.uniform(-strength, strength))
        cast = np.ones(3, np.float32)
    x = np.clip(x * gain * cast + bias, 0, 1) ** gamma
    return _keep_padding((x * 255).round().astype(np.uint8), lb)


def _degrade(rng, img: np.ndarray, probability: float, lb) -> np.ndarray:
    """Each with ``probability``: Gaussian blur, sensor noise, JPEG compression."""
    if probability <= 0:
        return img
    out = img
    if rng.random() < probability:
        out = cv2.GaussianBlur(out, (0, 0), rng.uniform(0.5, 1.5))
    if rng.random() < probability:
        noise = rng.normal(0, rng.uniform(2, 8), out.shape)
        out = (out.astype(np.float32) + noise).round().clip(0, 255).astype(np.uint8)
    if rng.random() < probability:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(20, 80))])
        if ok:
            out = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED).reshape(img.shape)
    return out if out is img else _keep_padding(out, lb)


def _keep_padding(img: np.ndarray, lb) -> np.ndarray:
    pad = np.ones(img.shape[:2], bool)
    pad[lb.top : lb.top + lb.new_height, lb.left : lb.left + lb.new_width] = False
    img[pad] = 0
    return img


def collate(batch: list[dict]) -> dict:
    out = {}
    for k in batch[0]:
        v = [b[k] for b in batch]
        out[k] = torch.stack(v) if isinstance(v[0], torch.Tensor) else torch.tensor(v)
    return out
