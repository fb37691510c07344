import cv2
import numpy as np
import pytest
import torch

from localscale import LocalScaleNet
from localscale.cache import FeatureCache, predict_pairs
from localscale.core.errors import LocalScaleError

TINY = dict(width=0.125, feature_dim=16, image_size=64)


@pytest.fixture(scope="module")
def files(tmp_path_factory, photos):
    d = tmp_path_factory.mktemp("cache")
    for name in ("coffee", "chelsea"):
        img = cv2.resize(photos[name], (160, 120), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(d / f"{name}.png"), img[..., ::-1])
    return d


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return LocalScaleNet(**TINY).eval()


def test_an_empty_cache_is_the_one_used(model, files):
    cache = FeatureCache(model, bf16=True)
    assert len(cache) == 0 and not cache  # falsy while empty
    pairs = [(files / "coffee.png", files / "chelsea.png"), (files / "chelsea.png", files / "coffee.png")]
    assert len(list(predict_pairs(model, pairs, cache, batch_size=2))) == 2
    assert (cache.misses, cache.hits, len(cache)) == (2, 2, 2)


def test_read_out_options_reach_the_batched_head(model, files):
    a, b = files / "coffee.png", files / "chelsea.png"
    ((_, soft),) = predict_pairs(model, [(a, b)])
    ((_, hard),) = predict_pairs(model, [(a, b)], hard=True)
    ((_, planar),) = predict_pairs(model, [(a, b)], planar=True)
    assert np.allclose(soft.scale, model.predict(a, b, anchor=False).scale, rtol=1e-4)
    assert np.allclose(hard.scale, model.predict(a, b, hard=True, anchor=False).scale, rtol=1e-4)
    assert np.allclose(planar.scale, model.predict(a, b, planar=True, anchor=False).scale, rtol=1e-4)
    assert not np.allclose(soft.scale, hard.scale)


def test_results_keep_the_input_order_when_a_pair_fails(model, files):
    a, b = files / "coffee.png", files / "chelsea.png"
    pairs = [(a, b), (a, files / "missing.png"), (b, a)]
    out = list(predict_pairs(model, pairs, batch_size=3))
    assert [p for p, _ in out] == pairs
    assert isinstance(out[1][1], LocalScaleError) and not isinstance(out[0][1], Exception)
