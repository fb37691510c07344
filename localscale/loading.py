"""The scale models by kind: one place that loads Local-ScaleNet or ScaleNet for a command.

local = load_scale_model("local")           # Local-ScaleNet, bundled weights, on the CPU
glob = load_scale_model("global", "ckpt.pt", device)
"""

from __future__ import annotations

from .core.errors import LocalScaleError

#: the two model kinds: Local-ScaleNet (dense map) and ScaleNet (one global factor)
MODEL_KINDS = ("local", "global")


def load_scale_model(kind: str, weights=None, device: str = "cpu"):
    """``kind`` ``"local"`` (Local-ScaleNet) or ``"global"`` (ScaleNet), from ``weights``
    (checkpoint path; None = the bundled weights) on ``device`` (checked by
    :func:`localscale.core.devices.resolve_device`)."""
    from .core.devices import resolve_device
    from .models import LocalScaleNet, ScaleNet

    if kind not in MODEL_KINDS:
        raise LocalScaleError(f"model kind must be one of {MODEL_KINDS}, got {kind!r}")
    cls = LocalScaleNet if kind == "local" else ScaleNet
    return cls.from_pretrained(weights, device=resolve_device(device))
