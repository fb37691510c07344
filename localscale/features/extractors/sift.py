"""OpenCV's SIFT: DoG keypoints and 128-D descriptors (the ``sift`` matcher)."""

from __future__ import annotations

import cv2
import numpy as np
import torch

from ..registry import register
from .base import Extractor


@register
class SIFT(Extractor):
    """OpenCV SIFT: DoG keypoints and 128-D descriptors, ``num_features`` at most."""

    name = "sift"
    default_conf = {"num_features": 4096}
    max_side = 2048
    ratio_test = "a_to_b"
    #: Lowe's ratio test 0.8 from A to B, then the mutual nearest-neighbour check
    matchers = {"sift": {"ratio": 0.8}}

    def _extract(self, image: np.ndarray):
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
        kps, desc = cv2.SIFT_create(nfeatures=self.conf["num_features"]).detectAndCompute(
            np.ascontiguousarray(gray), None
        )
        xy = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
        d = torch.from_numpy(np.zeros((0, 128), np.float32) if desc is None else desc)
        frames = np.array([(k.size, k.angle) for k in kps], np.float32).reshape(-1, 2)
        return xy, d, np.array([k.response for k in kps], np.float32), frames
