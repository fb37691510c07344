"""Shared plumbing of the two scale models: image preparation, encoding, loading."""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn

from ..core.errors import ImageError
from ..io import ImageLike, load_image, load_image_array, load_image_reduced
from ..io.preprocess import Letterbox, letterbox, to_tensor
from .common import FeatureExtractor, fold_batch_norm
from .registry import load_model

WEIGHTS_DIR = Path(__file__).resolve().parent.parent / "weights"


@dataclass
class EncodedImage:
    """Backbone+ASPP features of one image, reusable for every pair it is in.

    ``features``: ``1 x D x h x w`` (processing frame), ``letterbox``: how the original
    image sits in that frame. ``terms``: what a model's head computes from this image alone
    (e.g. Local-ScaleNet's self-correlation terms), filled on first use by the model that
    encoded it and reused for every later pair.
    """

    features: torch.Tensor
    letterbox: Letterbox
    terms: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def nbytes(self) -> int:
        extra = sum(
            t.numel() * t.element_size()
            for v in self.terms.values()
            for t in (v if isinstance(v, tuple) else (v,))
            if isinstance(t, torch.Tensor)
        )
        return self.features.numel() * self.features.element_size() + extra


class ScaleModel(nn.Module):
    """Base class: a feature extractor + a head over pairs of encoded images."""

    arch = "ScaleModel"
    config_class: type
    default_weights = ""

    def __init__(self, config):
        super().__init__()
        self._folded: list = []  # [eval copy with BatchNorm folded] (a list: not a submodule)
        self._is_inference_copy = False
        self.config = config
        self.extractor = FeatureExtractor(config.width, config.feature_dim, config.batch_norm, config.backbone)
        self.meta: dict = {}

    def _build_cue_branches(self, cells: int) -> int:
        """Create the optional position-invariant cue branches (``config.topk``,
        ``config.warp_features``); returns the channels they add."""
        from .common import conv_bn_relu

        extra = 0
        self.topk = min(self.config.topk, cells)
        if self.topk:
            self.reduce_topk = nn.Sequential(conv_bn_relu(2 * self.topk, 64, 1), conv_bn_relu(64, 32, 1))
            extra += 32
        if self.config.warp_features:
            self.reduce_warp = nn.Sequential(conv_bn_relu(3 * self.config.feature_dim, 64, 1), conv_bn_relu(64, 64, 3))
            extra += 64
        return extra

    @property
    def grid_size(self) -> int:
        return self.config.image_size // FeatureExtractor.stride

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """``B x 3 x P x P`` in [0, 1] (P = ``config.image_size``) -> ``B x D x P/8 x P/8``."""
        if images.dim() != 4 or images.shape[1] != 3 or images.shape[-2:] != (self.config.image_size,) * 2:
            raise ValueError(
                f"encode: expected B x 3 x {self.config.image_size} x {self.config.image_size}, "
                f"got {tuple(images.shape)}"
            )
        if self._channels_last:
            images = images.contiguous(memory_format=torch.channels_last)
        return self._inference_model().extractor(images)

    def _inference_model(self) -> "ScaleModel":
        """``self``, or without gradients in eval mode a copy of the model with every BatchNorm
        folded into its convolution (same outputs to float precision, fewer passes over the
        activations). The copy is rebuilt after ``train()``, ``load_state_dict`` and moves
        (``to``/``cuda``/``half``); edit weights in place only in train mode."""
        if self._is_inference_copy or self.training or torch.is_grad_enabled():
            return self
        if not self._folded:
            folded = copy.deepcopy(self)
            folded._is_inference_copy = True
            self._folded.append(fold_batch_norm(folded))
        return self._folded[0]

    def train(self, mode: bool = True):
        if mode:
            self._folded.clear()  # the weights may change: the folded copy is rebuilt on use
        return super().train(mode)

    def load_state_dict(self, *args, **kwargs):
        self._folded.clear()
        return super().load_state_dict(*args, **kwargs)

    def _apply(self, fn, *args, **kwargs):
        self._folded.clear()
        return super()._apply(fn, *args, **kwargs)

    @property
    def _channels_last(self) -> bool:
        """Whether the convolution weights are stored channels-last (as :func:`~.registry.load_model`
        stores them on CPU, where oneDNN's convolutions and pooling are faster in that layout)."""
        w = next((p for p in self.extractor.parameters() if p.dim() == 4), None)
        return (
            w is not None
            and w.device.type == "cpu"
            and not w.is_contiguous()
            and w.is_contiguous(memory_format=torch.channels_last)
        )

    @property
    def input_side(self) -> int:
        """Files are decoded at a reduced size down to this longer side (4x the network's input)."""
        return 4 * self.config.image_size

    def load(self, image: ImageLike, name: str = "image") -> tuple[np.ndarray, tuple[int, int]]:
        """An image as the network needs it: ``(rgb, (H, W))``, a large file decoded at a reduced
        size (:func:`~localscale.io.load_image_reduced`), with the size of the full image; an image
        of more than 8 bits (16-bit, float) as float32 in [0, 1], without rounding to 8 bits."""
        return load_image_reduced(image, name, self.input_side, precise=True)

    def prepare(
        self, image: ImageLike, name: str = "image", original_shape: tuple[int, int] | None = None, turns: int = 0
    ) -> tuple[torch.Tensor, Letterbox]:
        """Load/validate an image and letterbox it: ``1 x 3 x P x P`` tensor + placement.

        ``original_shape``: the full ``(H, W)`` when ``image`` is an array reduced by :meth:`load`.
        ``turns``: the image turned by this many quarter turns (counter-clockwise, ``np.rot90``)
        first; the placement is that of the turned image."""
        if original_shape is None:
            rgb, original_shape = self.load(image, name)
        elif isinstance(image, (str, Path)):
            rgb = self.load(image, name)[0]
        else:  # a reduced copy: the size limits apply to the full image
            rgb = load_image_array(image, name, precise=True, full_shape=tuple(original_shape))
        if turns % 4:
            rgb = np.ascontiguousarray(np.rot90(rgb, turns))
            original_shape = tuple(original_shape[::-1]) if turns % 2 else original_shape
        boxed, lb = letterbox(rgb, self.config.image_size, original_shape)
        return to_tensor(boxed)[None].to(self.device), lb

    def _batch_images(self, images, name: str) -> tuple[list[np.ndarray], "BatchFormat"]:
        """A batch (``B x 3 x H x W`` or ``B x 1 x H x W`` tensor/array, or one ``3 x H x W``
        image; float in [0, 1] or uint8, any device) as ``H x W x 3`` images via :func:`load_image`
        (float stays float32, as :meth:`load` keeps it)."""
        fmt = BatchFormat.of(images, name)
        t = torch.from_numpy(np.asarray(images)) if fmt.numpy else images.detach()
        t = t[None] if fmt.single else t
        if t.dim() != 4 or t.shape[1] not in (1, 3):
            raise ImageError(
                f"{name}: expected a B x 3 x H x W batch (or one 3 x H x W image), got shape {tuple(np.shape(images))}"
            )
        if t.shape[0] == 0:
            raise ImageError(f"{name}: empty batch")
        hwc = t.cpu().permute(0, 2, 3, 1).numpy()
        return [load_image(hwc[i], f"{name}[{i}]", precise=True) for i in range(hwc.shape[0])], fmt

    def _letterbox_batch(self, rgbs: list[np.ndarray]) -> tuple[torch.Tensor, Letterbox]:
        boxed = [self.prepare(rgb) for rgb in rgbs]
        return torch.cat([x for x, _ in boxed]), boxed[0][1]

    def prepare_batch(self, images, name: str = "images") -> tuple[torch.Tensor, Letterbox, "BatchFormat"]:
        """Letterbox a batch of same-size images: ``B x 3 x P x P`` on the model's device.

        ``images``: ``B x 3 x H x W`` (or ``B x 1 x H x W`` gray, or one ``3 x H x W`` image)
        torch tensor or numpy array, float in [0, 1] or uint8, on any device. Each image goes
        through exactly what :meth:`prepare` does to a single image (the same conversion and
        resize), so batched predictions equal per-pair ones. All images share one placement.
        """
        rgbs, fmt = self._batch_images(images, name)
        return (*self._letterbox_batch(rgbs), fmt)

    def _forward_batch(self, images_a, images_b, head, bf16: bool, batch_size: int | None):
        """Run ``head(f_A, f_B)`` on batches of pairs, ``batch_size`` pairs per pass.

        Pairs are prepared as :meth:`encode_pair` does (a pair with exactly one gray image is
        compared in gray). Returns the two letterboxes, the output format and the head's outputs
        concatenated over the batch, as float (an output that is None stays None).
        """
        rgb_a, fmt = self._batch_images(images_a, "images A")
        rgb_b, _ = self._batch_images(images_b, "images B")
        if len(rgb_a) != len(rgb_b):
            raise ValueError(f"predict_batch: {len(rgb_a)} images A but {len(rgb_b)} images B")
        for i, (a, b) in enumerate(zip(rgb_a, rgb_b)):
            if is_gray(a) != is_gray(b):
                rgb_a[i], rgb_b[i] = to_gray3(a), to_gray3(b)
        (xa, lb_a), (xb, lb_b) = self._letterbox_batch(rgb_a), self._letterbox_batch(rgb_b)
        step = batch_size or xa.shape[0]
        chunks = []
        for i in range(0, xa.shape[0], step):
            with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=bf16):
                chunks.append(head(self.encode(xa[i : i + step]), self.encode(xb[i : i + step])))
        outs = tuple(None if parts[0] is None else torch.cat(parts).float() for parts in zip(*chunks))
        return lb_a, lb_b, fmt, outs

    @torch.inference_mode()
    def encode_image(
        self,
        image: ImageLike,
        name: str = "image",
        bf16: bool = False,
        original_shape: tuple[int, int] | None = None,
        turns: int = 0,
    ) -> EncodedImage:
        """Encode one image for later pairing (the feature cache's unit); ``original_shape`` and
        ``turns`` as in :meth:`prepare`."""
        x, lb = self.prepare(image, name, original_shape, turns)
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=bf16):
            f = self.encode(x)
        return EncodedImage(f.float(), lb)

    def load_pair(self, image_a: ImageLike, image_b: ImageLike):
        """Both images as :meth:`load` gives them, ``((rgb_a, (H_A, W_A)), (rgb_b, (H_B, W_B)))``;
        when exactly one of them is gray, the other is turned gray too, so that a colour
        difference is not read as a scale change."""
        (a, shape_a), (b, shape_b) = self.load(image_a, "image A"), self.load(image_b, "image B")
        if is_gray(a) != is_gray(b):
            a, b = to_gray3(a), to_gray3(b)
        return (a, shape_a), (b, shape_b)

    def encode_pair(
        self, image_a: ImageLike, image_b: ImageLike, bf16: bool = False
    ) -> tuple[EncodedImage, EncodedImage]:
        """Encode both images of a pair (:meth:`load_pair`: a gray image makes the pair gray)."""
        (a, shape_a), (b, shape_b) = self.load_pair(image_a, image_b)
        return self.encode_image(a, "image A", bf16, shape_a), self.encode_image(b, "image B", bf16, shape_b)

    @classmethod
    def from_pretrained(cls, path: str | Path | None = None, device: str | torch.device = "cpu"):
        """Load weights; ``path=None`` loads the default model bundled with the package."""
        if path is None:
            path = WEIGHTS_DIR / cls.default_weights
        return load_model(path, arch=cls.arch, device=device)


def is_gray(rgb: np.ndarray) -> bool:
    """True when the three channels of an ``H x W x 3`` image are equal."""
    return bool(np.array_equal(rgb[..., 0], rgb[..., 1]) and np.array_equal(rgb[..., 1], rgb[..., 2]))


def to_gray3(rgb: np.ndarray) -> np.ndarray:
    """Luminance replicated to three channels (unchanged if already gray)."""
    if is_gray(rgb):
        return rgb
    import cv2

    return np.repeat(cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)[..., None], 3, 2)


def upsample_to_original(grid: torch.Tensor, lb: Letterbox) -> torch.Tensor:
    """Resize a ``C x h x w`` map on the processing grid to the original image (``C x H x W``;
    a ``B x C x h x w`` batch gives ``B x C x H x W``).

    The grid covers the full ``P x P`` frame; it is upsampled to ``P x P``, the image's
    region cropped out of the padding, and resized to the original resolution.
    """
    import torch.nn.functional as F

    batched = grid.dim() == 4
    x = grid.float() if batched else grid[None].float()
    x = F.interpolate(x, size=(lb.size, lb.size), mode="bilinear", align_corners=False)
    x = x[..., lb.top : lb.top + lb.new_height, lb.left : lb.left + lb.new_width]
    x = F.interpolate(x, size=(lb.height, lb.width), mode="bilinear", align_corners=False)
    return x if batched else x[0]


def as_numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().float().numpy()


@dataclass(frozen=True)
class BatchFormat:
    """How a batch came in, so that outputs go back in the same form: numpy in -> numpy out,
    a tensor in -> tensors on its device; one unbatched image -> unbatched outputs."""

    numpy: bool
    single: bool
    device: torch.device

    @classmethod
    def of(cls, images, name: str = "images") -> "BatchFormat":
        if isinstance(images, torch.Tensor):
            if images.is_meta:
                raise ImageError(f"{name}: tensor on the meta device (shape only, no data)")
            return cls(False, images.dim() == 3, images.device)
        if isinstance(images, np.ndarray):
            return cls(True, images.ndim == 3, torch.device("cpu"))
        raise ImageError(
            f"{name}: expected a torch tensor or a numpy array (B x 3 x H x W), got {type(images).__name__}"
        )

    def out(self, t: torch.Tensor | None):
        """A ``B x ...`` result in this format (None passes through)."""
        if t is None:
            return None
        t = t[0] if self.single else t
        return as_numpy(t) if self.numpy else t.to(self.device)
