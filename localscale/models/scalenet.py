"""Global ScaleNet (and its D-ScaleNet read-out): one scale factor for a pair of images.

Pipeline (paper, Sec. 3)::

    f_A, f_B  = FeatureExtractor(A), FeatureExtractor(B)      (shared with Local-ScaleNet)
    c_A, c_B  = self-correlations,  c_AB = cross-correlation   (ReLU + L2 norm)
    P_AB      = softmax(FC(flatten(Red_self(c_A), Red_self(c_B), Red_cross(c_AB))))

The consistency check reuses the same correlations (``c_BA`` is a transpose of the raw
``c_AB``), so both directions cost one backbone pass per image:
``S = exp((ln S_AB - ln S_BA) / 2)``.

Quarter turns (:meth:`ScaleNet.predict`, on by default): when the two directions disagree by more
than x1.41 (the prediction is unreliable), the pair is also predicted with B turned by 90, 180 and
270 degrees and with A turned by the same, and the most consistent of these six predictions
replaces the upright one if its two directions agree better by a factor of sqrt(2) at least (a
scale does not depend on a turn). Turning A as well as B keeps swapping A and B an exact
inversion. The rule was chosen on held-out synthetic pairs, where it is no worse than the upright
prediction on any of four sets (``docs/decisions/scalenet-quarter-turns.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from .. import scales
from ..io import ImageLike
from ..model_limits import limit_reasons
from .backbones import check_backbone_name
from .base import EncodedImage, ScaleModel
from .common import (
    ReductionBlock,
    correlation,
    normalise_correlation,
    topk_profile,
    transpose_correlation,
    warped_pair_features,
)
from .registry import register


@dataclass
class ScaleNetConfig:
    width: float = 0.25
    feature_dim: int = 128
    image_size: int = 192
    reduction: tuple[int, ...] = (128, 64, 64, 32)
    pooled_size: int = 6  #: reduced maps are average-pooled to this grid before the FC
    fc_channels: int = 256
    batch_norm: bool = True
    #: position-invariant cues (as in Local-ScaleNet), average-pooled into the FC input
    topk: int = 0
    warp_features: bool = False
    #: feature backbone: "vgg" (trainable, ``width`` channels) or a frozen pre-trained one
    #: (``"xfeat"``, ``"aliked"``; :mod:`localscale.models.backbones`)
    backbone: str = "vgg"

    def __post_init__(self):
        self.reduction = tuple(self.reduction)
        check_backbone_name(self.backbone)
        if self.image_size % 8 or self.image_size < 64:
            raise ValueError(f"image_size must be a multiple of 8 and >= 64, got {self.image_size}")


@dataclass
class GlobalScalePrediction:
    """Output of :meth:`ScaleNet.predict`.

    Attributes:
        scale: final ``S_{A->B}`` (consistency-checked soft scale, or what ``mode`` chose).
        scale_ab, scale_ba: soft scales of each direction (``scale_ba`` is ``S_{B->A}``).
        hard_scale: D-ScaleNet read-out (arg-max bin of ``probs_ab``).
        probs_ab, probs_ba: the two 13-bin distributions.
        reliable: False when the two directions disagree (see ``inconsistency_log2``) or when
            ``limits`` says why the network cannot answer for these images.
        limits: an image too thin or too small for the network, or a scale outside its bins'
            range after the resize correction (:func:`localscale.model_limits.limit_reasons`).
        turns: quarter turns (counter-clockwise) of A and of B the prediction was made with
            (``(0, 0)``: upright; see :meth:`ScaleNet.predict`).
    """

    scale: float
    scale_ab: float
    scale_ba: float
    hard_scale: float
    probs_ab: np.ndarray
    probs_ba: np.ndarray
    turns: tuple[int, int] = (0, 0)
    limits: list = field(default_factory=list)

    #: the two directions may disagree by at most this factor (log2) for a reliable estimate
    MAX_INCONSISTENCY_LOG2 = 0.5

    @property
    def inconsistency_log2(self) -> float:
        """``|log2 S_AB + log2 S_BA|``: 0 when the two directions agree exactly."""
        return abs(math.log2(self.scale_ab) + math.log2(self.scale_ba))

    @property
    def consistent(self) -> bool:
        """A->B and the inverse of B->A agree within x1.41."""
        return math.isfinite(self.scale) and self.inconsistency_log2 <= self.MAX_INCONSISTENCY_LOG2

    @property
    def reliable(self) -> bool:
        """False when the two directions disagree or ``limits`` holds a reason: do not trust ``scale``."""
        return self.consistent and not self.limits


@register
class ScaleNet(ScaleModel):
    """Global ScaleNet with the consistency check; see the module docstring."""

    arch = "ScaleNet"
    config_class = ScaleNetConfig
    default_weights = "scalenet.pt"
    #: a turned prediction replaces an unreliable upright one only when its inconsistency is lower by this (log2)
    TURN_MARGIN_LOG2 = 0.5

    def __init__(self, config: ScaleNetConfig | None = None, **overrides):
        config = config or ScaleNetConfig(**overrides)
        super().__init__(config)
        n = self.grid_size**2
        self.reduce_self = ReductionBlock(n, config.reduction)
        self.reduce_cross = ReductionBlock(n, config.reduction)
        self.pool = nn.AdaptiveAvgPool2d(config.pooled_size)
        c = 3 * config.reduction[-1] * config.pooled_size**2 + self._build_cue_branches(n)
        self.fc = nn.Sequential(
            nn.Linear(c, config.fc_channels), nn.ReLU(inplace=True), nn.Linear(config.fc_channels, scales.NUM_BINS)
        )

    def forward_features(self, fa: torch.Tensor, fb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Logits of both directions from encoded features: ``(B x 13, B x 13)`` for A->B, B->A."""
        net = self._inference_model()
        if net is not self:
            return net.forward_features(fa, fb)
        raw_ab = correlation(fa, fb)
        raw_ba = transpose_correlation(raw_ab, fb.shape[-2:])
        raw_a, raw_b = correlation(fa, fa), correlation(fb, fb)
        r_a = self.pool(self.reduce_self(normalise_correlation(raw_a))).flatten(1)
        r_b = self.pool(self.reduce_self(normalise_correlation(raw_b))).flatten(1)
        r_ab = self.pool(self.reduce_cross(normalise_correlation(raw_ab))).flatten(1)
        r_ba = self.pool(self.reduce_cross(normalise_correlation(raw_ba))).flatten(1)
        in_ab, in_ba = [r_a, r_b, r_ab], [r_b, r_a, r_ba]
        if self.topk:
            in_ab.append(self.reduce_topk(topk_profile(raw_ab, raw_a, self.topk)).mean((2, 3)))
            in_ba.append(self.reduce_topk(topk_profile(raw_ba, raw_b, self.topk)).mean((2, 3)))
        if self.config.warp_features:
            in_ab.append(self.reduce_warp(warped_pair_features(raw_ab, fa, fb)).mean((2, 3)))
            in_ba.append(self.reduce_warp(warped_pair_features(raw_ba, fb, fa)).mean((2, 3)))
        return self.fc(torch.cat(in_ab, 1)), self.fc(torch.cat(in_ba, 1))

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``B x 3 x P x P`` (x2) -> logits ``(B x 13, B x 13)`` for A->B and B->A (processing frame)."""
        return self.forward_features(self.encode(a), self.encode(b))

    @torch.inference_mode()
    def predict_from_features(self, ea: EncodedImage, eb: EncodedImage, bf16: bool = False) -> GlobalScalePrediction:
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=bf16):
            l_ab, l_ba = self.forward_features(ea.features, eb.features)
        return self._readout(F.softmax(l_ab.float(), 1)[0], F.softmax(l_ba.float(), 1)[0], ea.letterbox, eb.letterbox)

    def _readout(self, p_ab: torch.Tensor, p_ba: torch.Tensor, lb_a, lb_b) -> GlobalScalePrediction:
        corr = math.log(lb_a.factor / lb_b.factor)
        ls_ab = float(scales.soft_log_scale(p_ab, 0)) + corr
        ls_ba = float(scales.soft_log_scale(p_ba, 0)) - corr
        hard = math.log(float(scales.hard_scale(p_ab, 0))) + corr
        scale = math.exp(float(scales.consistent_log_scale(torch.tensor(ls_ab), torch.tensor(ls_ba))))
        return GlobalScalePrediction(
            scale=scale,
            scale_ab=math.exp(ls_ab),
            scale_ba=math.exp(ls_ba),
            hard_scale=math.exp(hard),
            probs_ab=p_ab.cpu().numpy(),
            probs_ba=p_ba.cpu().numpy(),
            limits=limit_reasons(lb_a, lb_b, scale),
        )

    @torch.inference_mode()
    def predict_batch(self, images_a, images_b, bf16: bool = False, batch_size: int | None = None):
        """Global ``S_{A->B}`` (consistency-checked soft scale, :attr:`GlobalScalePrediction.scale`)
        for a batch of pairs: ``B x 3 x H x W`` tensors (any device) or numpy arrays, float in
        [0, 1] or uint8 -> ``B`` scales (a tensor on the device of ``images_a``, or numpy for numpy
        input; a 0-d value for one unbatched pair). Equal to ``predict(..., turns=False)`` on each
        pair (no quarter turns)."""
        lb_a, lb_b, fmt, (l_ab, l_ba) = self._forward_batch(images_a, images_b, self.forward_features, bf16, batch_size)
        corr = math.log(lb_a.factor / lb_b.factor)
        ls_ab = scales.soft_log_scale(F.softmax(l_ab, 1), 1) + corr
        ls_ba = scales.soft_log_scale(F.softmax(l_ba, 1), 1) - corr
        return fmt.out(torch.exp(scales.consistent_log_scale(ls_ab, ls_ba)))

    @torch.inference_mode()
    def predict(
        self, image_a: ImageLike, image_b: ImageLike, bf16: bool = False, turns: bool = True
    ) -> GlobalScalePrediction:
        """Global ``S_{A->B}`` between two images (paths or arrays, any size); when exactly one
        image is gray, the other is turned gray before encoding.

        ``turns``: when the upright prediction is unreliable, also try quarter turns of B and of A
        and keep the most consistent prediction (module docstring; ``pred.turns`` says which).
        """
        (a, shape_a), (b, shape_b) = self.load_pair(image_a, image_b)
        return self.predict_loaded(a, shape_a, b, shape_b, bf16, turns)

    @torch.inference_mode()
    def predict_loaded(
        self,
        a: np.ndarray,
        shape_a: tuple[int, int],
        b: np.ndarray,
        shape_b: tuple[int, int],
        bf16: bool = False,
        turns: bool = True,
    ) -> GlobalScalePrediction:
        """:meth:`predict` on two images as :meth:`load_pair` gives them (arrays and full sizes)."""
        ea, eb = self.encode_image(a, "image A", bf16, shape_a), self.encode_image(b, "image B", bf16, shape_b)
        first = self.predict_from_features(ea, eb, bf16)
        return self.retry_turned(first, a, b, ea, eb, bf16, shape_a, shape_b) if turns else first

    @torch.inference_mode()
    def retry_turned(
        self,
        first: GlobalScalePrediction,
        a: np.ndarray,
        b: np.ndarray,
        ea: EncodedImage,
        eb: EncodedImage,
        bf16: bool = False,
        shape_a: tuple[int, int] | None = None,
        shape_b: tuple[int, int] | None = None,
    ) -> GlobalScalePrediction:
        """``first`` (the upright prediction from the encodings ``ea``, ``eb`` of the arrays ``a``,
        ``b``) when its two directions agree; else the most consistent of it and the predictions with B, then A,
        turned by 1, 2 and 3 quarter turns, if its two directions agree better than the upright
        ones' by :attr:`TURN_MARGIN_LOG2` at least. ``shape_a`` / ``shape_b``: full image sizes when
        the arrays were reduced (:meth:`load`)."""
        if first.consistent:
            return first
        candidates = [first]
        for k in (1, 2, 3):
            p = self.predict_from_features(ea, self.encode_image(b, "image B", bf16, shape_b, k), bf16)
            p.turns = (0, k)
            candidates.append(p)
        for k in (1, 2, 3):
            p = self.predict_from_features(self.encode_image(a, "image A", bf16, shape_a, k), eb, bf16)
            p.turns = (k, 0)
            candidates.append(p)
        best = min((p for p in candidates if math.isfinite(p.scale)), key=lambda p: p.inconsistency_log2, default=first)
        return best if best.inconsistency_log2 <= first.inconsistency_log2 - self.TURN_MARGIN_LOG2 else first


def estimate_scale(image_a: ImageLike, image_b: ImageLike, model: ScaleNet | None = None) -> float:
    """Functional form: global ``S_{A->B}`` (consistency-checked) with the default ScaleNet."""
    model = model or ScaleNet.from_pretrained()
    return model.predict(image_a, image_b).scale
