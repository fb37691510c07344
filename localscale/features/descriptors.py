"""Patch descriptors with one interface: ``describe(patches B x 1 x 32 x 32) -> B x 128``.

* :class:`HardNetDescriptor`: the 7-layer HardNet architecture
  (:class:`kornia.feature.HardNet`, or :class:`SlimHardNet` at narrower widths), trained by us
  on scale-corrected patches from synthetic homography pairs (``train/train_descriptor.py``).
  Bundled: ``hardnet`` = ``localscale/weights/hardnet.pt``, 16/32/64 channels distilled from
  ``hardnet-full`` = ``hardnet_full.pt`` (HardNet's own widths); model cards beside them. On CPU
  both describe in int8 by default (:mod:`.quantization`). Official HardNet
  weights in kornia's checkpoint format (a dict with a ``state_dict`` key, e.g.
  ``checkpoint_liberty_with_aug.pth``) load from a local path with the same loader.
* :class:`SIFTPatchDescriptor`: kornia's training-free RootSIFT on patches.

Patches are gray, any intensity range (both descriptors standardise each patch);
outputs are L2-normalised float32.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional, Union

import torch
import torch.nn as nn
import torch.nn.functional as F
from kornia.feature import HardNet, SIFTDescriptor

from ..checkpoint import check_format, check_state_dict, safe_load, save_atomic
from ..core.errors import CheckpointError, LocalScaleError
from .quantization import (
    calibrate_int8,
    check_int8_ranges,
    int8_available,
    int8_describe,
    int8_features,
    standardize_patches,
)

WEIGHTS_DIR = Path(__file__).resolve().parent.parent / "weights"
DEFAULT_HARDNET = WEIGHTS_DIR / "hardnet.pt"
#: bundled descriptor weights by name
BUNDLED_HARDNETS = {"hardnet": DEFAULT_HARDNET, "hardnet-full": WEIGHTS_DIR / "hardnet_full.pt"}


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
        if (
            not isinstance(patches, torch.Tensor)
            or patches.dim() != 4
            or patches.shape[1] != 1
            or patches.shape[-2:] != (self.patch_size, self.patch_size)
        ):
            shape = tuple(patches.shape) if isinstance(patches, torch.Tensor) else type(patches).__name__
            raise LocalScaleError(
                f"{self.name}: expected B x 1 x {self.patch_size} x {self.patch_size} patches, got {shape}"
            )
        if patches.shape[0] == 0:
            return torch.zeros(0, self.dim)
        dev = next(iter(self.parameters()), torch.empty(0)).device
        bs = (
            int(batch_size)
            if batch_size
            else (self.cpu_batch_size if dev.type == "cpu" and self.cpu_batch_size else default_batch_size(dev))
        )
        was_training = self.training
        self.eval()
        try:
            with torch.inference_mode():
                run = self._inference_fn(dev)
                out = [run(patches[i : i + bs].to(dev, torch.float32)) for i in range(0, patches.shape[0], bs)]
        finally:
            self.train(was_training)
        # outside inference mode: the result is an ordinary tensor (in-place edits allowed)
        return F.normalize(torch.cat(out).float(), dim=1).cpu()

    def _inference_fn(self, device: torch.device) -> Callable[[torch.Tensor], torch.Tensor]:
        """The function ``describe`` applies to each chunk (``forward`` here)."""
        return self


def default_batch_size(device: Union[str, torch.device] = "cpu") -> int:
    """Patches per descriptor call: 64 per CPU thread (64..256) on CPU, 4096 on GPUs.

    On CPU a chunk of 64-128 HardNet patches keeps the 32 x 32 x 32 activations (8-16 MB)
    near the caches; 512 was about 2x slower on a 2-core machine (``eval/benchmark.py``)."""
    if torch.device(device).type == "cpu":
        return int(min(256, max(64, 64 * torch.get_num_threads())))
    return 4096


class SlimHardNet(nn.Module):
    """HardNet's layout (7 convolutions, BatchNorm without affine, 128-D unit output) with the
    channel widths ``widths = (c1, c2, c3)`` instead of HardNet's ``(32, 64, 128)``.

    ``B x 1 x 32 x 32`` patches (standardised per patch, as HardNet) -> ``B x 128``. Layer
    indices of ``features`` are those of :class:`kornia.feature.HardNet`, so
    ``SlimHardNet((32, 64, 128))`` loads HardNet state dicts.
    """

    patch_size = 32

    def __init__(self, widths: tuple = (16, 32, 64), dim: int = 128, dropout: float = 0.1):
        super().__init__()
        c1, c2, c3 = (int(w) for w in widths)
        self.widths = (c1, c2, c3)

        def block(cin, cout, stride=1):
            return [
                nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False),
                nn.BatchNorm2d(cout, affine=False),
                nn.ReLU(),
            ]

        self.features = nn.Sequential(
            *block(1, c1),
            *block(c1, c1),
            *block(c1, c2, 2),
            *block(c2, c2),
            *block(c2, c3, 2),
            *block(c3, c3),
            nn.Dropout(dropout),
            nn.Conv2d(c3, dim, 8, bias=False),
            nn.BatchNorm2d(dim, affine=False),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = standardize_patches(x)
        if x.device.type == "cpu" and x.dtype == torch.float32:
            x = x.to(memory_format=torch.channels_last)
        return F.normalize(self.features(x).flatten(1), dim=1)


HARDNET_WIDTHS = (32, 64, 128)
#: precisions of :meth:`HardNetDescriptor.describe`
PRECISIONS = ("auto", "fp32", "bf16", "int8")


class HardNetDescriptor(PatchDescriptor):
    """HardNet (7 conv layers, 128-D). ``forward`` is differentiable (used for training).

    ``widths``: channel widths of the three stages; HardNet's own ``(32, 64, 128)`` uses
    :class:`kornia.feature.HardNet`, narrower ones :class:`SlimHardNet` (same layout).

    ``precision`` of :meth:`describe` (one of :data:`PRECISIONS`):

    * ``"fp32"``: float32;
    * ``"bf16"``: bfloat16 autocast (CPU or GPU);
    * ``"int8"``: CPU only, PyTorch's x86 quantised kernels with the activation ranges
      ``int8_ranges`` stored with the weights (:mod:`~localscale.features.quantization`); the
      quantised network is a snapshot of the weights, rebuilt after ``train()``;
    * ``"auto"``: ``int8`` on CPU when the weights carry ``int8_ranges`` and PyTorch has the
      engine, else ``fp32``.
    """

    name = "hardnet"

    def __init__(self, widths: tuple = HARDNET_WIDTHS, precision: str = "auto"):
        super().__init__()
        self.widths = tuple(int(w) for w in widths)
        self.net = HardNet(pretrained=False) if self.widths == HARDNET_WIDTHS else SlimHardNet(self.widths)
        self.meta: dict = {}
        self.int8_ranges: Optional[dict] = None
        self._int8: list = []  # [quantised snapshot] (a list: not a registered submodule)
        self.precision = "auto"
        self.set_precision(precision)

    def forward(self, patches: torch.Tensor) -> torch.Tensor:
        return self.net(patches)

    def set_precision(self, precision: str) -> "HardNetDescriptor":
        """Choose the precision of :meth:`describe` (see the class); returns ``self``."""
        if precision not in PRECISIONS:
            raise LocalScaleError(f"descriptor precision must be one of {PRECISIONS}, got {precision!r}")
        if precision == "int8" and not self.int8_ranges:
            raise LocalScaleError(
                "int8 descriptor precision needs weights with int8 activation ranges "
                "(train/train_descriptor.py --calibrate-int8 adds them)"
            )
        if precision == "int8" and not int8_available():
            raise LocalScaleError("int8 descriptor precision: this PyTorch build has no x86 quantised engine")
        self.precision = precision
        return self

    def resolved_precision(self, device: Union[str, torch.device] = "cpu") -> str:
        """The precision :meth:`describe` uses on ``device`` (``"auto"`` resolved)."""
        if self.precision != "auto":
            return self.precision
        cpu = torch.device(device).type == "cpu"
        return "int8" if cpu and self.int8_ranges and int8_available() else "fp32"

    def train(self, mode: bool = True) -> "HardNetDescriptor":
        if mode:
            self._int8.clear()  # the weights may change: the quantised snapshot is rebuilt on use
        return super().train(mode)

    def _inference_fn(self, device: torch.device) -> Callable[[torch.Tensor], torch.Tensor]:
        precision = self.resolved_precision(device)
        if precision == "int8":
            if device.type != "cpu":
                raise LocalScaleError(f"int8 descriptor precision runs on CPU only, the model is on {device}")
            if not self._int8:
                self._int8.append(int8_features(self.net, self.int8_ranges))
            quantised = self._int8[0]
            return lambda x: int8_describe(quantised, x)
        if precision == "bf16":

            def bf16(x: torch.Tensor) -> torch.Tensor:
                with torch.autocast(device.type, dtype=torch.bfloat16):
                    return self(x).float()

            return bf16
        return self

    @classmethod
    def from_pretrained(
        cls, path: Optional[Union[str, Path]] = None, device: str = "cpu", precision: str = "auto"
    ) -> "HardNetDescriptor":
        """Load weights: ``None`` = bundled ``weights/hardnet.pt``; also accepts kornia/official
        HardNet checkpoints (``{"state_dict": ...}``) and plain state dicts. ``precision``: of
        :meth:`describe` (see the class; ``int8`` needs weights with ``int8_ranges``).

        The file is read with ``weights_only=True``; one holding objects other than tensors
        and plain data is refused with a :class:`CheckpointError`."""
        path = Path(path) if path is not None else DEFAULT_HARDNET
        if not path.is_file():
            raise CheckpointError(f"HardNet weights not found: {path}")
        ckpt = safe_load(path)  # tensors and plain data only (weights_only=True)
        if not isinstance(ckpt, dict):
            raise CheckpointError(f"{path}: not a HardNet checkpoint (got {type(ckpt).__name__})")
        if "localscale_format" in ckpt:
            check_format(ckpt, path)
        arch = ckpt.get("arch")
        if arch is not None and arch != "HardNet":
            raise CheckpointError(f"{path}: checkpoint is a {arch}, expected a HardNet")
        sd = ckpt.get("state_dict", ckpt)
        check_state_dict(sd, path)
        sd = {k[len("net.") :] if k.startswith("net.") else k: v for k, v in sd.items()}
        sd = {k: v.float() if torch.is_tensor(v) and v.is_floating_point() else v for k, v in sd.items()}
        widths = ckpt.get("widths", HARDNET_WIDTHS)
        if not (
            isinstance(widths, (list, tuple)) and len(widths) == 3 and all(isinstance(w, int) and w > 0 for w in widths)
        ):
            raise CheckpointError(f"{path}: 'widths' must be three positive integers, got {widths!r}")
        model = cls(tuple(widths), precision="fp32")
        try:
            model.net.load_state_dict(sd, strict=True)
        except RuntimeError:
            raise CheckpointError(f"{path}: weights do not match the HardNet architecture") from None
        model.meta = ckpt.get("meta", {}) if isinstance(ckpt.get("meta", {}), dict) else {}
        ranges = ckpt.get("int8_ranges")
        if ranges is not None:
            try:
                check_int8_ranges(ranges)
            except LocalScaleError as e:
                raise CheckpointError(f"{path}: {e}") from None
            model.int8_ranges = ranges
        return model.set_precision(precision).to(device).eval()

    def save(self, path: Union[str, Path], meta: Optional[dict] = None, half: bool = True) -> None:
        """Write ``{"arch": "HardNet", "widths": [c1, c2, c3], "state_dict": ..., "meta": ...}``
        (kornia-compatible keys), plus ``int8_ranges`` when the model has them.

        ``int8_ranges`` belong to the weights they were calibrated on: set them
        (:meth:`calibrate_int8`) after the last change to the weights, on the weights as saved
        (``half=True`` rounds them to float16)."""
        sd = {k: (v.half() if half and v.is_floating_point() else v).cpu() for k, v in self.net.state_dict().items()}
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        ckpt = {
            "localscale_format": 1,
            "arch": "HardNet",
            "widths": list(self.widths),
            "state_dict": sd,
            "meta": meta or {},
        }
        if self.int8_ranges:
            ckpt["int8_ranges"] = self.int8_ranges
        save_atomic(ckpt, path)

    def calibrate_int8(self, patches: torch.Tensor) -> "HardNetDescriptor":
        """Set ``int8_ranges`` from ``patches`` (``B x 1 x 32 x 32``, e.g. a few thousand training
        patches) for the current weights; returns ``self``."""
        self.int8_ranges = calibrate_int8(self.net, patches)
        self._int8.clear()
        return self


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
    """``"hardnet"`` / ``"hardnet-full"`` (bundled weights), ``"sift"``, a path to HardNet
    weights, or a module."""
    if isinstance(descriptor, PatchDescriptor):
        return descriptor.eval()
    if isinstance(descriptor, str) and descriptor in BUNDLED_HARDNETS:
        return HardNetDescriptor.from_pretrained(BUNDLED_HARDNETS[descriptor])
    if descriptor == "sift":
        return SIFTPatchDescriptor().eval()
    if isinstance(descriptor, (str, Path)) and Path(descriptor).suffix in (".pt", ".pth"):
        return HardNetDescriptor.from_pretrained(descriptor)
    raise LocalScaleError(
        f"unknown descriptor {descriptor!r}: use 'hardnet', 'hardnet-full', 'sift' or a path to HardNet weights"
    )
