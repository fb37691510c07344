"""The scale-model architectures by name, and building the one a checkpoint names.

An architecture class registers itself with :func:`register` (its ``arch`` attribute is the
name a checkpoint records); :func:`load_model` reads a checkpoint
(:func:`localscale.checkpoint.read_checkpoint`), builds that architecture from the stored
config and loads the weights::

    from localscale.models import load_model
    model = load_model("model.pt", arch="LocalScaleNet")
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn as nn

from ..checkpoint import read_checkpoint
from ..core.devices import resolve_device
from ..core.errors import CheckpointError
from .backbones import check_record

_REGISTRY: dict[str, type] = {}


def register(cls: type) -> type:
    """Class decorator: make an architecture loadable by name."""
    _REGISTRY[cls.arch] = cls
    return cls


def load_model(path: str | Path, arch: str | None = None, device: str | torch.device = "cpu") -> nn.Module:
    """Build the model a checkpoint describes and load its weights (fp32, eval mode; on CPU the
    convolution weights in the channels-last layout, the faster one for oneDNN there).

    Args:
        arch: if given, the checkpoint must be of this architecture.
        device: checked first (:func:`~localscale.core.devices.resolve_device`): an unknown or
            unavailable device is a :class:`LocalScaleError` before the checkpoint is read.
    """
    device = resolve_device(device)
    ckpt = read_checkpoint(path)
    found = ckpt.get("arch")
    if arch is not None and found != arch:
        raise CheckpointError(f"{path}: checkpoint is a {found}, expected a {arch}")
    if found not in _REGISTRY:
        raise CheckpointError(f"{path}: unknown architecture {found!r}")
    cls = _REGISTRY[found]
    if not isinstance(ckpt.get("config"), dict):
        raise CheckpointError(f"{path}: checkpoint has no valid 'config' (got {type(ckpt.get('config')).__name__})")
    try:
        config = cls.config_class(**ckpt["config"])
        model = cls(config)
    except CheckpointError as e:  # a pre-trained backbone's weights are missing or unreadable
        raise type(e)(f"{path}: {e}") from None
    except Exception as e:
        msg = str(e).strip().splitlines()
        raise CheckpointError(
            f"{path}: config does not fit {found} ({type(e).__name__}: {msg[0][:160] if msg else ''})"
        ) from None
    sd = {k: v.float() if v.is_floating_point() else v for k, v in ckpt["state_dict"].items()}
    try:
        model.load_state_dict(sd)
    except RuntimeError as e:
        first = [line.strip() for line in str(e).splitlines() if line.strip()][1:2]
        raise CheckpointError(
            f"{path}: weights do not match the {found} architecture "
            f"({first[0][:160] if first else 'state_dict mismatch'})"
        ) from None
    check_record(model, ckpt.get("backbone"), path)
    model.meta = ckpt.get("meta", {})
    model.weights_file = str(Path(path).resolve())  # the checkpoint's identity (a run records its sha256)
    model = model.to(device).eval()
    return model.to(memory_format=torch.channels_last) if torch.device(device).type == "cpu" else model
