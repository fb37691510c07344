"""The scale space: 13 log-spaced bins, target distributions and read-outs.

Convention used everywhere in localscale: ``S_{A->B} > 1`` means that content looks
*bigger* in image B than in image A (B is a zoom-in of A).

Bins are ``s_i = sqrt(2) ** t`` for ``t = -6..6`` (0.125 .. 8). A scale value becomes a
distribution over the two neighbouring bins whose log-space expectation equals ``ln S``
exactly (clamped at the ends of the range), and the estimate is the soft expectation
``ln S = sum_i p_i ln s_i``. The hard read-out (D-ScaleNet) takes the arg-max bin.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

NUM_BINS: int = 13
BASE: float = math.sqrt(2.0)
#: exponents t of the bins, ``s_i = BASE ** t``
BIN_EXPONENTS = torch.arange(-(NUM_BINS // 2), NUM_BINS // 2 + 1, dtype=torch.float32)
#: ``ln s_i`` of the 13 bins
LOG_BINS = BIN_EXPONENTS * math.log(BASE)
MIN_SCALE: float = BASE ** float(BIN_EXPONENTS[0])
MAX_SCALE: float = BASE ** float(BIN_EXPONENTS[-1])


def bin_scales() -> torch.Tensor:
    """The 13 bin centres ``s_i`` (0.125 .. 8). Shape ``(13,)``."""
    return torch.exp(LOG_BINS)


def scale_to_distribution(scale: torch.Tensor, dim: int = -1) -> torch.Tensor:
    """Turn scale values into target distributions over the bins.

    The mass is split between the two bins around ``ln S`` so that
    ``sum_i p_i ln s_i == ln S`` exactly; scales outside ``[0.125, 8]`` are clamped.

    Args:
        scale: positive scales, any shape ``(*)``.
        dim: where the bin axis is inserted in the output.

    Returns:
        distribution with a new axis of size 13 at ``dim``.
    """
    scale = torch.as_tensor(scale, dtype=torch.float32)
    if not torch.isfinite(scale).all() or (scale <= 0).any():
        raise ValueError("scale_to_distribution: scales must be finite and > 0")
    t = torch.log(scale) / math.log(BASE)
    t = t.clamp(float(BIN_EXPONENTS[0]), float(BIN_EXPONENTS[-1])) - float(BIN_EXPONENTS[0])
    lower = t.floor().clamp(max=NUM_BINS - 2)
    w_upper = t - lower
    lower = lower.long()
    dist = torch.zeros(*scale.shape, NUM_BINS, dtype=torch.float32, device=scale.device)
    dist.scatter_(-1, lower.unsqueeze(-1), (1.0 - w_upper).unsqueeze(-1))
    dist.scatter_add_(-1, (lower + 1).unsqueeze(-1), w_upper.unsqueeze(-1))
    return dist.movedim(-1, dim)


def soft_log_scale(probs: torch.Tensor, dim: int = 1) -> torch.Tensor:
    """Soft read-out in log space, ``ln S = sum_i p_i ln s_i``.

    Args:
        probs: probabilities with the 13 bins on ``dim`` (e.g. ``B x 13 x H x W``).

    Returns:
        ``ln S`` with ``dim`` removed (e.g. ``B x H x W``).
    """
    _check_bins(probs, dim)
    shape = [1] * probs.dim()
    shape[dim] = NUM_BINS
    return (probs * LOG_BINS.to(probs).view(shape)).sum(dim)


def soft_scale(probs: torch.Tensor, dim: int = 1) -> torch.Tensor:
    """Soft-scale ``S = exp(sum_i p_i ln s_i)`` (ScaleNet read-out)."""
    return torch.exp(soft_log_scale(probs, dim))


def hard_scale(probs: torch.Tensor, dim: int = 1) -> torch.Tensor:
    """Hard read-out of D-ScaleNet: the scale of the arg-max bin."""
    _check_bins(probs, dim)
    return torch.exp(LOG_BINS.to(probs.device)[probs.argmax(dim)])


def entropy(probs: torch.Tensor, dim: int = 1) -> torch.Tensor:
    """Shannon entropy (nats) of the distributions on ``dim``."""
    _check_bins(probs, dim)
    return -(probs * torch.log(probs.clamp_min(1e-12))).sum(dim)


def confidence(probs: torch.Tensor, dim: int = 1) -> torch.Tensor:
    """``1 - entropy / ln 13``: 1 for a one-hot distribution, 0 for a uniform one."""
    return 1.0 - entropy(probs, dim) / math.log(NUM_BINS)


def kl_loss(
    logits: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None, dim: int = 1, per_pair: bool = False
) -> torch.Tensor:
    """Mean ``KL(target || softmax(logits))`` over the positions where ``mask`` is true.

    Args:
        logits: ``B x 13 x H x W`` (or ``B x 13``).
        target: distributions of the same shape.
        mask: ``B x H x W`` boolean (or ``B``); ``None`` means everywhere.
        per_pair: the mean of each pair's mean over its masked positions (pairs without any left
            out), so that a pair with few positions (a strong zoom-in shows little of A) weighs as
            much as one with many; default: the mean over all masked positions of the batch.
    """
    logp = F.log_softmax(logits.float(), dim=dim)
    kl = (target * (torch.log(target.clamp_min(1e-12)) - logp)).sum(dim)
    if mask is None:
        return kl.mean()
    mask = mask.to(kl.dtype)
    if per_pair and kl.dim() > 1:
        count = mask.flatten(1).sum(1)
        means = (kl * mask).flatten(1).sum(1) / count.clamp_min(1.0)
        return means[count > 0].mean() if bool((count > 0).any()) else means.sum() * 0.0
    return (kl * mask).sum() / mask.sum().clamp_min(1.0)


def scale_ratio_error(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Scale-ratio error ``r = max(s, g) / min(s, g) >= 1`` (element-wise)."""
    pred = torch.as_tensor(pred, dtype=torch.float64)
    gt = torch.as_tensor(gt, dtype=torch.float64)
    return torch.exp(torch.abs(torch.log(pred) - torch.log(gt)))


def consistent_log_scale(log_s_ab: torch.Tensor, log_s_ba: torch.Tensor) -> torch.Tensor:
    """ScaleNet consistency check: ``ln S = (ln S_AB - ln S_BA) / 2``."""
    return 0.5 * (log_s_ab - log_s_ba)


def _check_bins(probs: torch.Tensor, dim: int) -> None:
    if probs.shape[dim] != NUM_BINS:
        raise ValueError(f"expected {NUM_BINS} scale bins on dim {dim}, got shape {tuple(probs.shape)}")
