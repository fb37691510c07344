"""kornia's LightGlue with the pre-trained weights of an extractor, loaded from disk (nothing is downloaded)."""

from __future__ import annotations

from typing import Optional

import torch

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
