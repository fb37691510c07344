"""Patch descriptors with one interface: ``describe(patches B x 1 x 32 x 32) -> B x 128``.

* :class:`HardNetDescriptor`: the 7-layer HardNet architecture
  (:class:`kornia.feature.HardNet`), trained by us on scale-corrected patches from
  synthetic homography pairs (``train/train_descriptor.py``); the bundled weights are
  ``localscale/weights/hardnet.pt`` (model card ``hardnet.json``). Official HardNet
  weights in kornia's checkpoint format (a dict with a ``state_dict`` key, e.g.
  ``checkpoint_liberty_with_aug.pth``) load from a local path with the same loader.
* :class:`SIFTPatchDescriptor`: kornia's training-free RootSIFT on patches.

Patches are gray, any intensity range (both descriptors standardise each patch);
outputs are L2-normalised float32.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional, Union

import torch
import torch.nn as nn
import torch.nn.functional as F
from kornia.feature import HardNet, SIFTDescriptor

from ..checkpoint import check_format, check_state_dict, safe_load, save_atomic
from ..errors import CheckpointError, LocalScaleError

WEIGHTS_DIR = Path(__file__).resolve().parent.parent / "weights"
DEFAULT_HARDNET = WEIGHTS_DIR / "hardnet.pt"


class PatchDescriptor(nn.Module):
    """Base class. Subclasses implement ``forward(B x 1 x PS x PS) -> B x D``."""

    patch_size = 32
    dim = 128
    name = "descriptor"
    #: patches per call on CPU when ``describe`` gets no ``batch_size`` (None: :func:`default_batch_size`)
    cpu_batch_size: Optional[int] = None

    def describe(self, patches: torch.Tensor, batch_size: Optional[int] = None) -> torch.Tensor:
        """``B x 1 x 32 x 32`` patches -> ``B x 128`` L2-normalised descriptors (eval mode, no grad).

        ``batch_size``: patches per network call; ``None`` picks :func:`default_batch_size` for the
        module's device (small on CPU, where the activations of a chunk should stay in cache).
        Each descriptor depends only on its own patch, so the chunking does not change results.
        """
        if not isinstance(patches, torch.Tensor) or patches.dim() != 4 or patches.shape[1] != 1 \
                or patches.shape[-2:] != (self.patch_size, self.patch_size):
            shape = tuple(patches.shape) if isinstance(patches, torch.Tensor) else type(patches).__name__
            raise LocalScaleError(f"{self.name}: expected B x 1 x {self.patch_size} x {self.patch_size} patches, "
                                  f"got {shape}")
        if patches.shape[0] == 0:
            return torch.zeros(0, self.dim)
        dev = next(iter(self.parameters()), torch.empty(0)).device
        bs = int(batch_size) if batch_size else (self.cpu_batch_size if dev.type == "cpu" and self.cpu_batch_size
                                                 else default_batch_size(dev))
        was_training = self.training
        self.eval()
        try:
            with torch.inference_mode():
                out = [self(patches[i:i + bs].to(dev, torch.float32)) for i in range(0, patches.shape[0], bs)]
        finally:
            self.train(was_training)
        # outside inference mode: the result is an ordinary tensor (in-place edits allowed)
        return F.normalize(torch.cat(out).float(), dim=1).cpu()


def default_batch_size(device: Union[str, torch.device] = "cpu") -> int:
    """Patches per descriptor call: 64 per CPU thread (64..256) on CPU, 4096 on GPUs.

    On CPU a chunk of 64-128 HardNet patches keeps the 32 x 32 x 32 activations (8-16 MB)
    near the caches; 512 was about 2x slower on a 2-core machine (``eval/benchmark.py``)."""
    if torch.device(device).type == "cpu":
        return int(min(256, max(64, 64 * torch.get_num_threads())))
    return 4096


class HardNetDescriptor(PatchDescriptor):
    """HardNet (7 conv layers, 128-D). ``forward`` is differentiable (used for training)."""

    name = "hardnet"

    def __init__(self):
        super().__init__()
        self.net = HardNet(pretrained=False)
        self.meta: dict = {}

    def forward(self, patches: torch.Tensor) -> torch.Tensor:
        return self.net(patches)

    @classmethod
    def from_pretrained(cls, path: Optional[Union[str, Path]] = None, device: str = "cpu") -> "HardNetDescriptor":
        """Load weights: ``None`` = bundled ``weights/hardnet.pt``; also accepts kornia/official
        HardNet checkpoints (``{"state_dict": ...}``) and plain state dicts.

        The file is read with ``weights_only=True``; one holding objects other than tensors
        and plain data is refused with a :class:`CheckpointError`."""
        path = Path(path) if path is not None else DEFAULT_HARDNET
        if not path.is_file():
            raise CheckpointError(f"HardNet weights not found: {path}")
        ckpt = safe_load(path)   # tensors and plain data only (weights_only=True)
        if not isinstance(ckpt, dict):
            raise CheckpointError(f"{path}: not a HardNet checkpoint (got {type(ckpt).__name__})")
        if "localscale_format" in ckpt:
            check_format(ckpt, path)
        arch = ckpt.get("arch")
        if arch is not None and arch != "HardNet":
            raise CheckpointError(f"{path}: checkpoint is a {arch}, expected a HardNet")
        sd = ckpt.get("state_dict", ckpt)
        check_state_dict(sd, path)
        sd = {k[len("net."):] if k.startswith("net.") else k: v for k, v in sd.items()}
        sd = {k: v.float() if torch.is_tensor(v) and v.is_floating_point() else v for k, v in sd.items()}
        model = cls()
        try:
            model.net.load_state_dict(sd, strict=True)
        except RuntimeError:
            raise CheckpointError(f"{path}: weights do not match the HardNet architecture") from None
        model.meta = ckpt.get("meta", {}) if isinstance(ckpt.get("meta", {}), dict) else {}
        return model.to(device).eval()

    def save(self, path: Union[str, Path], meta: Optional[dict] = None, half: bool = True) -> None:
        """Write ``{"arch": "HardNet", "state_dict": ..., "meta": ...}`` (kornia-compatible keys)."""
        sd = {k: (v.half() if half and v.is_floating_point() else v).cpu() for k, v in self.net.state_dict().items()}
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        save_atomic({"localscale_format": 1, "arch": "HardNet", "state_dict": sd, "meta": meta or {}}, path)


class SIFTPatchDescriptor(PatchDescriptor):
    """Training-free RootSIFT (4x4 spatial x 8 orientation bins) on 32 x 32 patches."""

    name = "sift"
    # cheap per patch: fewer, larger calls (128 and 512 cost the same on one thread; 512 loses less
    # to thread synchronisation when the cores are shared with other jobs)
    cpu_batch_size = 512

    def __init__(self, rootsift: bool = True):
        super().__init__()
        self.sift = SIFTDescriptor(self.patch_size, 8, 4, rootsift=rootsift)
        self.register_buffer("_dev", torch.zeros(1), persistent=False)

    def forward(self, patches: torch.Tensor) -> torch.Tensor:
        return self.sift(patches)


def get_descriptor(descriptor: Union[str, PatchDescriptor] = "hardnet") -> PatchDescriptor:
    """``"hardnet"`` (bundled weights), ``"sift"``, a path to HardNet weights, or a module."""
    if isinstance(descriptor, PatchDescriptor):
        return descriptor.eval()
    if descriptor == "hardnet":
        return HardNetDescriptor.from_pretrained()
    if descriptor == "sift":
        return SIFTPatchDescriptor().eval()
    if isinstance(descriptor, (str, Path)) and Path(descriptor).suffix in (".pt", ".pth"):
        return HardNetDescriptor.from_pretrained(descriptor)
    raise LocalScaleError(f"unknown descriptor {descriptor!r}: use 'hardnet', 'sift' or a path to HardNet weights")
