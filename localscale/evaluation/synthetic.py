"""HPatches-layout sequences from any photos, with random strong-perspective homographies.

Each photo gives one sequence folder ``<out>/s_<stem>/``: ``1.png`` (the photo, resized
so its longer side is ``size``) and ``2.png .. {n}.png``, each the photo warped by a
random homography ``H_1_k`` (``localscale.geometry.sample_homography``, perspective and
scale ranges of :data:`STRONG`), the uncovered part filled from another photo (as in
the scale networks' training data, so there are no artificial black borders), plus the
plain-text ``H_1_k`` files (HPatches convention: pixel coords of image 1 -> image k).
With ``crop < 1`` image 1 is the central ``crop`` part of the photo and image k is rendered
from the *whole* photo, so around image 1's content it shows the photo's real surroundings,
as a second real view would (the fill photo only covers what lies beyond the photo).
Homographies whose co-visible part of image 1 is below ``min_covisible`` are redrawn.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence, Union

import cv2
import numpy as np

from ..geometry import HomographyConfig, central_crop, covisible_mask, sample_homography, translation, warp_image
from ..io import load_image

#: default sampler: strong perspective, zoom in and out
STRONG = HomographyConfig(scale_range=(0.3, 3.5), rotation_deg=15.0, skew=0.1, perspective=0.6, translation=0.1)


def resize_max_side(img: np.ndarray, size: int) -> np.ndarray:
    s = size / max(img.shape[:2])
    if abs(s - 1) < 1e-6:
        return img
    interp = cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR
    return cv2.resize(img, (max(16, round(img.shape[1] * s)), max(16, round(img.shape[0] * s))), interpolation=interp)


def random_homography(
    rng: np.random.Generator,
    shape: tuple[int, int],
    cfg: HomographyConfig = STRONG,
    min_covisible: float = 0.25,
    tries: int = 20,
) -> np.ndarray:
    """A random homography from a ``shape`` image to one of the same shape, redrawn (up to
    ``tries`` times) until at least ``min_covisible`` of the first image stays visible."""
    for _ in range(tries):
        H = sample_homography(rng, shape, shape, cfg)
        if covisible_mask(H, shape, shape, 8).mean() >= min_covisible:
            break
    return H


def random_pair(
    rng: np.random.Generator,
    img: np.ndarray,
    fill: np.ndarray | None = None,
    cfg: HomographyConfig = STRONG,
    min_covisible: float = 0.25,
    tries: int = 20,
):
    """``(B, H)``: ``img`` warped by a random homography with enough overlap (B has img's shape)."""
    H = random_homography(rng, img.shape[:2], cfg, min_covisible, tries)
    b, _ = warp_image(img, H, img.shape[:2], fill=fill)
    return b, H


def make_sequences(
    photos: Sequence[Union[str, Path, np.ndarray]],
    out: Union[str, Path],
    num_images: int = 6,
    size: int = 480,
    seed: int = 0,
    cfg: HomographyConfig = STRONG,
    crop: float = 1.0,
) -> list[Path]:
    """Write one HPatches-style sequence per photo; returns the sequence folders.

    ``crop`` in (0, 1]: image 1 is the central part of this side fraction (longer side ``size``),
    the other images show the whole photo around it (module docstring).
    """
    if not 0 < crop <= 1:
        raise ValueError(f"crop must be in (0, 1], got {crop}")
    out = Path(out)
    rng = np.random.default_rng(seed)
    imgs = [resize_max_side(load_image(p, f"photo {i}"), round(size / crop)) for i, p in enumerate(photos)]
    folders = []
    for i, img in enumerate(imgs):
        name = Path(photos[i]).stem if isinstance(photos[i], (str, Path)) else f"{i:03d}"
        d = out / f"s_{name}"
        d.mkdir(parents=True, exist_ok=True)
        full = img
        img, (x0, y0) = central_crop(full, crop) if crop < 1 else (full, (0, 0))
        cv2.imwrite(str(d / "1.png"), img[..., ::-1])
        for k in range(2, num_images + 1):
            fill = imgs[(i + k) % len(imgs)] if len(imgs) > 1 else None
            if fill is not None and crop < 1:
                fill = resize_max_side(fill, size)
            H = random_homography(rng, img.shape[:2], cfg)
            # rendered from the whole photo: H on image 1's pixels is H @ shift on the photo's
            b, _ = warp_image(full, H @ translation(-x0, -y0), img.shape[:2], fill=fill)
            cv2.imwrite(str(d / f"{k}.png"), b[..., ::-1])
            np.savetxt(d / f"H_1_{k}", H, fmt="%.10g")
        folders.append(d)
    return folders
