"""The bundled default models: they load, follow the convention and beat the constant baselines
on held-out pairs (scikit-image photos, never used for training)."""

import math

import numpy as np
import pytest

from localscale import LocalScaleNet, ScaleNet
from localscale.geometry import (
    HomographyConfig,
    covisible_mask,
    global_scale,
    homography_scale_map,
    sample_homography,
    warp_image,
)


@pytest.fixture(scope="module")
def local():
    return LocalScaleNet.from_pretrained()


def held_out_pairs(photos, n, seed, perspective):
    rng = np.random.default_rng(seed)
    names = list(photos)
    for _k in range(n):
        i, j = rng.choice(len(names), 2, replace=False)
        a = photos[names[i]]
        H = sample_homography(
            rng, a.shape[:2], a.shape[:2], HomographyConfig(scale_range=(0.25, 4.0), perspective=perspective)
        )
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


def _gray3(img):
    import cv2

    return np.repeat(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)[..., None], 3, 2)


@pytest.mark.parametrize("name", ["astronaut", "coffee", "chelsea", "rocket"])
def test_an_image_paired_with_itself_has_scale_one(local, photos, name):
    assert abs(float(np.median(local.predict(photos[name], photos[name]).scale)) - 1) < 0.03


@pytest.mark.parametrize("name", ["astronaut", "coffee", "rocket"])
def test_a_gray_copy_against_its_colour_original_has_scale_one(local, photos, name):
    assert abs(float(np.median(local.predict(_gray3(photos[name]), photos[name]).scale)) - 1) < 0.05


def test_swapping_a_and_b_inverts_the_global_scale_of_the_default_model(photos):
    model = ScaleNet.from_pretrained()
    for a, b, _ in held_out_pairs(photos, 3, 2, 0.2):
        assert model.predict(a, b).scale * model.predict(b, a).scale == pytest.approx(1, rel=1e-3)


def test_forward_and_backward_maps_agree_through_the_homography(local, photos):
    """S_{A->B}(x) * S_{B->A}(H x) = 1: the median log-ratio over co-visible pixels is small."""
    from localscale.geometry import project

    ratios = []
    for a, b, H in held_out_pairs(photos, 6, 3, 0.3):
        fwd, bwd = local.predict(a, b).scale, local.predict(b, a).scale
        ys, xs = np.mgrid[0 : a.shape[0] : 8, 0 : a.shape[1] : 8]
        q = np.round(project(H, np.stack([xs, ys], -1).astype(float))).astype(int)
        m = covisible_mask(H, a.shape[:2], b.shape[:2], 8)[: ys.shape[0], : ys.shape[1]]
        m &= (q[..., 0] >= 0) & (q[..., 0] < b.shape[1]) & (q[..., 1] >= 0) & (q[..., 1] < b.shape[0])
        if m.sum() > 20:
            ratios.append(np.median(np.log2(fwd[ys[m], xs[m]] * bwd[q[m][:, 1], q[m][:, 0]])))
    assert len(ratios) >= 3 and abs(float(np.median(ratios))) < 0.35, ratios


def test_default_model_sees_what_is_visible(local, photos):
    """The visibility output covers a pair's overlap and is low against an unrelated image."""
    ious, frac_err = [], []
    for a, b, H in held_out_pairs(photos, 8, 4, 0.2):
        v = local.predict(a, b).visible > 0.5
        cov = covisible_mask(H, a.shape[:2], b.shape[:2])
        frac_err.append(abs(v.mean() - cov.mean()))
        if cov.mean() > 0.3:
            ious.append((v & cov).sum() / max(1, (v | cov).sum()))
    assert len(ious) >= 3 and min(ious) > 0.6, ious
    assert np.mean(frac_err) < 0.15, frac_err
    noise = np.random.default_rng(0).integers(0, 256, photos["coffee"].shape, dtype=np.uint8)
    assert float(local.predict(photos["astronaut"], noise).visible.mean()) < 0.3


def test_pair_check_flags_unrelated_images_and_passes_an_easy_pair(local, photos):
    from localscale.reliability import check_pair

    a, b, _ = next(held_out_pairs(photos, 1, 5, 0.1))
    assert check_pair(local, a, a).reliable
    black = np.zeros_like(photos["coffee"])
    assert not check_pair(local, photos["astronaut"], black).reliable
