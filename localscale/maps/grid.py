"""Full-resolution maps from maps on the network's processing grid, in bounded memory.

A network predicts ``C x h x w`` maps on the grid of its ``P x P`` processing frame (``h = P/8``).
:class:`GridMaps` turns them into maps at the original image's resolution exactly as
:func:`localscale.models.base.upsample_to_original` does (bilinear to ``P x P``, crop the image's
region out of the padding, bilinear to ``H x W``, ``align_corners=False``), but row band by row
band: a full map costs its own ``4 bytes`` per pixel and nothing more, a band or a strided sample
costs only its size, and a map can go to a ``.npy`` file without ever being whole in memory.

Example::

    maps = GridMaps(grid, letterbox, transforms=(np.exp, None))   # channel 0: log scale
    scale = maps.full(0)                    # H x W float32
    for y0, band in maps.bands(0):          # rows y0 .. y0 + len(band)
        ...
    preview = maps.sampled(0, step=4)       # == maps.full(0)[::4, ::4]
"""

from __future__ import annotations

from typing import Callable, Iterator, Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..io.preprocess import Letterbox

#: elements per band (rows x width) of the band-wise read-out
BAND_ELEMENTS = 1 << 21


def _axis_weights(out_size: int, in_size: int, index: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Source indices and weights of bilinear resizing (``align_corners=False``, as PyTorch) for
    the output positions ``index`` of an axis of ``out_size`` read from one of ``in_size``."""
    src = (index.astype(np.float64) + 0.5) * (in_size / out_size) - 0.5
    src = np.maximum(src, 0.0)
    i0 = np.minimum(np.floor(src).astype(np.int64), in_size - 1)
    i1 = np.minimum(i0 + 1, in_size - 1)
    w1 = (src - i0).astype(np.float32)
    return i0, i1, w1


class GridMaps:
    """``C`` maps on a processing grid, read out at the original resolution of an image.

    Args:
        grid: ``C x h x w`` tensor on the processing grid of the frame ``letterbox`` describes.
        letterbox: where the original ``H x W`` image sits in the ``P x P`` frame.
        transforms: per channel, a function applied to the interpolated values (e.g. ``np.exp``
            for a log-scale channel, a clip for probabilities) or None.
    """

    def __init__(
        self,
        grid: torch.Tensor,
        letterbox: Letterbox,
        transforms: Sequence[Optional[Callable[[np.ndarray], np.ndarray]]] = (),
    ):
        if grid.dim() != 3:
            raise ValueError(f"GridMaps: expected a C x h x w grid, got shape {tuple(grid.shape)}")
        lb = letterbox
        x = F.interpolate(
            grid.detach().float().cpu()[None], size=(lb.size, lb.size), mode="bilinear", align_corners=False
        )[0]
        self.source = x[:, lb.top : lb.top + lb.new_height, lb.left : lb.left + lb.new_width].numpy()
        self.letterbox = lb
        self.transforms = list(transforms) + [None] * (grid.shape[0] - len(transforms))
        self._cols = _axis_weights(lb.width, self.source.shape[2], np.arange(lb.width))

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of the original image."""
        return self.letterbox.height, self.letterbox.width

    def finite(self) -> bool:
        """True when every grid value is finite (then so is every read-out value)."""
        return bool(np.isfinite(self.source).all())

    def _read(self, channel: int, rows: np.ndarray, cols: tuple) -> np.ndarray:
        src = self.source[channel]
        r0, r1, wr = _axis_weights(self.letterbox.height, src.shape[0], rows)
        band = src[r0] * (1 - wr)[:, None] + src[r1] * wr[:, None]
        c0, c1, wc = cols
        out = band[:, c0] * (1 - wc) + band[:, c1] * wc
        f = self.transforms[channel]
        return np.asarray(f(out) if f is not None else out, np.float32)

    def rows(self, channel: int, y0: int, y1: int) -> np.ndarray:
        """Rows ``y0 .. y1-1`` of a channel at full resolution: ``(y1 - y0) x W`` float32."""
        return self._read(channel, np.arange(y0, y1), self._cols)

    def band_rows(self, max_elements: int = BAND_ELEMENTS) -> int:
        return max(1, max_elements // max(1, self.letterbox.width))

    def bands(self, channel: int, max_elements: int = BAND_ELEMENTS) -> Iterator[tuple[int, np.ndarray]]:
        """``(y0, rows)`` row bands covering the full-resolution channel, each of at most
        ``max_elements`` values (and at least one row)."""
        step = self.band_rows(max_elements)
        for y0 in range(0, self.letterbox.height, step):
            yield y0, self.rows(channel, y0, min(self.letterbox.height, y0 + step))

    def full(self, channel: int) -> np.ndarray:
        """The whole channel at full resolution, ``H x W`` float32, filled band by band."""
        out = np.empty(self.shape, np.float32)
        for y0, band in self.bands(channel):
            out[y0 : y0 + len(band)] = band
        return out

    def sampled(self, channel: int, step: int) -> np.ndarray:
        """``full(channel)[::step, ::step]``, computed without the full map."""
        h, w = self.shape
        cols = _axis_weights(w, self.source.shape[2], np.arange(0, w, step))
        return self._read(channel, np.arange(0, h, step), cols)

    def sample_step(self, max_pixels: int) -> int:
        """The smallest stride whose :meth:`sampled` map has at most ``max_pixels`` pixels."""
        h, w = self.shape
        step = 1
        while -(-h // step) * -(-w // step) > max_pixels:
            step += 1
        return step
