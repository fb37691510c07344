import numpy as np

from localscale.geometry import homography_scale_map
from localscale.geometry.planar import planarize


def test_planar_fit_recovers_a_homography_scale_field_from_noisy_samples(rng):
    H = np.array([[1.3, 0.1, 5], [-0.05, 1.2, 3], [0.0011, -0.0006, 1.0]])
    gt = homography_scale_map(H, 240, 320).astype(np.float32)
    noisy = gt * np.exp(rng.normal(0, 0.25, gt.shape)).astype(np.float32)
    outliers = rng.random(gt.shape) < 0.1
    noisy[outliers] *= 6  # 10% gross errors
    fit = planarize(noisy, np.ones_like(gt), stride=4)
    err_raw = np.abs(np.log(noisy / gt)).mean()
    err_fit = np.abs(np.log(fit / gt)).mean()
    assert err_fit < 0.03 and err_fit < 0.1 * err_raw


def test_planar_fit_of_a_constant_map_is_constant():
    fit = planarize(np.full((50, 80), 2.5, np.float32), np.ones((50, 80)))
    assert np.allclose(fit, 2.5, rtol=1e-4)
