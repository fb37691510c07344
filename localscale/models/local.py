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

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from .. import scales
from ..geometry.planar import planarize
from ..io import ImageLike
from ..io.preprocess import Letterbox
from .anchor import Anchor, anchor_of
from .backbones import check_backbone_name
from .base import EncodedImage, ScaleModel, upsample_to_original
from .common import ReductionBlock, conv_bn_relu, correlation, normalise_correlation, warped_pair_features
from .local_prediction import LocalScaleBatch, LocalScalePrediction, reliability
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
                turn (:mod:`localscale.models.anchoring`; ``pred.meta["anchor"]`` says how);
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
        from .anchoring import anchored_prediction

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


def predict_scale_map(
    image_a: ImageLike, image_b: ImageLike, model: LocalScaleNet | None = None, hard: bool = False, planar: bool = False
) -> LocalScalePrediction:
    """Functional form: per-pixel ``S_{A->B}`` with the default (or given) Local-ScaleNet."""
    model = model or LocalScaleNet.from_pretrained()
    return model.predict(image_a, image_b, hard=hard, planar=planar)
