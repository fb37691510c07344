"""Saving and loading model checkpoints with architecture checks.

A checkpoint is a ``torch.save``-d dict::

    {"localscale_format": 1, "arch": "LocalScaleNet", "config": {...},
     "state_dict": {...}, "meta": {...}, "train_state": {...}  # optional}
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import torch
import torch.nn as nn

from .errors import CheckpointError

FORMAT_VERSION = 1
_REGISTRY: dict[str, type] = {}


def register(cls: type) -> type:
    """Class decorator: make an architecture loadable by name."""
    _REGISTRY[cls.arch] = cls
    return cls


def checkpoint_dict(model: nn.Module, meta: dict | None = None, half: bool = False) -> dict[str, Any]:
    sd = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    if half:
        sd = {k: v.half() if v.is_floating_point() else v for k, v in sd.items()}
    return {"localscale_format": FORMAT_VERSION, "arch": model.arch,
            "config": dataclasses.asdict(model.config), "state_dict": sd, "meta": meta or {}}


def save_model(model: nn.Module, path: str | Path, meta: dict | None = None, half: bool = False) -> None:
    """Write an inference checkpoint (weights + config + metadata); ``half`` stores fp16."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(checkpoint_dict(model, meta, half), tmp)
    tmp.replace(path)


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read and validate the container (not the weights) of a checkpoint file."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:
        raise CheckpointError(f"{path}: cannot read checkpoint, truncated or corrupt "
                              f"({type(e).__name__}: {str(e).splitlines()[0][:120]})") from None
    if not isinstance(ckpt, dict) or "localscale_format" not in ckpt:
        raise CheckpointError(f"{path}: not a localscale checkpoint (no 'localscale_format' key)")
    return ckpt


def load_model(path: str | Path, arch: str | None = None, device: str | torch.device = "cpu") -> nn.Module:
    """Build the model a checkpoint describes and load its weights (fp32, eval mode).

    Args:
        arch: if given, the checkpoint must be of this architecture.
    """
    ckpt = read_checkpoint(path)
    found = ckpt.get("arch")
    if arch is not None and found != arch:
        raise CheckpointError(f"{path}: checkpoint is a {found}, expected a {arch}")
    if found not in _REGISTRY:
        raise CheckpointError(f"{path}: unknown architecture {found!r}")
    cls = _REGISTRY[found]
    try:
        config = cls.config_class(**ckpt["config"])
    except TypeError as e:
        raise CheckpointError(f"{path}: config does not fit {found} ({e})") from None
    model = cls(config)
    sd = {k: v.float() if v.is_floating_point() else v for k, v in ckpt["state_dict"].items()}
    try:
        model.load_state_dict(sd)
    except RuntimeError as e:
        first = [line.strip() for line in str(e).splitlines() if line.strip()][1:2]
        raise CheckpointError(f"{path}: weights do not match the {found} architecture "
                              f"({first[0][:160] if first else 'state_dict mismatch'})") from None
    model.meta = ckpt.get("meta", {})
    return model.to(device).eval()
