"""Building blocks shared by ScaleNet and Local-ScaleNet.

* :class:`FeatureExtractor`: a backbone to stride 8 (the trainable VGG16 layout with a width
  multiplier, or a frozen pre-trained one from :mod:`.backbones`) + ASPP (3x3 convs with
  dilations 2, 3, 4, concatenated, fused by a 1x1 conv), L2-normalised.
* :func:`correlation`: dense (self- or cross-) correlation volume, ReLU + L2 norm.
* :class:`ReductionBlock`: four Conv-BN-ReLU layers that reduce a correlation volume.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

from ..core.errors import CheckpointError

#: VGG16 up to conv4_3 (stride 8); "M" is a 2x2 max-pool.
VGG16_STRIDE8 = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512)
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def conv_bn_relu(cin: int, cout: int, k: int = 3, dilation: int = 1, bn: bool = True) -> nn.Sequential:
    pad = dilation * (k // 2)
    layers: list[nn.Module] = [nn.Conv2d(cin, cout, k, padding=pad, dilation=dilation, bias=not bn)]
    if bn:
        layers.append(nn.BatchNorm2d(cout))
    layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


def fold_batch_norm(module: nn.Module) -> nn.Module:
    """Fold every BatchNorm that directly follows a Conv2d inside an ``nn.Sequential`` (at any
    depth) into the convolution (eval-mode statistics), in place; returns ``module`` (a
    Sequential passed in is returned as a new one). Inference only: the folded module has no
    BatchNorm left to train. Weights keep their memory layout."""
    if isinstance(module, nn.Sequential):
        return _fold_sequential(module)
    for name, child in module.named_children():
        setattr(module, name, fold_batch_norm(child))
    return module


def _fold_sequential(seq: nn.Sequential) -> nn.Sequential:
    from torch.nn.utils.fusion import fuse_conv_bn_eval

    layers, out, i = list(seq), [], 0
    while i < len(layers):
        conv, bn = layers[i], layers[i + 1] if i + 1 < len(layers) else None
        if isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d) and bn.track_running_stats:
            fused = fuse_conv_bn_eval(conv.eval(), bn.eval())
            if conv.weight.is_contiguous(memory_format=torch.channels_last) and not conv.weight.is_contiguous():
                fused = fused.to(memory_format=torch.channels_last)
            out.append(fused)
            i += 2
        else:
            out.append(fold_batch_norm(conv))
            i += 1
    return nn.Sequential(*out)


class VGGBackbone(nn.Module):
    """VGG16 conv1_1 .. conv4_3 (stride 8), channel widths scaled by ``width``.

    Input ``B x 3 x H x W`` in [0, 1] (ImageNet normalisation is applied inside);
    output ``B x C x H/8 x W/8`` with ``C = 512 * width``.
    """

    def __init__(self, width: float = 0.25, batch_norm: bool = True):
        super().__init__()
        layers: list[nn.Module] = []
        cin = 3
        for v in VGG16_STRIDE8:
            if v == "M":
                layers.append(nn.MaxPool2d(2, 2))
            else:
                cout = max(8, int(round(v * width)))
                layers += list(conv_bn_relu(cin, cout, 3, bn=batch_norm))
                cin = cout
        self.features = nn.Sequential(*layers)
        self.out_channels = cin
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.features((x - self.mean) / self.std)

    def load_torchvision_vgg16(self, path: str | Path) -> None:
        """Load ImageNet weights from a local torchvision ``vgg16``/``vgg16_bn`` state-dict file.

        Only valid for ``width == 1``; the first 10 conv layers (and BNs) are copied in order.
        """
        path = Path(path)
        if not path.is_file():
            raise CheckpointError(f"VGG16 weights file not found: {path}")
        try:
            sd = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:
            raise CheckpointError(f"{path}: cannot read VGG16 weights ({type(e).__name__})") from None
        src_convs = [k[: -len(".weight")] for k, v in sd.items() if k.endswith(".weight") and v.dim() == 4]
        dst_convs = [m for m in self.features if isinstance(m, nn.Conv2d)]
        dst_bns = [m for m in self.features if isinstance(m, nn.BatchNorm2d)]
        if len(src_convs) < len(dst_convs):
            raise CheckpointError(f"{path}: has {len(src_convs)} conv layers, need {len(dst_convs)}")
        for i, (name, conv) in enumerate(zip(src_convs, dst_convs)):
            w = sd[name + ".weight"]
            if w.shape != conv.weight.shape:
                raise CheckpointError(
                    f"{path}: {name} has shape {tuple(w.shape)}, model wants "
                    f"{tuple(conv.weight.shape)} (ImageNet weights need width=1)"
                )
            conv.weight.data.copy_(w)
            if conv.bias is not None and name + ".bias" in sd:
                conv.bias.data.copy_(sd[name + ".bias"])
            bn_name = name.rsplit(".", 1)[0] + "." + str(int(name.rsplit(".", 1)[1]) + 1)
            if dst_bns and bn_name + ".running_mean" in sd:
                bn = dst_bns[i]
                for attr in ("weight", "bias", "running_mean", "running_var"):
                    getattr(bn, attr).data.copy_(sd[f"{bn_name}.{attr}"])


class ASPP(nn.Module):
    """Atrous spatial pyramid: 3x3 convs with dilations (2, 3, 4), concat, 1x1 fusion."""

    def __init__(self, cin: int, cout: int, dilations: tuple[int, ...] = (2, 3, 4)):
        super().__init__()
        self.branches = nn.ModuleList(conv_bn_relu(cin, cout, 3, dilation=d) for d in dilations)
        self.fuse = nn.Conv2d(cout * len(dilations), cout, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fuse(torch.cat([b(x) for b in self.branches], 1))


class FeatureExtractor(nn.Module):
    """Backbone + ASPP -> L2-normalised ``B x D x H/8 x W/8`` features.

    ``backbone``: ``"vgg"`` (trainable, ``width`` and ``batch_norm`` apply) or the name of a frozen
    pre-trained one (:data:`.backbones.BACKBONES`; only the ASPP trains)."""

    stride = 8

    def __init__(self, width: float = 0.25, feature_dim: int = 128, batch_norm: bool = True, backbone: str = "vgg"):
        super().__init__()
        if backbone == "vgg":
            self.backbone = VGGBackbone(width, batch_norm)
        else:
            from .backbones import FrozenBackbone

            self.backbone = FrozenBackbone(backbone)
        self.aspp = ASPP(self.backbone.out_channels, feature_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.normalize(self.aspp(self.backbone(x)).float(), dim=1)


def correlation(fa: torch.Tensor, fb: torch.Tensor) -> torch.Tensor:
    """Raw dense correlation: ``out[b, j, y, x] = <fa[b, :, y, x], fb[b, :, j]>``.

    ``fa``: ``B x D x Ha x Wa``; ``fb``: ``B x D x Hb x Wb`` -> ``B x (Hb*Wb) x Ha x Wa``.
    """
    b, d, ha, wa = fa.shape
    return torch.bmm(fb.flatten(2).transpose(1, 2), fa.flatten(2)).view(b, -1, ha, wa)


def transpose_correlation(corr: torch.Tensor, shape_b: tuple[int, int]) -> torch.Tensor:
    """The B->A volume from the A->B one without recomputing it: ``B x (Ha*Wa) x Hb x Wb``."""
    b, _, ha, wa = corr.shape
    return corr.flatten(2).transpose(1, 2).reshape(b, ha * wa, *shape_b)


def normalise_correlation(corr: torch.Tensor) -> torch.Tensor:
    """ReLU + L2 normalisation over the correlation channels (as in NCNet / ScaleNet)."""
    return F.normalize(F.relu(corr), dim=1)


def topk_profile(raw_cross: torch.Tensor, raw_self: torch.Tensor, k: int) -> torch.Tensor:
    """Position-invariant match-spread cue: the ``k`` largest cross- and self-correlations of
    each pixel, sorted. ``B x N x H x W`` (x2) -> ``B x 2k x H x W``."""
    return torch.cat([raw_cross.topk(k, 1).values, raw_self.topk(k, 1).values], 1)


def warped_pair_features(
    raw: torch.Tensor, fa: torch.Tensor, fb: torch.Tensor, temperature: float = 20.0
) -> torch.Tensor:
    """B's features soft-warped onto A through the raw correlation ``raw`` (``B x Hb*Wb x Ha x Wa``),
    next to A's own: ``B x 3D x Ha x Wa`` = ``[f_A, f_B->A, f_A * f_B->A]``."""
    att = torch.softmax(raw.float() * temperature, 1)
    fb_warped = torch.bmm(fb.flatten(2), att.flatten(2)).view_as(fa)
    return torch.cat([fa, fb_warped, fa * fb_warped], 1)


class ReductionBlock(nn.Sequential):
    """Four Conv-BN-ReLU layers reducing a ``B x N x H x W`` correlation volume."""

    def __init__(self, cin: int, channels: tuple[int, ...] = (128, 64, 64, 32)):
        layers = [conv_bn_relu(cin, channels[0], 1)]
        for a, b in zip(channels[:-1], channels[1:]):
            layers.append(conv_bn_relu(a, b, 3))
        super().__init__(*layers)
        self.out_channels = channels[-1]
