"""Per-pixel reliability calibration, the visibility output and the pair-level check."""

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from localscale import LocalScaleNet, ScaleNet
from localscale.checkpoint import save_model
from localscale.models import load_model
from localscale.models.local_prediction import reliability, reliability_features
from localscale.models.scalenet import GlobalScalePrediction
from localscale.reliability import PairCheckConfig, auroc, check_pair, fit_calibration, flag_reasons, pair_statistics

TINY = dict(width=0.125, feature_dim=16, image_size=64)


def test_fit_calibration_recovers_a_known_logistic_model():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(20000, 3))
    true = np.array([0.5, 2.0, -1.0, 0.0])
    p = 1 / (1 + np.exp(-(true[0] + x @ true[1:])))
    y = rng.random(len(p)) < p
    coef = np.array(fit_calibration(x, y))
    assert np.allclose(coef, true, atol=0.15)


def test_fit_calibration_rejects_bad_shapes():
    with pytest.raises(ValueError, match="N x K"):
        fit_calibration(np.zeros(5), np.zeros(5))


def test_auroc_on_known_rankings():
    assert auroc([1, 2, 3, 4], [0, 0, 1, 1]) == 1.0
    assert auroc([4, 3, 2, 1], [0, 0, 1, 1]) == 0.0
    assert auroc([1, 1, 1, 1], [0, 1, 0, 1]) == 0.5
    assert math.isnan(auroc([1, 2], [1, 1]))


def _pred(scale, visible=None, rel=None):
    return SimpleNamespace(scale=np.asarray(scale, np.float32), visible=visible, reliability=rel)


def test_pair_statistics_and_flag():
    ones = np.ones((20, 30))
    fwd, bwd = _pred(2 * ones, ones, 0.9 * ones), _pred(0.5 * ones, ones)
    stats = pair_statistics(fwd, bwd)
    assert stats["inconsistency_log2"] == pytest.approx(0) and stats["visible_fraction"] == 1
    assert flag_reasons(stats) == []
    bad = pair_statistics(_pred(2 * ones, ones, 0.9 * ones), _pred(2 * ones, ones))  # both say "bigger"
    assert bad["inconsistency_log2"] == pytest.approx(2)
    assert any("disagree" in r for r in flag_reasons(bad))
    hidden = pair_statistics(_pred(ones, 0.01 * ones, 0.9 * ones), _pred(ones, ones))
    assert any("visible" in r for r in flag_reasons(hidden))
    shaky = pair_statistics(_pred(ones, ones, 0.1 * ones), _pred(ones, ones))
    assert any("reliability" in r for r in flag_reasons(shaky, PairCheckConfig(min_reliability=0.3)))


def test_reliability_features_and_calibrated_map():
    probs = torch.softmax(torch.randn(2, 13, 4, 5), 1)
    vis = torch.rand(2, 4, 5)
    f = reliability_features(probs, vis, 1)
    assert f.shape == (2, 3, 4, 5)
    assert torch.allclose(f[:, 1], vis)
    sharp = torch.zeros(1, 13, 1, 1)
    sharp[0, 6] = 1
    assert float(reliability_features(sharp, None, 1)[0, 2]) == pytest.approx(0)  # no spread
    r = reliability(probs, vis, (0.0, 1.0, 1.0, -1.0), 1)
    assert r.shape == (2, 4, 5) and float(r.min()) >= 0 and float(r.max()) <= 1


def test_visibility_output_and_calibration_survive_a_checkpoint(tmp_path, photos):
    torch.manual_seed(0)
    model = LocalScaleNet(**TINY, visibility=True, calibration=(0.1, 1.0, 2.0, -0.5)).eval()
    logits, vis = model(torch.rand(2, 3, 64, 64), torch.rand(2, 3, 64, 64), all_outputs=True)
    assert logits.shape == (2, 13, 8, 8) and vis.shape == (2, 1, 8, 8)
    a = photos["astronaut"][:120, :90]
    pred = model.predict(a, photos["coffee"])
    assert pred.visible.shape == a.shape[:2] and pred.reliability.shape == a.shape[:2]
    assert 0 <= pred.visible.min() and pred.visible.max() <= 1
    save_model(model, tmp_path / "m.pt")
    loaded = load_model(tmp_path / "m.pt", arch="LocalScaleNet")
    assert loaded.config.calibration == model.config.calibration
    assert np.allclose(loaded.predict(a, photos["coffee"]).reliability, pred.reliability, atol=1e-5)


def test_a_model_without_visibility_has_none():
    pred = (
        LocalScaleNet(**TINY)
        .eval()
        .predict(np.zeros((64, 64, 3), np.uint8) + 100, np.zeros((64, 64, 3), np.uint8) + 90)
    )
    assert pred.visible is None and pred.reliability is None


def test_bad_calibration_is_refused():
    with pytest.raises(ValueError, match="4 coefficients"):
        LocalScaleNet(**TINY, calibration=(1.0, 2.0))


def test_check_pair_runs_both_directions(photos):
    torch.manual_seed(0)
    model = LocalScaleNet(**TINY, visibility=True).eval()
    a, b = photos["astronaut"][:100, :120], photos["coffee"][:90, :80]
    check = check_pair(model, a, b)
    assert check.forward.scale.shape == a.shape[:2] and check.backward.scale.shape == b.shape[:2]
    assert check.reliable == (not check.reasons)


def test_global_prediction_flags_disagreeing_directions():
    probs = np.full(13, 1 / 13)
    ok = GlobalScalePrediction(scale=2.0, scale_ab=2.0, scale_ba=0.5, hard_scale=2.0, probs_ab=probs, probs_ba=probs)
    bad = GlobalScalePrediction(
        scale=1.35, scale_ab=1.8, scale_ba=1 / 1.0, hard_scale=2.0, probs_ab=probs, probs_ba=probs
    )
    assert ok.reliable and ok.inconsistency_log2 == pytest.approx(0)
    assert not bad.reliable


def test_swapping_a_and_b_inverts_the_global_scale(photos):
    torch.manual_seed(0)
    g = ScaleNet(**TINY).eval()
    a, b = photos["astronaut"], photos["chelsea"]
    assert g.predict(a, b).scale * g.predict(b, a).scale == pytest.approx(1, rel=1e-4)
