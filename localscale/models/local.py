"""Local-ScaleNet: a dense, per-pixel scale distribution between two images.

Pipeline (paper appendix "Local-ScaleNet")::

    A, B --letterbox--> P x P --VGG16/8 + ASPP--> f_A, f_B (L2-normalised)
    c_A  = corr(f_A, f_A),  c_AB = corr(f_A, f_B)     (ReLU + L2 norm)
    c'_A, c'_AB = Reduction(c_A), Reduction(c_AB)      (Conv-BN-ReLU x 4 each)
    logits = DenseHead(concat(c'_A, c'_AB))            (B x 13 x P/8 x P/8)

The soft-scale map is corrected for the two letterbox factors and resized to A's
original resolution. There is no consistency check (B->A is not aligned with A).

Beyond the paper (optional, on in the shipped model): the reduced volumes see B's cells as
*channels*, so a 1x1 conv must learn the same "how spread is my match" rule separately for
every position of B. Two position-invariant cues make that explicit: the ``topk`` largest
cross- and self-correlations of each pixel of A (sorted, so independent of where the match
is), and B's features soft-warped onto A through the correlation, next to A's own (how the
matched content looks at the two scales). Measured on identical data: training loss 1.59 at
step 250 with the cues vs 1.71 without (the paper-only model needed ~1300 steps for 1.59).

Example::

    net = LocalScaleNet.from_pretrained()
    pred = net.predict("a.jpg", "b.jpg")
    pred.scale  # H_A x W_A, > 1 where content looks bigger in B
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterator

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from .. import scales
from ..geometry.planar import planarize
from ..io import ImageLike
from ..maps import GridMaps
from ..preprocess import Letterbox
from .anchor import Anchor, anchor_of
from .backbones import check_backbone_name
from .base import EncodedImage, ScaleModel, as_numpy, upsample_to_original
from .common import ReductionBlock, conv_bn_relu, correlation, normalise_correlation, warped_pair_features
from .registry import register

#: the bundled ScaleNet that anchors predictions, loaded once per device
_BUNDLED_ANCHORS: dict = {}


@dataclass
class LocalScaleNetConfig:
    width: float = 0.25  #: VGG16 channel multiplier
    feature_dim: int = 128  #: ASPP output channels
    image_size: int = 192  #: processing frame P (multiple of 8)
    reduction: tuple[int, ...] = (128, 64, 64, 32)
    head_channels: int = 96
    batch_norm: bool = True
    #: position-invariant cues added beside the paper's reduced volumes (0 / False = paper only):
    #: the k largest cross- and self-correlations of each pixel of A (how spread its match is),
    topk: int = 0
    #: and B's features soft-warped onto A through the correlation (what the match looks like)
    warp_features: bool = False
    #: a second output: per pixel of A, the probability that it is visible in B
    visibility: bool = False
    #: logistic calibration of the per-pixel reliability, ``(bias, w_confidence, w_visible,
    #: w_spread)``: ``P(r < 1.25) = sigmoid(bias + w . features)``, fitted on held-out
    #: synthetic pairs after training (empty: not calibrated)
    calibration: tuple[float, ...] = ()
    #: feature backbone: "vgg" (trainable, ``width`` channels) or a frozen pre-trained one
    #: (``"xfeat"``, ``"aliked"``; :mod:`localscale.models.backbones`)
    backbone: str = "vgg"

    def __post_init__(self):
        self.reduction = tuple(self.reduction)
        check_backbone_name(self.backbone)
        self.calibration = tuple(float(c) for c in self.calibration)
        if self.calibration and len(self.calibration) != 4:
            raise ValueError(f"calibration needs 4 coefficients, got {len(self.calibration)}")
        if self.image_size % 8 or self.image_size < 64:
            raise ValueError(f"image_size must be a multiple of 8 and >= 64, got {self.image_size}")


class DenseHead(nn.Module):
    """Fully convolutional head: local context (dilated convs) + global context -> 13 logits/pixel."""

    def __init__(self, cin: int, channels: int, visibility: bool = False):
        super().__init__()
        self.context = conv_bn_relu(cin, channels, 1)
        self.body = nn.Sequential(
            conv_bn_relu(cin + channels, channels, 3),
            conv_bn_relu(channels, channels, 3, dilation=2),
            conv_bn_relu(channels, channels, 3, dilation=4),
            conv_bn_relu(channels, channels, 3),
        )
        self.out = nn.Conv2d(channels, scales.NUM_BINS, 1)
        self.visible = nn.Conv2d(channels, 1, 1) if visibility else None

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``B x C x h x w`` -> scale logits ``B x 13 x h x w`` and visibility logits ``B x 1 x h x w`` (or None)."""
        g = self.context(x.mean((2, 3), keepdim=True)).expand(-1, -1, *x.shape[-2:])
        y = self.body(torch.cat([x, g], 1))
        return self.out(y), (self.visible(y) if self.visible is not None else None)


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


@register
class LocalScaleNet(ScaleModel):
    """Dense Local-ScaleNet. See the module docstring for the pipeline."""

    arch = "LocalScaleNet"
    config_class = LocalScaleNetConfig
    default_weights = "local_scalenet.pt"

    def __init__(self, config: LocalScaleNetConfig | None = None, **overrides):
        config = config or LocalScaleNetConfig(**overrides)
        super().__init__(config)
        self._anchor: list = []  # [the ScaleNet of the anchored pass] (a list: not a submodule)
        n = self.grid_size**2
        self.reduce_self = ReductionBlock(n, config.reduction)
        self.reduce_cross = ReductionBlock(n, config.reduction)
        self.head = DenseHead(
            2 * config.reduction[-1] + self._build_cue_branches(n), config.head_channels, config.visibility
        )

    def forward_features(self, fa: torch.Tensor, fb: torch.Tensor) -> torch.Tensor:
        """Logits from encoded features: ``B x D x h x w`` (x2) -> ``B x 13 x h x w``."""
        return self.forward_features_all(fa, fb)[0]

    def self_terms(self, fa: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """What the head computes from A alone, reusable for every B: the reduced
        self-correlation ``B x C x h x w`` and (with ``topk``) A's ``k`` largest
        self-correlations ``B x k x h x w`` (else None)."""
        net = self._inference_model()
        if net is not self:
            return net.self_terms(fa)
        raw_a = correlation(fa, fa)
        top = raw_a.topk(self.topk, 1).values if self.topk else None
        return self.reduce_self(normalise_correlation(raw_a)), top

    def forward_features_all(
        self, fa: torch.Tensor, fb: torch.Tensor, terms_a: tuple[torch.Tensor, torch.Tensor | None] | None = None
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Scale logits ``B x 13 x h x w`` and visibility logits ``B x 1 x h x w`` (None without the
        visibility output) from encoded features; ``terms_a``: :meth:`self_terms` of ``fa``
        when already computed."""
        net = self._inference_model()
        if net is not self:
            return net.forward_features_all(fa, fb, terms_a)
        reduced_a, top_a = terms_a if terms_a is not None else self.self_terms(fa)
        raw_ab = correlation(fa, fb)
        parts = [reduced_a, self.reduce_cross(normalise_correlation(raw_ab))]
        if self.topk:
            parts.append(self.reduce_topk(torch.cat([raw_ab.topk(self.topk, 1).values, top_a], 1)))
        if self.config.warp_features:
            parts.append(self.reduce_warp(warped_pair_features(raw_ab, fa, fb)))
        return self.head(torch.cat(parts, 1))

    def forward(self, a: torch.Tensor, b: torch.Tensor, all_outputs: bool = False):
        """``B x 3 x P x P`` (x2, in [0, 1]) -> logits ``B x 13 x P/8 x P/8`` (processing frame);
        with ``all_outputs`` also the visibility logits ``B x 1 x P/8 x P/8`` (or None)."""
        out = self.forward_features_all(self.encode(a), self.encode(b))
        return out if all_outputs else out[0]

    @torch.inference_mode()
    def predict_from_features(
        self, ea: EncodedImage, eb: EncodedImage, hard: bool = False, bf16: bool = False, planar: bool = False
    ) -> LocalScalePrediction:
        """Scale map from two cached encodings (see :meth:`encode_image`); A's :meth:`self_terms`
        are kept in ``ea.terms`` for its later pairs."""
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=bf16):
            logits, vis = self.forward_features_all(ea.features, eb.features, self.cached_self_terms(ea, bf16))
        probs = F.softmax(logits.float(), 1)[0]
        visible = torch.sigmoid(vis.float())[0, 0] if vis is not None else None
        return self._readout(probs, ea.letterbox, eb.letterbox, hard, planar, visible)

    def cached_self_terms(self, enc: EncodedImage, bf16: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
        """:meth:`self_terms` of an encoding, computed once and kept in ``enc.terms``."""
        key = ("local_self_terms", bf16)
        if key not in enc.terms:
            with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=bf16):
                enc.terms[key] = self.self_terms(enc.features)
        return enc.terms[key]

    @torch.inference_mode()
    def predict(
        self,
        image_a: ImageLike,
        image_b: ImageLike,
        hard: bool = False,
        bf16: bool = False,
        planar: bool = False,
        anchor: bool | Anchor = True,
    ) -> LocalScalePrediction:
        """Per-pixel scale ``S_{A->B}`` between two images (paths or arrays, any size).

        Args:
            hard: D-ScaleNet read-out (arg-max bin) instead of the soft expectation.
            bf16: run the network under bfloat16 autocast (faster on CPUs with AMX).
            planar: replace the map by the best scale field of a homography (planar scenes
                only; see :mod:`localscale.geometry.planar`).
            anchor: ``True``: the pass is anchored on the global ScaleNet's scale and quarter
                turn (:mod:`localscale.anchoring`; ``pred.meta["anchor"]`` says how);
                an :class:`~localscale.models.anchor.Anchor`: anchored on that; ``False``: the
                plain one-pass map of both images letterboxed as they are.

        When exactly one image is gray, the other is turned gray before encoding.
        """
        if anchor is False:
            ea, eb = self.encode_pair(image_a, image_b, bf16)
            return self.predict_from_features(ea, eb, hard, bf16, planar)
        (a, shape_a), (b, shape_b) = self.load_pair(image_a, image_b)
        if not isinstance(anchor, Anchor):
            anchor = self.find_anchor(a, shape_a, b, shape_b, bf16)
        from ..anchoring import anchored_prediction

        return anchored_prediction(self, a, shape_a, b, shape_b, anchor, hard, bf16, planar)

    def anchor_model(self) -> ScaleModel:
        """The ScaleNet that anchors :meth:`predict`: the one given to :meth:`set_anchor_model`,
        else the bundled one on this model's device."""
        if self._anchor:
            return self._anchor[0]
        key = str(self.device)
        if key not in _BUNDLED_ANCHORS:
            from .scalenet import ScaleNet

            _BUNDLED_ANCHORS[key] = ScaleNet.from_pretrained(device=self.device)
        return _BUNDLED_ANCHORS[key]

    def set_anchor_model(self, model: ScaleModel | None) -> None:
        """Anchor :meth:`predict` on ``model`` (a ScaleNet; None: the bundled one)."""
        self._anchor[:] = [] if model is None else [model]

    def find_anchor(self, a: np.ndarray, shape_a, b: np.ndarray, shape_b, bf16: bool = False) -> Anchor:
        """ScaleNet's :class:`~localscale.models.anchor.Anchor` of two images as :meth:`load_pair`
        gives them."""
        return anchor_of(self.anchor_model().predict_loaded(a, shape_a, b, shape_b, bf16))

    @torch.inference_mode()
    def predict_batch(
        self, images_a, images_b, hard: bool = False, bf16: bool = False, batch_size: int | None = None
    ) -> LocalScaleBatch:
        """Per-pixel ``S_{A->B}`` for a batch of pairs, in one network pass per ``batch_size`` pairs.

        Args:
            images_a, images_b: ``B x 3 x H x W`` batches (torch tensors on any device or numpy
                arrays; float in [0, 1] or uint8). A and B may have different sizes; all A share one
                size, all B another. One ``3 x H x W`` image each is one pair (no batch axis out).
            hard, bf16: as in :meth:`predict`.
            batch_size: pairs per network pass (default: all at once).

        Returns:
            :class:`LocalScaleBatch` of ``B x H_A x W_A`` maps; tensors on the device of
            ``images_a`` for tensor input, numpy arrays for numpy input. Equal (to float
            precision) to ``predict(..., anchor=False)`` on each pair (the one-pass map).
        """
        lb_a, lb_b, fmt, (logits, vis) = self._forward_batch(
            images_a, images_b, self.forward_features_all, bf16, batch_size
        )
        probs = F.softmax(logits, 1)
        visible = torch.sigmoid(vis)[:, 0] if vis is not None else None
        log_s = torch.log(scales.hard_scale(probs, 1)) if hard else scales.soft_log_scale(probs, 1)
        log_s = log_s + math.log(lb_a.factor / lb_b.factor)
        grids = [log_s, scales.confidence(probs, 1)] + ([visible] if visible is not None else [])
        if self.config.calibration:
            grids.append(reliability(probs, visible, self.config.calibration, 1))
        maps = upsample_to_original(torch.stack(grids, 1), lb_a)
        return LocalScaleBatch(
            scale=fmt.out(torch.exp(maps[:, 0])),
            confidence=fmt.out(maps[:, 1].clamp(0, 1)),
            visible=fmt.out(maps[:, 2].clamp(0, 1)) if visible is not None else None,
            reliability=fmt.out(maps[:, -1].clamp(0, 1)) if self.config.calibration else None,
            probs=fmt.out(probs),
        )

    def _readout(
        self,
        probs: torch.Tensor,
        lb_a: Letterbox,
        lb_b: Letterbox,
        hard: bool,
        planar: bool = False,
        visible: torch.Tensor | None = None,
    ) -> LocalScalePrediction:
        log_s = torch.log(scales.hard_scale(probs, 0)) if hard else scales.soft_log_scale(probs, 0)
        log_s = log_s + math.log(lb_a.factor / lb_b.factor)
        conf = scales.confidence(probs, 0)
        grids, channels = [log_s, conf], ["scale", "confidence"]
        if visible is not None:
            grids.append(visible)
            channels.append("visible")
        if self.config.calibration:
            grids.append(reliability(probs, visible, self.config.calibration, 0))
            channels.append("reliability")
        pred = LocalScalePrediction(torch.stack(grids).float().cpu(), tuple(channels), probs.cpu(), lb_a, lb_b)
        if planar:
            pred.scale = planarize(pred.scale, pred.confidence, stride=max(1, round(8 / lb_a.factor)))
        return pred


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


def predict_scale_map(
    image_a: ImageLike, image_b: ImageLike, model: LocalScaleNet | None = None, hard: bool = False, planar: bool = False
) -> LocalScalePrediction:
    """Functional form: per-pixel ``S_{A->B}`` with the default (or given) Local-ScaleNet."""
    model = model or LocalScaleNet.from_pretrained()
    return model.predict(image_a, image_b, hard=hard, planar=planar)
