"""Descriptor matching and geometric verification against a known homography.

* :func:`match_descriptors`: mutual nearest neighbours (``kornia.feature.match_mnn``), or
  with ``ratio`` the mutual NN that also pass Lowe's ratio test
  (``kornia.feature.match_smnn``).
* :func:`reprojection_errors`: ``|| H x_A - x_B ||`` in pixels of B for each match
  (the HPatches MMA protocol of D2-Net).
* :func:`matching_accuracy`: fraction of matches with error below thresholds.
"""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
import torch
from kornia.feature import match_mnn, match_smnn

from ..errors import LocalScaleError
from ..geometry import orient_homography, project  # noqa: F401  (orient_homography re-exported)


def match_descriptors(desc_a: torch.Tensor, desc_b: torch.Tensor, ratio: Optional[float] = None
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
        raise LocalScaleError(f"descriptors must be N x D and M x D, got {tuple(desc_a.shape)} and {tuple(desc_b.shape)}")
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


def reprojection_errors(keypoints_a: np.ndarray, keypoints_b: np.ndarray, matches: np.ndarray,
                        H: np.ndarray) -> np.ndarray:
    """``|| H x_A - x_B ||`` (pixels of B) for each match; ``inf`` where ``H x_A`` is undefined."""
    matches = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
    if len(matches) == 0:
        return np.zeros(0, np.float64)
    pa = np.asarray(keypoints_a, np.float64)[matches[:, 0]]
    pb = np.asarray(keypoints_b, np.float64)[matches[:, 1]]
    err = np.linalg.norm(project(H, pa) - pb, axis=1)
    return np.where(np.isfinite(err), err, np.inf)


def matching_accuracy(errors: np.ndarray, thresholds: Sequence[float] = (5.0,)) -> np.ndarray:
    """Fraction of matches with error ``< t`` for each threshold (0 when there are no matches)."""
    errors = np.asarray(errors, np.float64)
    if errors.size == 0:
        return np.zeros(len(thresholds))
    return np.array([(errors < t).mean() for t in thresholds])
