"""The output of a Local-ScaleNet: per-pixel maps kept on the processing grid
(:class:`LocalScalePrediction`, :class:`LocalScaleBatch`), and the calibrated reliability of a
scale distribution (:func:`reliability`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import numpy as np
import torch

from .. import scales
from ..io.preprocess import Letterbox
from ..maps import GridMaps
from .base import as_numpy, upsample_to_original


def _clip01(x: np.ndarray) -> np.ndarray:
    return np.clip(x, 0, 1, out=x)


#: channels of :class:`LocalScalePrediction`'s grid and how each is read out at full resolution
_CHANNELS = {"scale": np.exp, "confidence": _clip01, "visible": _clip01, "reliability": _clip01}


class LocalScalePrediction:
    """Output of :meth:`LocalScaleNet.predict`.

    The maps are kept on the network's processing grid and read out at A's original resolution
    when first used (then cached), band by band: a full map costs its own 4 bytes per pixel and
    no temporaries. :meth:`bands` and :meth:`sampled` read a map without making it whole.

    Attributes:
        scale: ``H_A x W_A`` float32, ``S_{A->B}`` per pixel of A (original resolution).
        confidence: ``H_A x W_A`` in [0, 1], ``1 - entropy / ln 13`` of the distribution.
        probs: ``13 x h x w`` distributions on the processing grid of A (``h = w = P/8``).
        letterbox_a, letterbox_b: placement of the images in the processing frame.
        visible: ``H_A x W_A`` in [0, 1], the probability that each pixel of A is visible in B
            (None for a model without the visibility output). The scale is meaningful only there.
        reliability: ``H_A x W_A`` in [0, 1], the calibrated probability that the scale at a
            pixel is within a factor 1.25 of the truth (None for an uncalibrated model).
        maps: the :class:`~localscale.maps.GridMaps` behind them (channels in :attr:`channels`).
    """

    def __init__(
        self,
        grid: torch.Tensor,
        channels: tuple[str, ...],
        probs: torch.Tensor,
        letterbox_a: Letterbox,
        letterbox_b: Letterbox,
        meta: dict | None = None,
    ):
        self.channels = tuple(channels)
        self.maps = GridMaps(grid, letterbox_a, [_CHANNELS[c] for c in self.channels])
        self.probs = probs
        self.letterbox_a, self.letterbox_b = letterbox_a, letterbox_b
        self.meta = meta if meta is not None else {}
        self._full: dict[str, np.ndarray] = {}

    def has(self, name: str) -> bool:
        return name in self._full or name in self.channels

    def full(self, name: str) -> np.ndarray | None:
        """A map at full resolution (None when the model has no such output)."""
        if name not in self._full:
            if name not in self.channels:
                return None
            self._full[name] = self.maps.full(self.channels.index(name))
        return self._full[name]

    def bands(self, name: str) -> Iterator[tuple[int, np.ndarray]]:
        """``(y0, rows)`` row bands of a map at full resolution, without making it whole."""
        if name in self._full:
            step = self.maps.band_rows()
            for y0 in range(0, self._full[name].shape[0], step):
                yield y0, self._full[name][y0 : y0 + step]
        else:
            yield from self.maps.bands(self.channels.index(name))

    def sampled(self, name: str, max_pixels: int = 4_000_000) -> np.ndarray:
        """A map on every ``k``-th pixel (``full(name)[::k, ::k]``, ``k`` the smallest stride with at
        most ``max_pixels`` pixels; ``k = 1`` for images up to that size)."""
        step = self.maps.sample_step(max_pixels)
        if name in self._full:
            return self._full[name][::step, ::step]
        return self.maps.sampled(self.channels.index(name), step)

    def finite(self) -> bool:
        """True when every map is finite."""
        return self.maps.finite() and all(np.isfinite(m).all() for m in self._full.values())

    @property
    def scale(self) -> np.ndarray:
        return self.full("scale")

    @scale.setter
    def scale(self, value: np.ndarray) -> None:
        self.set_map("scale", value)

    def set_map(self, name: str, value: np.ndarray) -> None:
        """Replace a map by a full-resolution ``H_A x W_A`` array (used by read-outs that change it)."""
        shape = (self.letterbox_a.height, self.letterbox_a.width)
        if np.shape(value) != shape:
            raise ValueError(f"{name}: expected a {shape[0]} x {shape[1]} map, got {np.shape(value)}")
        self._full[name] = value

    @property
    def confidence(self) -> np.ndarray:
        return self.full("confidence")

    @property
    def visible(self) -> np.ndarray | None:
        return self.full("visible")

    @property
    def reliability(self) -> np.ndarray | None:
        return self.full("reliability")

    @property
    def log2_scale(self) -> np.ndarray:
        return np.log2(self.scale)

    def distribution(self) -> np.ndarray:
        """Per-pixel distribution at A's original resolution: ``13 x H_A x W_A`` (bins shifted
        by the letterbox correction are not re-binned; use :attr:`scale` for values)."""
        return as_numpy(upsample_to_original(self.probs, self.letterbox_a))


@dataclass
class LocalScaleBatch:
    """Output of :meth:`LocalScaleNet.predict_batch`: ``B x H_A x W_A`` maps (tensors on the
    input's device, or numpy arrays for numpy input; no batch axis for one unbatched pair).

    Attributes:
        scale: ``S_{A->B}`` per pixel of each A.
        confidence: ``1 - entropy / ln 13``, in [0, 1].
        visible: visibility probability of each pixel of A in B (None without that output).
        reliability: calibrated ``P(r < 1.25)`` (None for an uncalibrated model).
        probs: ``B x 13 x h x w`` distributions on the processing grid of A.
    """

    scale: torch.Tensor | np.ndarray
    confidence: torch.Tensor | np.ndarray
    visible: torch.Tensor | np.ndarray | None = None
    reliability: torch.Tensor | np.ndarray | None = None
    probs: torch.Tensor | np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.scale)


def reliability_features(probs: torch.Tensor, visible: torch.Tensor | None, dim: int = 1) -> torch.Tensor:
    """Per-pixel features of the reliability calibration, stacked on ``dim``: the entropy
    confidence, the visibility probability (1 when the model has none) and the spread of the
    distribution (std of ``log2 s`` in bins). ``probs``: ``... x 13 x ...`` -> ``... x 3 x ...``."""
    conf = scales.confidence(probs, dim)
    log2 = scales.bin_scales().to(probs).log2().view([-1 if d == dim % probs.dim() else 1 for d in range(probs.dim())])
    mean = (probs * log2).sum(dim, keepdim=True)
    spread = ((probs * (log2 - mean) ** 2).sum(dim)).clamp_min(0).sqrt()
    vis = visible if visible is not None else torch.ones_like(conf)
    return torch.stack([conf, vis.to(conf), spread], dim % probs.dim())


def reliability(
    probs: torch.Tensor, visible: torch.Tensor | None, calibration: tuple[float, ...], dim: int = 1
) -> torch.Tensor:
    """Calibrated ``P(r < 1.25)`` per pixel from :func:`reliability_features`."""
    f = reliability_features(probs, visible, dim)
    w = torch.tensor(calibration[1:], dtype=f.dtype, device=f.device)
    w = w.view([-1 if d == dim % f.dim() else 1 for d in range(f.dim())])
    return torch.sigmoid(calibration[0] + (f * w).sum(dim % f.dim()))
