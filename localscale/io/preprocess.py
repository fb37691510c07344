"""Letterboxing: fit any image into the fixed ``size x size`` processing frame.

The image is resized (aspect ratio kept) so its longer side equals ``size`` and padded
with zeros, centred. :class:`Letterbox` records the mapping so that scales predicted in
the processing frame can be corrected back to the original images:
``S_orig = S_proc * f_A / f_B`` where ``f`` is each image's resize factor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch


@dataclass(frozen=True)
class Letterbox:
    """Placement of an original ``height x width`` image inside the ``size x size`` frame."""

    height: int
    width: int
    size: int
    new_height: int
    new_width: int
    top: int
    left: int

    @property
    def fx(self) -> float:
        return self.new_width / self.width

    @property
    def fy(self) -> float:
        return self.new_height / self.height

    @property
    def factor(self) -> float:
        """Linear resize factor (geometric mean of x and y)."""
        return math.sqrt(self.fx * self.fy)

    def matrix(self) -> np.ndarray:
        """3x3 map from original pixel coordinates to processing-frame coordinates."""
        return np.array(
            [[self.fx, 0, self.left + 0.5 * self.fx - 0.5], [0, self.fy, self.top + 0.5 * self.fy - 0.5], [0, 0, 1]],
            dtype=np.float64,
        )

    def valid_mask(self, stride: int = 1) -> np.ndarray:
        """Grid cells (at ``stride``) whose centre lies on the image, not the padding."""
        n = math.ceil(self.size / stride)
        c = np.arange(n) * stride + (stride - 1) / 2
        my = (c >= self.top - 0.5) & (c <= self.top + self.new_height - 0.5)
        mx = (c >= self.left - 0.5) & (c <= self.left + self.new_width - 0.5)
        return my[:, None] & mx[None, :]


def make_letterbox(height: int, width: int, size: int) -> Letterbox:
    f = size / max(height, width)
    nh, nw = max(1, min(size, round(height * f))), max(1, min(size, round(width * f)))
    return Letterbox(height, width, size, nh, nw, (size - nh) // 2, (size - nw) // 2)


def letterbox(
    image: np.ndarray, size: int, original_shape: tuple[int, int] | None = None
) -> tuple[np.ndarray, Letterbox]:
    """Resize + pad an ``H x W x C`` image (uint8, or float32 in [0, 1]) into ``size x size``
    (zeros outside), keeping its dtype.

    ``original_shape``: ``(H, W)`` of the original when ``image`` is a reduced copy of it (see
    :func:`localscale.io.load_image_reduced`); the placement is then that of the original.
    """
    lb = make_letterbox(*(original_shape or image.shape[:2]), size)
    interp = cv2.INTER_AREA if lb.new_width < image.shape[1] else cv2.INTER_LINEAR
    resized = cv2.resize(image, (lb.new_width, lb.new_height), interpolation=interp)
    out = np.zeros((size, size) + image.shape[2:], dtype=image.dtype)
    out[lb.top : lb.top + lb.new_height, lb.left : lb.left + lb.new_width] = resized
    return out, lb


def to_tensor(image: np.ndarray) -> torch.Tensor:
    """``H x W x 3`` uint8 (divided by 255) or float in [0, 1] (as it is, at full precision)
    -> ``3 x H x W`` float32 in [0, 1]."""
    t = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)
    return t.float().div_(255.0) if image.dtype == np.uint8 else t.float()
