"""Pictures of matches: two images side by side, the matches drawn between them."""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Union

import cv2
import numpy as np

from ..core.errors import LocalScaleError
from ..io import load_working_image
from .metrics import reprojection_errors
from .result import MatchResult

#: default working resolution of pictures (longer side, pixels)
MAX_SIDE = 2048
#: file types :func:`draw_matches` writes
PICTURE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")


def draw_matches(
    image_a,
    image_b,
    result: MatchResult,
    path: Union[str, Path, None] = None,
    threshold: float = 5.0,
    max_lines: int = 500,
    max_side: Optional[int] = MAX_SIDE,
) -> np.ndarray:
    """Side-by-side picture; with ``H`` inliers (error < ``threshold``) green, outliers red,
    else all matches yellow. Images larger than ``max_side`` are drawn at that size. Returns the
    RGB canvas and writes it to ``path`` (``.png``, ``.jpg``, ``.tif``, ``.bmp``, ``.webp``) if given.

    Raises :class:`LocalScaleError` when ``path`` is a folder or has another extension, and when
    the result's keypoints do not fit these images (a result of another pair)."""
    if path is not None:
        path = _picture_path(path)
    a, to_a = load_working_image(image_a, max_side, "image A")
    b, to_b = load_working_image(image_b, max_side, "image B")
    _check_keypoints(result, a, to_a, b, to_b)
    canvas = _side_by_side(a, b)
    m, ok = _shown_matches(result, threshold, max_lines)
    lw = max(1, round(max(canvas.shape) / 800))
    kpa = result.keypoints_a * np.diag(to_a)[:2] + to_a[:2, 2]
    kpb = result.keypoints_b * np.diag(to_b)[:2] + to_b[:2, 2]
    for i, (ia, ib) in enumerate(m):
        pa = tuple(int(round(v)) for v in kpa[ia])
        pb = kpb[ib]
        pb = (int(round(pb[0])) + a.shape[1], int(round(pb[1])))
        colour = (255, 220, 0) if ok is None else ((0, 220, 0) if ok[i] else (230, 0, 0))
        cv2.line(canvas, pa, pb, colour, lw, cv2.LINE_AA)
        cv2.circle(canvas, pa, 2 * lw, colour, -1)
        cv2.circle(canvas, pb, 2 * lw, colour, -1)
    _draw_label(canvas, result, lw)
    if path is not None:
        _write_picture(path, canvas)
    return canvas


def _picture_path(path) -> Path:
    """``path`` as a :class:`Path`; refuses a folder and a name without a picture suffix."""
    path = Path(path)
    if path.is_dir():
        raise LocalScaleError(f"cannot write picture {path}: an existing folder has that name (give a file name)")
    if path.suffix.lower() not in PICTURE_SUFFIXES:
        raise LocalScaleError(f"picture {path}: the name must end in one of {', '.join(PICTURE_SUFFIXES)}")
    return path


def _check_keypoints(result: MatchResult, a: np.ndarray, to_a: np.ndarray, b: np.ndarray, to_b: np.ndarray) -> None:
    """Refuse a result whose keypoints lie outside the full images of ``a`` / ``b`` (a result of another pair)."""
    for name, kp, S, img in (("A", result.keypoints_a, to_a, a), ("B", result.keypoints_b, to_b, b)):
        full_w, full_h = (img.shape[1] + 1) / S[0, 0] - 1, (img.shape[0] + 1) / S[1, 1] - 1
        kp = np.asarray(kp, np.float64).reshape(-1, 2)
        if len(kp) and (kp.min() < -2 or kp[:, 0].max() > full_w + 2 or kp[:, 1].max() > full_h + 2):
            raise LocalScaleError(
                f"the result's keypoints of {name} lie outside image {name} "
                f"({full_w + 1:.0f} x {full_h + 1:.0f} px): it belongs to other images"
            )


def _side_by_side(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A beside B on a black canvas, darkened so that the lines stand out."""
    h = max(a.shape[0], b.shape[0])
    canvas = np.zeros((h, a.shape[1] + b.shape[1], 3), np.uint8)
    canvas[: a.shape[0], : a.shape[1]] = a
    canvas[: b.shape[0], a.shape[1] :] = b
    return (canvas.astype(np.float32) * 0.7).astype(np.uint8)


def _shown_matches(result: MatchResult, threshold: float, max_lines: int) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """The matches drawn (at most ``max_lines``, a fixed random sample) and whether each is an inlier
    (``None`` without errors)."""
    m = result.matches
    if len(m) > max_lines:
        m = m[np.random.default_rng(0).choice(len(m), max_lines, replace=False)]
    ok = None
    if result.errors is not None:
        err = (
            reprojection_errors(result.keypoints_a, result.keypoints_b, m, result.H)
            if result.H is not None
            else result.errors[: len(m)]
        )
        ok = err < threshold
    return m, ok


def _draw_label(canvas: np.ndarray, result: MatchResult, lw: int) -> None:
    """The matcher, correction (``auto``'s choice) and number of matches in the top-left corner."""
    label = " / ".join(str(x) for x in (result.meta.get("matcher"), result.correction) if x)
    if "auto" in result.meta:
        auto = result.meta["auto"]
        label += f" ({auto['chosen']}{'' if auto['verified'] else ', not verified'})"
    cv2.putText(
        canvas,
        f"{label}: {len(result.matches)} matches",
        (8, 8 + 14 * lw),
        cv2.FONT_HERSHEY_SIMPLEX,
        0.5 * lw,
        (255, 255, 255),
        lw,
        cv2.LINE_AA,
    )


def _write_picture(path: Path, canvas: np.ndarray) -> None:
    """Write the RGB ``canvas`` to ``path``, creating its folder."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise LocalScaleError(f"cannot create folder {path.parent}: {e.strerror or e}") from None
    from ..core.outputs import write_image

    write_image(path, canvas[..., ::-1])
