"""Nearest-neighbour matching of descriptors.

* :func:`match_descriptors`: mutual nearest neighbours (``kornia.feature.match_mnn``), or
  with ``ratio`` the mutual NN that also pass Lowe's symmetric ratio test
  (``kornia.feature.match_smnn``);
* :func:`ratio_mutual_matches`: Lowe's test from A to B, then the mutual check (OpenCV's
  brute-force matcher, as OpenCV SIFT users match).
"""

from __future__ import annotations

from typing import Optional

import cv2
import numpy as np
import torch
from kornia.feature import match_mnn, match_smnn

from ..core.errors import LocalScaleError


def match_descriptors(
    desc_a: torch.Tensor, desc_b: torch.Tensor, ratio: Optional[float] = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mutual nearest-neighbour matching (+ optional ratio test).

    Args:
        desc_a: ``N x D``; desc_b: ``M x D`` (same D).
        ratio: Lowe ratio threshold in (0, 1]; ``None`` = plain mutual NN.

    Returns:
        ``(distances K, matches K x 2 long)`` with ``matches[:, 0]`` indexing A, ``[:, 1]`` B.
    """
    desc_a, desc_b = torch.as_tensor(desc_a).float(), torch.as_tensor(desc_b).float()
    if desc_a.dim() != 2 or desc_b.dim() != 2 or desc_a.shape[1] != desc_b.shape[1]:
        raise LocalScaleError(
            f"descriptors must be N x D and M x D, got {tuple(desc_a.shape)} and {tuple(desc_b.shape)}"
        )
    if len(desc_a) == 0 or len(desc_b) == 0:
        return torch.zeros(0), torch.zeros(0, 2, dtype=torch.long)
    if ratio is None:
        d, idx = match_mnn(desc_a, desc_b)
    else:
        if not 0 < ratio <= 1:
            raise LocalScaleError(f"ratio must be in (0, 1], got {ratio}")
        if len(desc_a) < 2 or len(desc_b) < 2:
            d, idx = match_mnn(desc_a, desc_b)
        else:
            d, idx = match_smnn(desc_a, desc_b, ratio)
    return d.reshape(-1), idx.long().reshape(-1, 2)


def ratio_mutual_matches(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float = 0.8) -> np.ndarray:
    """Mutual nearest neighbours (L2) that pass Lowe's ratio test, with OpenCV's brute-force matcher.
    ``desc_a``: ``N x D``, ``desc_b``: ``M x D`` float32; returns ``K x 2`` int64 indices (A, B)."""
    if len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros((0, 2), np.int64)
    bf = cv2.BFMatcher(cv2.NORM_L2)
    fwd = bf.knnMatch(desc_a, desc_b, k=2)
    back = {m.queryIdx: m.trainIdx for m in bf.match(desc_b, desc_a)}
    out = [
        (m.queryIdx, m.trainIdx)
        for m, n in (p for p in fwd if len(p) == 2)
        if m.distance < ratio * n.distance and back.get(m.trainIdx) == m.queryIdx
    ]
    return np.array(out, np.int64).reshape(-1, 2)
