import cv2
import numpy as np
import pytest
import torch

from localscale import CheckpointError, ImageError, LocalScaleNet, ScaleNet
from localscale.checkpoint import save_model
from localscale.models import load_model
from localscale.models.common import correlation, transpose_correlation

TINY = dict(width=0.125, feature_dim=16, image_size=64)


@pytest.fixture(scope="module")
def local_model():
    torch.manual_seed(0)
    return LocalScaleNet(**TINY).eval()


def test_forward_shapes(local_model):
    a, b = torch.rand(2, 3, 64, 64), torch.rand(2, 3, 64, 64)
    assert local_model(a, b).shape == (2, 13, 8, 8)
    g = ScaleNet(**TINY).eval()
    l_ab, l_ba = g(a, b)
    assert l_ab.shape == (2, 13) and l_ba.shape == (2, 13)


def test_predict_returns_map_at_original_resolution(local_model, photos):
    a = photos["astronaut"][:300, :200]
    pred = local_model.predict(a, photos["coffee"])
    assert pred.scale.shape == (300, 200) and pred.confidence.shape == (300, 200)
    assert np.isfinite(pred.scale).all() and (pred.scale > 0).all()
    assert pred.probs.shape == (13, 8, 8)
    assert torch.allclose(pred.probs.sum(0), torch.ones(8, 8), atol=1e-5)
    assert pred.distribution().shape == (13, 300, 200)


def test_letterbox_correction_follows_the_convention(local_model, photos):
    """B enlarged 2x looks the same in the processing frame; the returned scale must be 2x larger."""
    a = photos["coffee"]
    b = photos["chelsea"][:200, :300]
    b2 = cv2.resize(b, (600, 400), interpolation=cv2.INTER_LINEAR)
    s1 = local_model.predict(a, b, anchor=False).scale
    s2 = local_model.predict(a, b2, anchor=False).scale
    assert np.median(s2 / s1) == pytest.approx(2.0, rel=0.05)


def test_cached_features_give_identical_predictions(local_model, photos):
    ea = local_model.encode_image(photos["coffee"])
    eb = local_model.encode_image(photos["chelsea"])
    p1 = local_model.predict_from_features(ea, eb)
    p2 = local_model.predict(photos["coffee"], photos["chelsea"], anchor=False)
    assert np.allclose(p1.scale, p2.scale, rtol=1e-5)


def test_self_terms_are_computed_once_per_encoding(local_model, photos):
    ea = local_model.encode_image(photos["coffee"])
    eb = local_model.encode_image(photos["chelsea"])
    ec = local_model.encode_image(photos["astronaut"])
    size = ea.nbytes
    p_ab = local_model.predict_from_features(ea, eb)
    assert len(ea.terms) == 1 and ea.nbytes > size and not eb.terms
    # the kept terms are the ones the full head computes: same maps with and without them
    ea.terms.clear()
    p_ac = local_model.predict_from_features(ea, ec)
    assert np.allclose(local_model.predict_from_features(ea, ec).scale, p_ac.scale, rtol=1e-6)
    assert np.allclose(local_model.predict_from_features(ea, eb).scale, p_ab.scale, rtol=1e-6)
    assert not np.allclose(p_ab.scale, p_ac.scale)  # B still matters


def test_loaded_models_are_channels_last_on_cpu_with_the_same_output(tmp_path, local_model, photos):
    path = tmp_path / "m.pt"
    save_model(local_model, path)
    loaded = LocalScaleNet.from_pretrained(path)
    w = loaded.extractor.backbone.features[0].weight
    assert w.is_contiguous(memory_format=torch.channels_last) and not w.is_contiguous()
    assert loaded._channels_last and not local_model._channels_last
    a, b = photos["coffee"], photos["chelsea"]
    assert np.allclose(loaded.predict(a, b).scale, local_model.predict(a, b).scale, rtol=1e-4)


def test_global_consistency_reuses_one_correlation():
    fa, fb = torch.randn(2, 8, 5, 6), torch.randn(2, 8, 4, 3)
    assert torch.allclose(transpose_correlation(correlation(fa, fb), (4, 3)), correlation(fb, fa), atol=1e-5)


def test_global_predict_consistency(photos):
    torch.manual_seed(0)
    g = ScaleNet(**TINY).eval()
    p = g.predict(photos["coffee"], photos["chelsea"])
    assert p.scale == pytest.approx(np.sqrt(p.scale_ab / p.scale_ba), rel=1e-5)
    assert p.probs_ab.shape == (13,) and p.hard_scale > 0


def test_checkpoint_roundtrip_and_errors(tmp_path, local_model, photos):
    path = tmp_path / "m.pt"
    save_model(local_model, path)
    loaded = LocalScaleNet.from_pretrained(path)
    x = torch.rand(1, 3, 64, 64)
    assert torch.allclose(loaded(x, x), local_model(x, x), atol=1e-6)

    with pytest.raises(CheckpointError, match="is a LocalScaleNet, expected a ScaleNet"):
        ScaleNet.from_pretrained(path)
    with pytest.raises(CheckpointError, match="not found"):
        LocalScaleNet.from_pretrained(tmp_path / "missing.pt")
    trunc = tmp_path / "trunc.pt"
    trunc.write_bytes(path.read_bytes()[:2000])
    with pytest.raises(CheckpointError, match="truncated or corrupt"):
        load_model(trunc)
    ck = torch.load(path, weights_only=False)
    ck["config"]["feature_dim"] = 32
    torch.save(ck, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="do not match"):
        load_model(tmp_path / "other.pt")
    torch.save({"weights": 1}, tmp_path / "foreign.pt")
    with pytest.raises(CheckpointError, match="not a localscale checkpoint"):
        load_model(tmp_path / "foreign.pt")


def test_bad_images_are_refused_with_a_clear_error(local_model, tmp_path):
    with pytest.raises(ImageError, match="not found"):
        local_model.predict(tmp_path / "nope.png", tmp_path / "nope.png")
    with pytest.raises(ImageError, match="smaller than the minimum"):
        local_model.predict(np.zeros((10, 10, 3), np.uint8), np.zeros((100, 100, 3), np.uint8))
    with pytest.raises(ValueError, match="encode: expected"):
        local_model.encode(torch.rand(1, 3, 32, 32))


def test_position_invariant_cues_variant(tmp_path, photos):
    """top-k correlation profile + warped-B-features branch (the shipped configuration)."""
    torch.manual_seed(0)
    m = LocalScaleNet(**TINY, topk=100, warp_features=True).eval()  # topk > 8*8 cells is clipped
    x = torch.rand(2, 3, 64, 64)
    assert m(x, x.flip(-1)).shape == (2, 13, 8, 8)
    save_model(m, tmp_path / "v.pt")
    m2 = load_model(tmp_path / "v.pt")
    assert m2.config.topk == 100 and m2.config.warp_features
    assert torch.allclose(m2(x, x), m(x, x), atol=1e-6)


def test_planar_option_gives_a_homography_scale_field(local_model, photos):
    pred = local_model.predict(photos["coffee"], photos["chelsea"], planar=True)
    raw = local_model.predict(photos["coffee"], photos["chelsea"])
    assert pred.scale.shape == raw.scale.shape and np.isfinite(pred.scale).all()
    ls = np.log(pred.scale)  # ln S = c - 1.5 ln(1 + p.x) is smooth: tiny second differences
    assert np.abs(np.diff(ls, 2, axis=1)).max() < 1e-3


def test_global_with_cues_is_symmetric_in_structure():
    """Swapping A and B swaps the two directions (the head is shared, the correlation computed once)."""
    torch.manual_seed(0)
    g = ScaleNet(**TINY, topk=16, warp_features=True).eval()
    a, b = torch.rand(1, 3, 64, 64), torch.rand(1, 3, 64, 64)
    l_ab, l_ba = g(a, b)
    m_ab, m_ba = g(b, a)
    assert torch.allclose(l_ab, m_ba, atol=1e-4) and torch.allclose(l_ba, m_ab, atol=1e-4)


def _orientation_sensitive(g):
    """Replace ScaleNet's encoder by the letterboxed gray image and its head by a function of the
    two that depends on the images' orientation and keeps the structure of the real head
    (swapping A and B swaps the directions)."""
    from localscale.models.base import EncodedImage
    from localscale.models.scalenet import GlobalScalePrediction

    def encode(image, name="image", bf16=False, original_shape=None, turns=0):
        x, lb = g.prepare(image, name, original_shape, turns)
        return EncodedImage(x.mean(1, keepdim=True), lb)

    def top(e):
        f = e.features
        return float(f[..., : f.shape[-2] // 2, :].mean() - f[..., f.shape[-2] // 2 :, :].mean())

    def left(e):
        f = e.features
        return float(f[..., : f.shape[-1] // 2].mean() - f[..., f.shape[-1] // 2 :].mean())

    def head(ea, eb, bf16=False):
        shared = 100 * left(ea) * left(eb) + 1000 * top(ea) * top(eb)  # common bias: the inconsistency
        ls_ab, ls_ba = 20 * (top(eb) - top(ea)) + shared, 20 * (top(ea) - top(eb)) + shared
        probs = np.full(13, 1 / 13, np.float32)
        return GlobalScalePrediction(
            scale=float(np.exp((ls_ab - ls_ba) / 2)),
            scale_ab=float(np.exp(ls_ab)),
            scale_ba=float(np.exp(ls_ba)),
            hard_scale=1.0,
            probs_ab=probs,
            probs_ba=probs,
        )

    g.encode_image, g.predict_from_features = encode, head
    return g


def test_global_quarter_turns_keep_the_most_consistent_prediction(photos):
    torch.manual_seed(0)
    g = _orientation_sensitive(ScaleNet(**TINY).eval())
    a, b = photos["coffee"][:, :200], photos["chelsea"][:150]
    upright = g.predict(a, b, turns=False)
    assert not upright.reliable and upright.turns == (0, 0)
    rot = lambda x, k: np.ascontiguousarray(np.rot90(x, k))  # noqa: E731
    candidates = (
        [upright]
        + [g.predict(a, rot(b, k), turns=False) for k in (1, 2, 3)]
        + [g.predict(rot(a, k), b, turns=False) for k in (1, 2, 3)]
    )
    incs = [c.inconsistency_log2 for c in candidates]
    assert max(incs) - min(incs) > 0.1, "the turns must matter for this test"
    p = g.predict(a, b)
    assert p.inconsistency_log2 == pytest.approx(min(incs), abs=1e-9) and p.inconsistency_log2 < incs[0]
    assert p.scale == pytest.approx(candidates[int(np.argmin(incs))].scale, rel=1e-6)
    k = max(p.turns)
    assert k in (1, 2, 3) and p.turns in ((0, k), (k, 0))
    # turns of A and of B are both tried, so swapping A and B still inverts the scale exactly
    q = g.predict(b, a)
    assert p.scale * q.scale == pytest.approx(1, rel=1e-6) and q.turns == p.turns[::-1]
    # a reliable upright prediction is kept as it is
    g.TURN_MARGIN_LOG2 = incs[0] - min(incs) + 0.01  # not better by the margin: the upright one stays
    assert g.predict(a, b).turns == (0, 0) and g.predict(a, b).scale == upright.scale
    kept = g.predict(a, rot(b, 1))
    assert kept.reliable and kept.turns == (0, 0) and kept.scale == candidates[1].scale


def test_folded_inference_copy_matches_and_follows_weight_changes(local_model, tmp_path):
    from localscale.models.common import fold_batch_norm

    torch.manual_seed(1)
    model = LocalScaleNet(**TINY)
    model.train()
    model(torch.rand(2, 3, 64, 64), torch.rand(2, 3, 64, 64))  # BatchNorm statistics move off 0 / 1
    model.eval()
    x = torch.rand(1, 3, 64, 64)
    with torch.no_grad():
        folded = model.encode(x)
        assert len(model._folded) == 1
        assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in model._folded[0].modules())
        assert torch.allclose(folded, model.extractor(x), atol=1e-5)
        model.load_state_dict(local_model.state_dict())  # new weights reach inference
        assert not model._folded
        assert torch.allclose(model.encode(x), local_model.extractor(x), atol=1e-5)
        fa, fb = model.encode(x), model.encode(x.flip(-1))
        with torch.enable_grad():
            plain = model.forward_features_all(fa, fb)[0]  # the model's own modules
        assert torch.allclose(model.forward_features_all(fa, fb)[0], plain, atol=1e-4)
    with torch.enable_grad():  # training path: the real modules
        assert model.encode(x).requires_grad
    assert isinstance(
        fold_batch_norm(torch.nn.Sequential(torch.nn.Conv2d(1, 2, 3), torch.nn.BatchNorm2d(2).eval()))[0],
        torch.nn.Conv2d,
    )
