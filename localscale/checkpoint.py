"""Saving and reading model checkpoints: the file format, its checks, and training state.

A checkpoint is a ``torch.save``-d dict::

    {"localscale_format": 1, "arch": "LocalScaleNet", "config": {...},
     "state_dict": {...}, "meta": {...}, "train_state": {...},  # optional
     "backbone": {"name": "xfeat", "sha256": ..., "licence": ...}}  # frozen pre-trained backbone only

A frozen pre-trained backbone's weights are not in the checkpoint: the model reads them from
their own file (the models package's ``backbones`` module), which must have the recorded sha256.

Checkpoints are read with ``torch.load(weights_only=True)``: only tensors and plain data
(dict, list, tuple, str, numbers, bool, None) are unpickled, so a checkpoint cannot run
code when it is loaded. A file holding any other object is refused with a
:class:`CheckpointError`.

The model a checkpoint names is built, and its weights loaded, by the models package's
``load_model``; this module knows the file, not the architectures.
"""

from __future__ import annotations

import dataclasses
import pickle
import re
import warnings
from collections import Counter
from pathlib import Path
from typing import Any

import torch
import torch.nn as nn

from .core.errors import CheckpointError
from .core.outputs import atomic_path

FORMAT_VERSION = 1


def checkpoint_dict(model: nn.Module, meta: dict | None = None, half: bool = False) -> dict[str, Any]:
    sd = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    if half:
        sd = {k: v.half() if v.is_floating_point() else v for k, v in sd.items()}
    ckpt = {
        "localscale_format": FORMAT_VERSION,
        "arch": model.arch,
        "config": dataclasses.asdict(model.config),
        "state_dict": sd,
        "meta": meta or {},
    }
    record = backbone_record(model)
    if record is not None:
        ckpt["backbone"] = record
    return ckpt


def backbone_record(model: nn.Module) -> dict | None:
    """What a checkpoint stores about a frozen pre-trained backbone (name, weight file, sha256,
    licence, source; its weights stay out of the checkpoint), or None for a trainable one."""
    backbone = getattr(getattr(model, "extractor", None), "backbone", None)
    return backbone.record() if hasattr(backbone, "record") else None


def save_model(model: nn.Module, path: str | Path, meta: dict | None = None, half: bool = False) -> None:
    """Write an inference checkpoint (weights + config + metadata); ``half`` stores fp16.

    Atomic (temporary name, then rename); weights with NaN or inf are refused (nothing written)."""
    path = Path(path)
    ckpt = checkpoint_dict(model, meta, half)
    bad = non_finite_tensors(ckpt["state_dict"])
    if bad:
        raise CheckpointError(
            f"{path}: not saved, the weights contain NaN or inf ({len(bad)} tensor(s), e.g. {bad[0][:80]})"
        )
    path.parent.mkdir(parents=True, exist_ok=True)
    save_atomic(ckpt, path)


def save_atomic(obj: Any, path: str | Path) -> None:
    """``torch.save`` through :func:`localscale.core.outputs.atomic_path`: ``path`` is complete or untouched."""
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def safe_load(path: str | Path) -> Any:
    """``torch.load`` restricted to tensors and plain data (``weights_only=True``), on the CPU.

    Raises:
        CheckpointError: the file is missing, holds other objects (refused unread), or is
            truncated or corrupt. The message is one line and names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    try:
        with warnings.catch_warnings():  # torch warns about the pickle protocol of foreign files
            warnings.simplefilter("ignore")
            return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        found = re.search(r"GLOBAL ([\w.]+)", str(e))
        if found:
            raise CheckpointError(
                f"{path}: checkpoint contains non-tensor objects ({found.group(1)}); refused, "
                f"only tensors and plain data (dict, list, str, numbers) are loaded"
            ) from None
        raise CheckpointError(
            f"{path}: cannot read checkpoint, not a torch file of tensors and plain data, or truncated or corrupt"
        ) from None
    except Exception as e:
        msg = str(e).strip().splitlines()
        raise CheckpointError(
            f"{path}: cannot read checkpoint, truncated or corrupt ({type(e).__name__}: {msg[0][:120] if msg else ''})"
        ) from None


def check_format(ckpt: dict, path: str | Path) -> None:
    """Refuse a ``localscale_format`` other than :data:`FORMAT_VERSION`."""
    version = ckpt.get("localscale_format")
    if type(version) is not int or version != FORMAT_VERSION:
        raise CheckpointError(
            f"{path}: unsupported checkpoint format version {version!r} "
            f"(this localscale reads version {FORMAT_VERSION})"
        )


def check_state_dict(sd: Any, path: str | Path) -> None:
    """A state dict must map names (str) to tensors, and every floating-point tensor must be
    finite (a checkpoint with NaN or inf weights would give NaN maps)."""
    if not isinstance(sd, dict):
        raise CheckpointError(f"{path}: 'state_dict' is a {type(sd).__name__}, not a dict of tensors")
    for k, v in sd.items():
        if not isinstance(k, str) or not isinstance(v, torch.Tensor):
            raise CheckpointError(f"{path}: 'state_dict' entry {str(k)[:80]!r} is a {type(v).__name__}, not a tensor")
    bad = non_finite_tensors(sd)
    if bad:
        raise CheckpointError(f"{path}: weights contain NaN or inf ({len(bad)} tensor(s), e.g. {bad[0][:80]}); refused")


def non_finite_tensors(sd: dict) -> list[str]:
    """Names of the floating-point tensors of a state dict that hold NaN or inf."""
    return [
        k
        for k, v in sd.items()
        if isinstance(v, torch.Tensor)
        and (v.is_floating_point() or v.is_complex())
        and not bool(torch.isfinite(v).all())
    ]


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read and validate the container (not the weights) of a checkpoint file.

    Checks: a dict with ``localscale_format`` equal to :data:`FORMAT_VERSION` and a
    ``state_dict`` mapping names to tensors.
    """
    ckpt = safe_load(path)
    if not isinstance(ckpt, dict) or "localscale_format" not in ckpt:
        raise CheckpointError(f"{path}: not a localscale checkpoint (no 'localscale_format' key)")
    check_format(ckpt, path)
    if "state_dict" not in ckpt:
        raise CheckpointError(f"{path}: checkpoint has no 'state_dict' (no weights)")
    check_state_dict(ckpt["state_dict"], path)
    return ckpt


def train_state(optimizer: torch.optim.Optimizer, scheduler: Any, step: int) -> dict[str, Any]:
    """Optimizer and LR-scheduler state as tensors and plain data, for a resumable checkpoint.

    ``MultiStepLR`` keeps its milestones in a ``collections.Counter``; it is stored as a
    plain dict (torch before 2.4 refuses a ``Counter`` under ``weights_only=True``).
    """
    sched = {k: dict(v) if isinstance(v, Counter) else v for k, v in scheduler.state_dict().items()}
    return {"optimizer": optimizer.state_dict(), "scheduler": sched, "step": int(step)}


def restore_train_state(optimizer: torch.optim.Optimizer, scheduler: Any, state: dict[str, Any]) -> int:
    """Load what :func:`train_state` stored (milestones back into a ``Counter``); returns the step."""
    optimizer.load_state_dict(state["optimizer"])
    sched = dict(state["scheduler"])
    if isinstance(sched.get("milestones"), dict):
        sched["milestones"] = Counter(sched["milestones"])
    scheduler.load_state_dict(sched)
    return int(state["step"])
