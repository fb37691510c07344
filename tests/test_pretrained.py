"""The bundled default models: they load, follow the convention and beat the constant baselines
on held-out pairs (scikit-image photos, never used for training)."""
import math

import numpy as np
import pytest

from localscale import LocalScaleNet, ScaleNet
from localscale.geometry import HomographyConfig, covisible_mask, global_scale, homography_scale_map, sample_homography, warp_image


@pytest.fixture(scope="module")
def local():
    return LocalScaleNet.from_pretrained()


def held_out_pairs(photos, n, seed, perspective):
    rng = np.random.default_rng(seed)
    names = list(photos)
    for k in range(n):
        i, j = rng.choice(len(names), 2, replace=False)
        a = photos[names[i]]
        H = sample_homography(rng, a.shape[:2], a.shape[:2], HomographyConfig(scale_range=(0.25, 4.0), perspective=perspective))
        b, _ = warp_image(a, H, a.shape[:2], fill=photos[names[j]])
        yield a, b, H


def test_default_local_model_beats_constant_map(local, photos):
    errs, base = [], []
    for a, b, H in held_out_pairs(photos, 12, 0, 0.45):
        pred = local.predict(a, b).scale[::8, ::8]
        gt = homography_scale_map(H, *a.shape[:2], stride=8)
        m = covisible_mask(H, a.shape[:2], b.shape[:2], 8) & np.isfinite(gt)
        errs.append(np.abs(np.log(pred[m]) - np.log(gt[m])))
        base.append(np.abs(np.log(gt[m])))
    r_model = np.exp(np.concatenate(errs)).mean()
    r_const = np.exp(np.concatenate(base)).mean()
    assert r_model < 0.8 * r_const, (r_model, r_const)


def test_default_local_model_follows_the_convention_on_pure_zooms(local, photos):
    """Zoom-outs give S < 1, zoom-ins S > 1, and the predicted scale grows with the zoom."""
    h, w = photos["astronaut"].shape[:2]
    c = np.array([[1, 0, -(w - 1) / 2], [0, 1, -(h - 1) / 2], [0, 0, 1]])
    meds, errs = [], []
    for zoom in (0.35, 0.6, 1.7, 2.8):
        H = np.linalg.inv(c) @ np.diag([zoom, zoom, 1]) @ c
        b, _ = warp_image(photos["astronaut"], H, (h, w), fill=photos["coffee"])
        s = local.predict(photos["astronaut"], b).scale
        med = float(np.median(s[covisible_mask(H, (h, w), (h, w))]))
        assert (med > 1) == (zoom > 1), (zoom, med)
        meds.append(med)
        errs.append(abs(math.log(med / zoom)))
    assert meds == sorted(meds)
    assert math.exp(np.mean(errs)) < 1.6, meds


def test_default_global_model(photos):
    model = ScaleNet.from_pretrained()
    errs, base = [], []
    for a, b, H in held_out_pairs(photos, 10, 1, 0.2):
        g = global_scale(H, a.shape[:2], b.shape[:2])
        errs.append(abs(math.log(model.predict(a, b).scale / g)))
        base.append(abs(math.log(g)))
    assert np.exp(errs).mean() < 0.8 * np.exp(base).mean()
