"""Devices and the bundled scale models: one place that checks a device name and loads a model.

    device = resolve_device("cuda")             # LocalScaleError when this torch / machine lacks it
    local = load_scale_model("local")           # Local-ScaleNet, bundled weights, on the CPU
    glob = load_scale_model("global", "ckpt.pt", device)
"""
from __future__ import annotations

from .errors import LocalScaleError

#: the two model kinds: Local-ScaleNet (dense map) and ScaleNet (one global factor)
MODEL_KINDS = ("local", "global")


def resolve_device(device) -> str:
    """Check that ``device`` names a torch device this installation can use; returns its name.

    Raises :class:`LocalScaleError` (one line) for unknown names (``banana``) and for devices
    this torch build or machine lacks (``cuda`` on a CPU-only torch, ``cuda:3`` on a one-GPU machine).
    """
    import torch

    try:
        d = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise LocalScaleError(f"unknown device {device!r} (use cpu, cuda, cuda:N or mps)") from None
    if d.type == "cpu":
        return str(d)
    if d.type == "cuda":
        if not torch.cuda.is_available():
            raise LocalScaleError(f"device {device!r}: no CUDA device available to this torch "
                                  f"({torch.__version__}); use --device cpu")
        if d.index is not None and d.index >= torch.cuda.device_count():
            raise LocalScaleError(f"device {device!r}: only {torch.cuda.device_count()} CUDA device(s)")
        return str(d)
    if d.type == "mps":
        if not (hasattr(torch.backends, "mps") and torch.backends.mps.is_available()):
            raise LocalScaleError(f"device {device!r}: MPS is not available; use --device cpu")
        return str(d)
    raise LocalScaleError(f"device {device!r} is not supported (use cpu, cuda, cuda:N or mps)")


def load_scale_model(kind: str, weights=None, device: str = "cpu"):
    """``kind`` ``"local"`` (Local-ScaleNet) or ``"global"`` (ScaleNet), from ``weights``
    (checkpoint path; None = the bundled weights) on ``device`` (checked by :func:`resolve_device`)."""
    from .models import LocalScaleNet, ScaleNet

    if kind not in MODEL_KINDS:
        raise LocalScaleError(f"model kind must be one of {MODEL_KINDS}, got {kind!r}")
    cls = LocalScaleNet if kind == "local" else ScaleNet
    return cls.from_pretrained(weights, device=resolve_device(device))
