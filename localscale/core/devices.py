"""Checking a torch device name before anything is placed on it."""

from __future__ import annotations

from functools import lru_cache

import torch

from .errors import LocalScaleError


def resolve_device(device: str | torch.device) -> str:
    """Check that ``device`` names a torch device this installation can run models on; returns its name.

    Raises :class:`LocalScaleError` (one line) for unknown names (``banana``), for devices this
    torch build or machine lacks (``cuda`` on a CPU-only torch, ``cuda:3`` on a one-GPU machine)
    and for device types that hold no data or that the models do not run on (``meta``, ``xla``).
    """
    try:
        d = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise LocalScaleError(f"unknown device {device!r} (use cpu, cuda, cuda:N or mps)") from None
    if d.type == "cpu":
        return str(d)
    if d.type == "cuda":
        if not torch.cuda.is_available():
            raise LocalScaleError(
                f"device {str(device)!r}: no CUDA device available to this torch "
                f"({torch.__version__}); use the cpu device"
            )
        if d.index is not None and d.index >= torch.cuda.device_count():
            raise LocalScaleError(f"device {str(device)!r}: only {torch.cuda.device_count()} CUDA device(s)")
        return str(d)
    if d.type == "mps":
        if not (hasattr(torch.backends, "mps") and torch.backends.mps.is_available()):
            raise LocalScaleError(f"device {str(device)!r}: MPS is not available; use the cpu device")
        return str(d)
    raise LocalScaleError(f"device {str(device)!r} is not supported (use cpu, cuda, cuda:N or mps)")


@lru_cache(maxsize=1)
def cpu_has_bf16() -> bool:
    """Whether this CPU computes bfloat16 natively: AVX-512 BF16 or AMX in ``/proc/cpuinfo``'s flags
    (Linux); elsewhere oneDNN's own check (``torch.ops.mkldnn._is_mkldnn_bf16_supported``)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            flags = next((line.split(":", 1)[1].split() for line in f if line.startswith("flags")), None)
        if flags is not None:
            return "avx512_bf16" in flags or "amx_bf16" in flags
    except OSError:
        pass
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False
