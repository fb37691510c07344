import math

import pytest
import torch

from localscale import scales


def test_bins_are_log_spaced_powers_of_sqrt2():
    s = scales.bin_scales()
    assert s.shape == (13,)
    assert (
        s[0].item() == pytest.approx(0.125) and s[6].item() == pytest.approx(1.0) and s[-1].item() == pytest.approx(8.0)
    )
    assert torch.allclose(s[1:] / s[:-1], torch.full((12,), math.sqrt(2)))


def test_target_distribution_has_exact_log_expectation():
    s = torch.exp(torch.empty(1000).uniform_(math.log(0.125), math.log(8.0)))
    d = scales.scale_to_distribution(s)
    assert d.shape == (1000, 13)
    assert torch.allclose(d.sum(-1), torch.ones(1000))
    assert ((d > 0).sum(-1) <= 2).all()
    assert torch.allclose(scales.soft_scale(d, dim=-1), s, rtol=1e-5)


def test_target_distribution_mass_sits_on_neighbouring_bins():
    d = scales.scale_to_distribution(torch.tensor([1.5]))[0]
    nz = torch.nonzero(d).flatten().tolist()
    assert nz == [7, 8]  # between sqrt(2) and 2


def test_target_clamps_at_the_ends():
    d = scales.scale_to_distribution(torch.tensor([0.01, 100.0, 8.0, 0.125]))
    assert d[0, 0] == 1 and d[1, -1] == 1 and d[2, -1] == 1 and d[3, 0] == 1


def test_target_rejects_non_positive():
    with pytest.raises(ValueError):
        scales.scale_to_distribution(torch.tensor([0.0]))


def test_dense_layout_and_hard_readout():
    s = torch.tensor([[[0.5, 2.0], [1.0, 3.9]]])  # B x H x W
    d = scales.scale_to_distribution(s, dim=1)  # B x 13 x H x W
    assert d.shape == (1, 13, 2, 2)
    assert torch.allclose(scales.soft_scale(d), s, rtol=1e-5)
    hard = scales.hard_scale(d)
    assert torch.allclose(hard[0, 0], torch.tensor([0.5, 2.0]))
    assert hard[0, 1, 1].item() == pytest.approx(4.0)  # 3.9 is closer (in log) to 4 than to 2*sqrt2


def test_kl_loss_is_zero_at_target_and_masked():
    s = torch.tensor([[[0.7, 3.0]]])
    target = scales.scale_to_distribution(s, dim=1)
    perfect = torch.log(target.clamp_min(1e-12))
    assert scales.kl_loss(perfect, target).item() == pytest.approx(0.0, abs=1e-6)
    wrong = torch.zeros_like(perfect)
    assert scales.kl_loss(wrong, target).item() > 0.5
    mask = torch.tensor([[[True, False]]])
    half = perfect.clone()
    half[..., 1] = 0  # wrong only where masked out
    assert scales.kl_loss(half, target, mask).item() == pytest.approx(0.0, abs=1e-6)


def test_ratio_error_and_consistency():
    assert scales.scale_ratio_error(torch.tensor(2.0), torch.tensor(0.5)).item() == pytest.approx(4.0)
    assert scales.scale_ratio_error(torch.tensor(0.5), torch.tensor(2.0)).item() == pytest.approx(4.0)
    ls = scales.consistent_log_scale(torch.tensor(math.log(2.2)), torch.tensor(-math.log(1.8)))
    assert math.exp(ls.item()) == pytest.approx(math.sqrt(2.2 * 1.8))


def test_confidence_bounds():
    one_hot = torch.zeros(1, 13)
    one_hot[0, 3] = 1
    uniform = torch.full((1, 13), 1 / 13)
    assert scales.confidence(one_hot).item() == pytest.approx(1.0)
    assert scales.confidence(uniform).item() == pytest.approx(0.0, abs=1e-6)


def test_kl_loss_per_pair_weighs_each_pair_once():
    from localscale.scales import kl_loss, scale_to_distribution

    torch.manual_seed(0)
    logits = torch.zeros(2, 13, 4, 4)
    target = scale_to_distribution(torch.full((2, 4, 4), 8.0), dim=1)  # far from the uniform prediction
    target[1] = scale_to_distribution(torch.ones(1, 4, 4), dim=1)[0]
    logits[1, 6] = 20.0  # pair 1 predicts its truth: KL ~ 0
    mask = torch.zeros(2, 4, 4, dtype=torch.bool)
    mask[0, 0, 0] = True  # pair 0: one cell (a strong zoom-in), pair 1: all 16
    mask[1] = True
    one = kl_loss(logits[:1], target[:1], mask[:1])
    pooled, per_pair = kl_loss(logits, target, mask), kl_loss(logits, target, mask, per_pair=True)
    assert torch.isclose(per_pair, one / 2, rtol=1e-4)  # each pair weighs 1/2
    assert torch.isclose(pooled, one / 17, rtol=1e-3)  # the one cell weighs 1/17
    empty = torch.zeros_like(mask)
    assert kl_loss(logits, target, empty, per_pair=True) == 0
