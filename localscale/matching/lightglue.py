"""kornia's LightGlue with the pre-trained weights of an extractor, loaded from disk (nothing is downloaded)."""

from __future__ import annotations

from typing import Optional

import torch

from ..core.devices import cpu_has_bf16
from ..core.errors import LocalScaleError
from ..features.extractors import get_extractor
from ..features.pretrained import find_weights, load_weights


def load_lightglue(
    features: str,
    filter_threshold: float = 0.1,
    depth_confidence: Optional[float] = None,
    width_confidence: Optional[float] = None,
    weights=None,
) -> torch.nn.Module:
    """LightGlue for the descriptors of the extractor ``features`` (``aliked``, ``disk``: LightGlue;
    ``xfeat``: LighterGlue) in kornia's configuration for them (its ``lightglue``), with its
    ``lightglue_weights``; ``None`` confidences keep kornia's values."""
    import kornia.feature as KF

    extractor = get_extractor(features)
    if extractor.lightglue is None or extractor.lightglue_weights is None:
        raise LocalScaleError(f"the {features} extractor has no LightGlue weights")
    conf = {**KF.LightGlue.features[extractor.lightglue], "weights": None, "filter_threshold": filter_threshold}
    for name, value in (("depth_confidence", depth_confidence), ("width_confidence", width_confidence)):
        if value is not None:
            conf[name] = value
    net = KF.LightGlue(None, **conf)
    n_layers = net.conf.n_layers

    def rename(sd: dict) -> dict:
        # the files' names: an optional "matcher." prefix, and "self_attn.i" / "cross_attn.i" for
        # what kornia calls "transformers.i.self_attn" / ".cross_attn"
        out = {}
        for k, v in sd.items():
            k = k[len("matcher.") :] if k.startswith("matcher.") else k
            for i in range(n_layers):
                k = k.replace(f"self_attn.{i}.", f"transformers.{i}.self_attn.")
                k = k.replace(f"cross_attn.{i}.", f"transformers.{i}.cross_attn.")
            out[k] = v
        return out

    return load_weights(net, find_weights(extractor.lightglue_weights, weights), rename)


def quantize_lightglue(net: torch.nn.Module) -> torch.nn.Module:
    """``net`` with the linear layers of its transformer layers and match assignment in dynamic int8
    (:func:`torch.ao.quantization.quantize_dynamic`: int8 weights, activations quantised per call);
    the positional encoding stays float (kornia reads its weight's dtype)."""
    import warnings

    from torch.ao.quantization import quantize_dynamic

    net.eval()
    with warnings.catch_warnings():  # torch's notices that eager quantisation is deprecated
        warnings.simplefilter("ignore")
        for name in ("transformers", "log_assignment"):
            setattr(net, name, quantize_dynamic(getattr(net, name), {torch.nn.Linear}, dtype=torch.qint8))
    return net


#: LightGlue's run-time precisions (:class:`~localscale.matching.MatchConfig` ``lightglue_precision``)
LIGHTGLUE_PRECISIONS = ("auto", "fp32", "bf16", "int8")


def resolve_precision(precision: str, device) -> str:
    """``auto``: ``bf16`` on a CPU with native bfloat16, else ``fp32``; another value as it is."""
    if precision != "auto":
        return precision
    return "bf16" if torch.device(device).type == "cpu" and cpu_has_bf16() else "fp32"


def lightglue_runtime(net: torch.nn.Module, precision: str, device) -> torch.nn.Module:
    """``net`` set to run in ``precision`` (:data:`LIGHTGLUE_PRECISIONS`, :func:`resolve_precision`):
    ``bf16``: kornia's mixed precision (``mp``: autocast, bfloat16 on CPU, float16 on CUDA); ``int8``:
    :func:`quantize_lightglue` (CPU only)."""
    precision = resolve_precision(precision, device)
    if precision == "bf16":
        net.conf.mp = True
    elif precision == "int8":
        if torch.device(device).type != "cpu":
            raise LocalScaleError(f"lightglue_precision 'int8' runs on the CPU only, not on {device}")
        net = quantize_lightglue(net)
    return net
