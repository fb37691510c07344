"""The training configuration of both scale models (:class:`TrainConfig`), and what a failed run raises."""

from __future__ import annotations

from dataclasses import dataclass

from ..core.errors import LocalScaleError
from ..data import PairConfig
from ..geometry import HomographyConfig
from ..models import LocalScaleNet, LocalScaleNetConfig, ScaleNet, ScaleNetConfig


class TrainingDiverged(RuntimeError):
    """The loss became NaN/inf; the last good checkpoint is kept."""


@dataclass
class TrainConfig:
    model: str = "local"  #: "local" (Local-ScaleNet) or "global" (ScaleNet)
    data: str = "../shared/data/train_images"
    out: str = "runs/local"
    backbone: str = "vgg"  #: "vgg" (trainable) or a frozen pre-trained one ("xfeat", "aliked")
    width: float = 0.25
    feature_dim: int = 128
    image_size: int = 192
    steps: int = 10000
    batch_size: int = 8
    lr: float = 1e-4
    lr_milestones: tuple[int, ...] = ()  #: steps where lr is multiplied by ``lr_gamma`` (paper: 0.1)
    lr_gamma: float = 0.1
    perspective: float = 0.45
    scale_min: float = 0.16
    scale_max: float = 6.0
    context: bool = False  #: B shows the photo's real surroundings of A (PairConfig.context)
    crop_min: float = 0.6  #: smallest side of A's crop, as a fraction of the photo
    holdout_every: int = 10  #: every n-th photo (sorted) is held out for validation
    val_pairs: int = 64
    val_every: int = 500
    ckpt_every: int = 250
    workers: int = 1
    seed: int = 0
    device: str = "cpu"
    amp: str = "auto"  #: "on"/"off"/"auto": fp16 AMP on CUDA, bf16 autocast on CPU
    #: ("auto" = CUDA, or a CPU with AVX-512 BF16 or AMX, where bf16 is faster)
    threads: int = 0  #: torch CPU threads (0 = torch default)
    vgg_weights: str = ""  #: optional local torchvision VGG16(-BN) state dict (width 1)
    init_weights: str = ""  #: checkpoint of the same architecture to fine-tune from (new schedule)
    init_extractor: str = ""  #: checkpoint whose feature extractor initialises this model
    init_head: str = ""  #: checkpoint whose layers after the feature extractor (reductions,
    #: cues, head) initialise this model (e.g. across backbones)
    freeze_extractor: bool = False  #: train only the correlation/reduction/head layers
    topk: int = 0  #: extra cue: k largest correlations per pixel
    warp_features: bool = False  #: extra cue: B's features soft-warped onto A
    visibility: bool = False  #: local: also predict per-pixel co-visibility (BCE loss)
    visibility_weight: float = 0.5  #: weight of the visibility BCE beside the KL loss
    loss_per_pair: bool = False  #: local: the KL averaged per pair first (zoom-ins show few cells of A)
    rotation: float = 30.0  #: max |in-plane rotation| in degrees of ordinary pairs
    translation: float = 0.2  #: max shift of A's centre in B, fraction of B's size
    identity_probability: float = 0.0  #: PairConfig: share of exact / near identity pairs
    full_rotation_probability: float = 0.0  #: PairConfig: share of pairs rotated over the whole circle
    low_overlap_probability: float = 0.0  #: PairConfig: share of pairs with A far off B's centre
    unrelated_probability: float = 0.0  #: PairConfig: share of pairs where B is another photo
    gray_one_side_probability: float = 0.0  #: PairConfig: one side gray
    strong_light_probability: float = 0.0  #: PairConfig: strong lighting change on B
    degrade_probability: float = 0.0  #: PairConfig: blur / noise / JPEG, each, on each side
    swap_probability: float = 0.0  #: PairConfig: share of pairs with A and B swapped
    photometric: float = 0.25  #: PairConfig: strength of the mild photometric jitter
    real_pairs: str = ""  #: labelled real pairs (``.npz`` files of :mod:`.real_pairs`, comma-separated)
    real_fraction: float = 0.5  #: share of training samples drawn from ``real_pairs``
    real_val_pairs: str = ""  #: labelled real pairs validated beside the synthetic ones (a held-out collection)

    def check(self) -> None:
        """Refuse settings that cannot train (one-line :class:`LocalScaleError`)."""
        import math

        for name in ("steps", "batch_size", "ckpt_every", "val_every", "val_pairs", "holdout_every"):
            if getattr(self, name) < 1:
                raise LocalScaleError(f"{name.replace('_', '-')} must be >= 1, got {getattr(self, name)}")
        if self.workers < 0:
            raise LocalScaleError(f"workers must be >= 0, got {self.workers}")
        if self.image_size < 32 or self.image_size % 8:
            raise LocalScaleError(f"image-size must be a multiple of 8 and >= 32, got {self.image_size}")
        for name in ("lr_gamma", "width"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise LocalScaleError(f"{name.replace('_', '-')} must be a finite number > 0, got {v}")
        if not 0 <= self.lr <= 1:
            raise LocalScaleError(f"lr must be in [0, 1] (Adam's step size), got {self.lr}")
        if self.feature_dim < 1:
            raise LocalScaleError(f"feature-dim must be >= 1, got {self.feature_dim}")
        if self.model not in ("local", "global"):
            raise LocalScaleError(f"unknown model {self.model!r} (use 'local' or 'global')")
        from ..core.devices import resolve_device

        resolve_device(self.device)  # cuda on a CPU-only torch, cuda:N beyond the GPUs, unknown names
        from ..models.backbones import BACKBONE_NAMES

        if self.backbone not in BACKBONE_NAMES:
            raise LocalScaleError(f"unknown backbone {self.backbone!r} (choose from {', '.join(BACKBONE_NAMES)})")
        if not 0 <= self.real_fraction <= 1:
            raise LocalScaleError(f"real-fraction must be in [0, 1], got {self.real_fraction}")
        if self.vgg_weights and self.backbone != "vgg":
            raise LocalScaleError(f"vgg-weights needs --backbone vgg, got {self.backbone!r}")

    def pair_config(self) -> PairConfig:
        if not 0 < self.crop_min <= 1:
            raise LocalScaleError(f"crop_min must be in (0, 1] (a fraction of the photo side), got {self.crop_min}")
        for name in (
            "identity_probability",
            "full_rotation_probability",
            "low_overlap_probability",
            "unrelated_probability",
            "gray_one_side_probability",
            "strong_light_probability",
            "degrade_probability",
            "swap_probability",
        ):
            if not 0 <= getattr(self, name) <= 1:
                raise LocalScaleError(f"{name.replace('_', '-')} must be in [0, 1], got {getattr(self, name)}")
        return PairConfig(
            image_size=self.image_size,
            homography=HomographyConfig(
                scale_range=(self.scale_min, self.scale_max),
                perspective=self.perspective,
                rotation_deg=self.rotation,
                translation=self.translation,
            ),
            crop_fraction=(self.crop_min, 1.0),
            context=self.context,
            photometric=self.photometric,
            identity_probability=self.identity_probability,
            full_rotation_probability=self.full_rotation_probability,
            low_overlap_probability=self.low_overlap_probability,
            unrelated_probability=self.unrelated_probability,
            gray_one_side_probability=self.gray_one_side_probability,
            strong_light_probability=self.strong_light_probability,
            degrade_probability=self.degrade_probability,
            swap_probability=self.swap_probability,
        )

    def build_model(self):
        if self.model == "local":
            return LocalScaleNet(
                LocalScaleNetConfig(
                    self.width,
                    self.feature_dim,
                    self.image_size,
                    topk=self.topk,
                    warp_features=self.warp_features,
                    visibility=self.visibility,
                    backbone=self.backbone,
                )
            )
        if self.model == "global":
            return ScaleNet(
                ScaleNetConfig(
                    self.width,
                    self.feature_dim,
                    self.image_size,
                    topk=self.topk,
                    warp_features=self.warp_features,
                    backbone=self.backbone,
                )
            )
        raise LocalScaleError(f"unknown model {self.model!r} (use 'local' or 'global')")


#: layers a fine-tune may add to a trained model (initialised fresh when absent from the source)
NEW_LAYER_PREFIXES = ("head.visible.",)
