"""HPatches-layout sequences and their ``(1, k)`` pairs: loading, checks and splits.

A sequence is a folder ``<root>/<seq>/`` with images ``1.ppm .. 6.ppm`` (also ``.png`` / ``.jpg``...)
and homographies ``H_1_2 .. H_1_6`` (:func:`load_hpatches`); :func:`make_pairs` makes its pairs
``(1, k)`` with their perspective / scale / rotation splits (:mod:`.report`) and leaves out, with a
warning, those that cannot be evaluated; :func:`content_agreement` tells whether a homography
belongs to the images it is given with.
"""

from __future__ import annotations

import math
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Optional, Sequence

import cv2
import numpy as np

from ..core.errors import HomographyError, LocalScaleError
from ..geometry import covisible_mask, global_scale, homography_rotation, orient_homography, perspective_spread
from ..io import read_homography
from .report import perspective_split, rotation_split, scale_split

#: the high-resolution sequences of HPatches (``--exclude-hires``)
HIGH_RES = (
    "i_contruction",
    "i_crownnight",
    "i_dc",
    "i_pencils",
    "i_whitebuilding",
    "v_artisans",
    "v_astronautis",
    "v_talent",
)
IMAGE_EXTS = (".ppm", ".png", ".jpg", ".jpeg", ".pgm", ".bmp", ".tif", ".tiff")


@dataclass
class HSequence:
    name: str
    images: dict  #: index -> path
    homographies: dict  #: k -> H_1_k
    bad: dict = field(default_factory=dict)  #: k -> why pair (1, k) cannot be evaluated (bad H_1_k)


@dataclass
class PairInfo:
    sequence: str
    k: int
    image_a: Path
    image_b: Path
    H: np.ndarray
    spread: float = 0.0
    log2_scale: float = 0.0
    perspective_split: str = ""
    scale_split: str = ""
    covisible: float = 0.0
    rotation: float = 0.0
    rotation_split: str = ""

    @property
    def name(self) -> str:
        return f"{self.sequence}/1-{self.k}"


def _find_image(folder: Path, index: int) -> Optional[Path]:
    for ext in IMAGE_EXTS:
        for cand in (folder / f"{index}{ext}", folder / f"{index}{ext.upper()}"):
            if cand.is_file():
                return cand
    return None


def load_hpatches(
    root,
    include_illumination: bool = False,
    exclude_hires: bool = False,
    exclude: Iterable[str] = (),
    sequences: Optional[Iterable[str]] = None,
) -> list[HSequence]:
    """Sequences of an HPatches-layout folder (sorted by name).

    A sub-folder counts as a sequence when it has image ``1.*`` and at least one ``H_1_k``
    with image ``k.*``. ``i_*`` are skipped unless ``include_illumination``.
    """
    root = Path(root)
    if not root.is_dir():
        raise LocalScaleError(f"HPatches root not found: {root}")
    exclude = set(exclude) | (set(HIGH_RES) if exclude_hires else set())
    wanted = set(sequences) if sequences is not None else None
    out = []
    for d in sorted(p for p in root.iterdir() if p.is_dir()):
        if d.name in exclude or (wanted is not None and d.name not in wanted):
            continue
        if d.name.startswith("i_") and not include_illumination:
            continue
        first = _find_image(d, 1)
        if first is None:
            continue
        images, Hs, bad = {1: first}, {}, {}
        for hf in sorted(d.glob("H_1_*")):
            m = re.fullmatch(r"H_1_(\d+)", hf.name)
            if not m:
                continue
            k = int(m.group(1))
            img = _find_image(d, k)
            if img is None:
                continue
            images[k] = img
            try:
                Hs[k] = read_homography(hf)
            except HomographyError as e:
                bad[k] = " ".join(str(e).split())
        if Hs or bad:
            out.append(HSequence(d.name, images, Hs, bad))
    if not out:
        raise LocalScaleError(f"no sequences (folders with 1.ppm/png/jpg and H_1_k files) in {root}")
    return out


def _warn(message: str) -> None:
    """One ``warning: ...`` line on stderr (beside a progress bar)."""
    from tqdm import tqdm

    tqdm.write(f"warning: {' '.join(message.split())}", file=sys.stderr)


def image_size(path: Path) -> tuple[int, int]:
    """``(height, width)`` from the file header: :func:`localscale.io.header_shape`."""
    from ..io import header_shape

    return header_shape(path)


#: a pair whose GT homography maps less than this fraction of image 1 into image k is warned about
MIN_COVISIBLE = 0.05


def make_pairs(seqs: Sequence[HSequence], skipped: Optional[list] = None) -> list[PairInfo]:
    """All ``(1, k)`` pairs with their perspective / scale splits.

    Pairs that cannot be evaluated (bad ``H_1_k``, an image whose size cannot be read or is too
    small, an ``H`` that maps all of image 1 outside image k) are left out with a warning and
    appended to ``skipped`` as ``{"pair", "reason"}``; a pair where ``H`` maps less than
    :data:`MIN_COVISIBLE` of image 1 into image k is kept with a warning.
    """
    pairs = []
    skipped = [] if skipped is None else skipped

    def skip(name, reason):
        reason = " ".join(str(reason).split())
        _warn(f"pair {name} skipped: {reason}")
        skipped.append({"pair": name, "reason": reason})

    for s in seqs:
        for k, why in sorted(s.bad.items()):
            skip(f"{s.name}/1-{k}", why)
        try:
            sa = image_size(s.images[1])
        except LocalScaleError as e:
            for k in sorted(s.homographies):
                skip(f"{s.name}/1-{k}", e)
            continue
        for k, H in sorted(s.homographies.items()):
            name = f"{s.name}/1-{k}"
            try:
                sb = image_size(s.images[k])
            except LocalScaleError as e:
                skip(name, e)
                continue
            H = orient_homography(H, sa)
            covisible = float(covisible_mask(H, sa, sb, 8).mean())
            if not covisible > 0:
                skip(
                    name,
                    f"H_1_{k} maps all of image 1 outside image {k} ({sb[1]}x{sb[0]}): check that H and "
                    f"the images belong together",
                )
                continue
            if covisible < MIN_COVISIBLE:
                _warn(
                    f"pair {name}: H_1_{k} maps only {covisible:.1%} of image 1 into image {k}; "
                    f"check that H and the image sizes belong together"
                )
            p = PairInfo(s.name, k, s.images[1], s.images[k], H)
            p.spread = perspective_spread(H, sa, sb)
            try:
                p.log2_scale = math.log2(global_scale(H, sa, sb))
            except ValueError:
                p.log2_scale = float("nan")
            p.covisible = covisible
            p.rotation = homography_rotation(H, sa)
            p.perspective_split, p.scale_split = perspective_split(p.spread), scale_split(p.log2_scale)
            p.rotation_split = rotation_split(p.rotation)
            pairs.append(p)
    return pairs


#: :func:`content_agreement` below this is warned about (the Oxford and HPatches pairs of
#: ``docs/RESULTS.md`` give 0.5-1.0; the same pairs with image k at half the size H expects, <= 0.15)
MIN_AGREEMENT = 0.25


def content_agreement(a: np.ndarray, b: np.ndarray, H: np.ndarray, side: int = 192) -> float:
    """Correlation of image-1 gradients with those of image k warped into image 1 by ``H``, over the
    co-visible region, at ``side`` px: near 0 when ``H`` does not belong to the images (e.g. an image
    of another size than the one ``H`` was measured on), 1 for a perfect fit. NaN-free; 1.0 when
    too little is co-visible to tell."""
    f = side / max(a.shape[:2])
    fb = side / max(b.shape[:2])
    S = np.diag([f, f, 1.0]) @ np.asarray(H, np.float64) @ np.diag([1 / f, 1 / f, 1.0])
    S = np.diag([fb / f, fb / f, 1.0]) @ S
    ga = cv2.cvtColor(
        cv2.resize(a, (max(1, round(a.shape[1] * f)), max(1, round(a.shape[0] * f))), interpolation=cv2.INTER_AREA),
        cv2.COLOR_RGB2GRAY,
    ).astype(np.float32)
    gb = cv2.cvtColor(
        cv2.resize(b, (max(1, round(b.shape[1] * fb)), max(1, round(b.shape[0] * fb))), interpolation=cv2.INTER_AREA),
        cv2.COLOR_RGB2GRAY,
    ).astype(np.float32)
    size = (ga.shape[1], ga.shape[0])
    warped = cv2.warpPerspective(gb, S, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    cover = cv2.warpPerspective(np.ones_like(gb), S, size, flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP)
    mask = cv2.erode(cover, np.ones((5, 5), np.uint8)) > 0.5
    if mask.sum() < 200:
        return 1.0

    def grad(g):
        g = cv2.GaussianBlur(g, (0, 0), 1.0)
        return np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))

    x, y = grad(ga)[mask], grad(warped)[mask]
    x, y = x - x.mean(), y - y.mean()
    den = float(np.sqrt((x * x).sum() * (y * y).sum()))
    return float((x * y).sum() / den) if den > 0 else 1.0
