"""int8 HardNet on CPU: PyTorch's eager-mode x86 post-training quantisation.

The seven convolutions of HardNet's ``features`` (kornia's layer indices, shared by
:class:`~localscale.features.descriptors.SlimHardNet`) are fused with their BatchNorm and ReLU,
weights are quantised per output channel, activations per tensor with ranges found once on
calibration patches (:func:`calibrate_int8`, PyTorch's histogram observer). The ranges are plain
numbers (``{module name: [scale, zero_point, quant_min, quant_max]}``) stored beside the weights,
so loading needs no calibration data: :func:`int8_features` rebuilds the quantised network from
the float one and those numbers.

Per-patch standardisation and the final L2 normalisation stay in float32.
"""

from __future__ import annotations

import copy
import warnings
from typing import Dict, List

import torch
import torch.nn as nn
import torch.nn.functional as F

from ..core.errors import LocalScaleError

#: quantised engine used (PyTorch's default on x86 CPUs)
ENGINE = "x86"
#: groups of ``features`` indices fused into one quantised module
FUSE_GROUPS = [
    ["0", "1", "2"],
    ["3", "4", "5"],
    ["6", "7", "8"],
    ["9", "10", "11"],
    ["12", "13", "14"],
    ["15", "16", "17"],
    ["19", "20"],
]
#: modules whose output is quantised, in forward order
OBSERVED = ["quant"] + [f"features.{g[0]}" for g in FUSE_GROUPS]


def int8_available() -> bool:
    """Whether this PyTorch build has the x86 quantised engine (fbgemm/oneDNN kernels)."""
    return ENGINE in torch.backends.quantized.supported_engines


def standardize_patches(x: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Zero mean, unit standard deviation per patch (HardNet's input normalisation). ``B x 1 x H x W``."""
    flat = x.flatten(1)
    return (x - flat.mean(1).view(-1, 1, 1, 1)) / (flat.std(1).view(-1, 1, 1, 1) + eps)


class _QuantWrapped(nn.Module):
    """``QuantStub -> fused features -> DeQuantStub`` of a float HardNet-layout network."""

    def __init__(self, features: nn.Sequential):
        super().__init__()
        self.quant = torch.ao.quantization.QuantStub()
        self.features = features
        self.dequant = torch.ao.quantization.DeQuantStub()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.dequant(self.features(self.quant(x)))


def _fused(net: nn.Module) -> _QuantWrapped:
    features = getattr(net, "features", None)
    if not isinstance(features, nn.Sequential) or len(features) != 21:
        raise LocalScaleError("int8: expected a HardNet-layout network (21 modules in .features)")
    wrapped = _QuantWrapped(copy.deepcopy(features).float().cpu().eval())
    torch.ao.quantization.fuse_modules(wrapped.features, FUSE_GROUPS, inplace=True)
    return wrapped


def _convert(prepared: nn.Module) -> nn.Module:
    with warnings.catch_warnings():  # eager-mode quantisation announces its deprecation
        warnings.simplefilter("ignore")
        return torch.ao.quantization.convert(prepared, inplace=False).eval()


def _prepare(wrapped: nn.Module, qconfigs: Dict[str, torch.ao.quantization.QConfig]) -> nn.Module:
    for name, module in wrapped.named_modules():
        if name in qconfigs:
            module.qconfig = qconfigs[name]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return torch.ao.quantization.prepare(wrapped, inplace=False)


def calibrate_int8(net: nn.Module, patches: torch.Tensor, batch_size: int = 256) -> Dict[str, List[float]]:
    """Activation ranges of ``net`` (HardNet layout) on ``patches`` (``B x 1 x 32 x 32``, any range).

    Returns ``{module name: [scale, zero_point, quant_min, quant_max]}`` for :func:`int8_features`.
    """
    if not int8_available():
        raise LocalScaleError(f"int8: this PyTorch has no {ENGINE!r} quantised engine")
    if patches.dim() != 4 or patches.shape[0] == 0:
        raise LocalScaleError(f"int8: calibration needs B x 1 x H x W patches, got {tuple(patches.shape)}")
    torch.backends.quantized.engine = ENGINE
    qconfig = torch.ao.quantization.get_default_qconfig(ENGINE)
    prepared = _prepare(_fused(net), {name: qconfig for name in OBSERVED + ["dequant"]}).eval()
    with torch.inference_mode():
        for i in range(0, patches.shape[0], batch_size):
            prepared(standardize_patches(patches[i : i + batch_size].float().cpu()))
    out = {}
    for name in OBSERVED:
        obs = prepared.get_submodule(name).activation_post_process
        scale, zero_point = obs.calculate_qparams()
        out[name] = [float(scale), int(zero_point), int(obs.quant_min), int(obs.quant_max)]
    return out


def check_int8_ranges(ranges) -> None:
    """Raise :class:`LocalScaleError` unless ``ranges`` is what :func:`calibrate_int8` returns."""
    try:
        ok = isinstance(ranges, dict) and set(ranges) == set(OBSERVED)
        ok = ok and all(
            isinstance(v, (list, tuple)) and len(v) == 4 and float(v[0]) > 0 and int(v[2]) <= int(v[1]) <= int(v[3])
            for v in ranges.values()
        )
    except (TypeError, ValueError):  # entries that are not numbers
        ok = False
    if not ok:
        raise LocalScaleError(f"int8: activation ranges must map {OBSERVED} to [scale > 0, zero_point, qmin, qmax]")


def int8_features(net: nn.Module, ranges: Dict[str, List[float]]) -> nn.Module:
    """Quantised copy of ``net``'s ``features`` with fixed activation ``ranges``.

    The module maps standardised ``B x 1 x 32 x 32`` float patches to ``B x D x 1 x 1`` float
    outputs (not normalised); it is a snapshot: later changes to ``net`` do not reach it.
    """
    if not int8_available():
        raise LocalScaleError(f"int8: this PyTorch has no {ENGINE!r} quantised engine")
    check_int8_ranges(ranges)
    torch.backends.quantized.engine = ENGINE
    weight = torch.ao.quantization.get_default_qconfig(ENGINE).weight
    qconfigs = {}
    for name, (scale, zp, qmin, qmax) in ranges.items():
        act = torch.ao.quantization.FixedQParamsObserver.with_args(
            scale=float(scale), zero_point=int(zp), dtype=torch.quint8, quant_min=int(qmin), quant_max=int(qmax)
        )
        qconfigs[name] = torch.ao.quantization.QConfig(activation=act, weight=weight)
    qconfigs["dequant"] = qconfigs["quant"]
    return _convert(_prepare(_fused(net), qconfigs))


def int8_describe(features_int8: nn.Module, patches: torch.Tensor) -> torch.Tensor:
    """``B x 1 x 32 x 32`` patches -> ``B x D`` unit descriptors through a module of :func:`int8_features`."""
    return F.normalize(features_int8(standardize_patches(patches.float())).flatten(1), dim=1)
