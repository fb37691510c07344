"""Pruning before LightGlue: a pair whose stored descriptors share too few mutual nearest neighbours
that pass Lowe's ratio test is not given to LightGlue (it would find nothing that verifies).

:func:`mutual_nn_count` counts them from ``features.h5``'s descriptors (one matrix product, a few
milliseconds for 2048 keypoints, against ~1 s of LightGlue on one CPU core);
:func:`skip_pair` applies the threshold. The threshold was chosen on the shared collections
(``docs/decisions/prune-before-lightglue.md``).

Example::

    if skip_pair(fa.descriptors, fb.descriptors, min_mnn=16):
        matches = np.zeros((0, 2), np.int64)
"""

from __future__ import annotations

import torch

#: Lowe's ratio of the count (symmetric: in both directions)
PRUNE_RATIO = 0.9


def mutual_nn_count(desc_a, desc_b, ratio: float = PRUNE_RATIO) -> int:
    """Mutual nearest neighbours (L2 of the descriptors, ``N x D`` and ``M x D``) that pass Lowe's
    ratio test ``ratio`` in both directions (1.0: no ratio test)."""
    a, b = torch.as_tensor(desc_a).float(), torch.as_tensor(desc_b).float()
    if len(a) < 2 or len(b) < 2:
        return 0
    with torch.inference_mode():
        d = torch.cdist(a, b)
        d_ab, i_ab = d.topk(2, dim=1, largest=False)
        d_ba, i_ba = d.topk(2, dim=0, largest=False)
        mutual = i_ba[0][i_ab[:, 0]] == torch.arange(len(a))
        ok = mutual & (d_ab[:, 0] <= ratio * d_ab[:, 1])
        ok &= d_ba[0][i_ab[:, 0]] <= ratio * d_ba[1][i_ab[:, 0]]
    return int(ok.sum())


def skip_pair(desc_a, desc_b, min_mnn: int, ratio: float = PRUNE_RATIO) -> bool:
    """Whether a pair shares fewer than ``min_mnn`` ratio-tested mutual nearest neighbours
    (:func:`mutual_nn_count`); ``min_mnn`` 0 never skips."""
    return min_mnn > 0 and mutual_nn_count(desc_a, desc_b, ratio) < min_mnn
