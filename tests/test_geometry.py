import numpy as np
import pytest

from localscale import geometry as G


def zoom(s, cx=0.0, cy=0.0):
    return np.array([[s, 0, cx], [0, s, cy], [0, 0, 1.0]])


def test_pure_zoom_gives_constant_map():
    for s in (0.2, 1.0, 3.7):
        m = G.homography_scale_map(zoom(s, 5, -3), 40, 60)
        assert m.shape == (40, 60)
        assert np.allclose(m, s)


def test_analytic_map_matches_finite_differences(rng):
    H = G.sample_homography(rng, (120, 160), (120, 160), G.HomographyConfig(perspective=0.45))
    pts = G.grid_points(120, 160, 16).reshape(-1, 2)
    eps = 1e-3
    jx = (G.project(H, pts + [eps, 0]) - G.project(H, pts - [eps, 0])) / (2 * eps)
    jy = (G.project(H, pts + [0, eps]) - G.project(H, pts - [0, eps])) / (2 * eps)
    det = jx[:, 0] * jy[:, 1] - jx[:, 1] * jy[:, 0]
    analytic = G.homography_scale_map(H, 120, 160, 16).reshape(-1)
    assert np.allclose(analytic, np.sqrt(np.abs(det)), rtol=1e-5)


def test_map_composed_with_inverse_is_one(rng):
    H = G.sample_homography(rng, (100, 100), (100, 100))
    pts = G.grid_points(100, 100, 10).reshape(-1, 2)
    s_ab = G.homography_scale_at(H, pts)
    s_ba = G.homography_scale_at(np.linalg.inv(H), G.project(H, pts))
    assert np.allclose(s_ab * s_ba, 1.0, rtol=1e-8)


def test_strided_map_samples_cell_centres():
    H = np.array([[1, 0, 0], [0, 1, 0], [0.002, 0.001, 1.0]])
    full = G.homography_scale_map(H, 64, 64)
    strided = G.homography_scale_map(H, 64, 64, stride=8)
    assert strided.shape == (8, 8)
    # cell (i, j) centre is pixel (8j + 3.5, 8i + 3.5): the mean of the 4 central pixels' scale is close
    c = full[3:5, 3:5].mean()
    assert strided[0, 0] == pytest.approx(c, rel=1e-3)


def test_perspective_makes_the_scale_vary_and_horizon_is_nan():
    H = np.array([[1, 0, 0], [0, 1, 0], [0.004, 0, 1.0]])
    m = G.homography_scale_map(H, 10, 100)
    assert m[0, 0] > 1.5 * m[0, -1]
    H2 = np.array([[1, 0, 0], [0, 1, 0], [-0.02, 0, 1.0]])  # w <= 0 for x >= 50
    assert np.isnan(G.homography_scale_map(H2, 4, 100)[0, 60])


def test_sampler_respects_ranges(rng):
    cfg = G.HomographyConfig(perspective=0.0, translation=0.0)
    centres = []
    for _ in range(300):
        H = G.sample_homography(rng, (100, 120), (100, 120), cfg)
        centres.append(G.homography_scale_at(H, np.array([59.5, 49.5])))
        assert G.project(H, np.array([59.5, 49.5])) == pytest.approx([59.5, 49.5])
    centres = np.array(centres)
    assert centres.min() >= 0.16 - 1e-9 and centres.max() <= 6 + 1e-9
    assert centres.min() < 0.3 and centres.max() > 3.5  # log-uniform covers the range


def test_covisible_mask_and_global_scale():
    H = zoom(2.0)
    m = G.covisible_mask(H, (50, 50), (50, 50))
    assert m[:25, :25].all() and not m[30:, 30:].any()
    assert G.global_scale(H, (50, 50), (50, 50)) == pytest.approx(2.0)
    with pytest.raises(ValueError):
        G.global_scale(zoom(1, 1000, 1000), (50, 50), (50, 50))


def test_warp_fills_empty_region_from_other_image():
    a = np.full((60, 80, 3), 200, np.uint8)
    fill = np.full((30, 30, 3), 17, np.uint8)
    warped, valid = G.warp_image(a, zoom(0.5), (60, 80), fill=fill)
    assert warped.dtype == np.uint8 and warped.shape == (60, 80, 3)
    assert (warped[5:25, 5:35] == 200).all()
    assert (warped[45:, 60:] == 17).all()  # not zeros: taken from the fill image
    assert valid[5:25, 5:35].min() == pytest.approx(1.0) and valid[45:, 60:].max() == 0


def test_negative_sign_homographies_are_oriented():
    """H and -H are the same homography (leuven H_1_5 and EVD files are stored with w < 0)."""
    H = np.array([[1.2, 0.1, 3], [0.0, 1.1, -2], [0.0005, 0.0002, 1.0]])
    for M in (H, -H):
        assert np.allclose(G.homography_scale_map(M, 40, 50), G.homography_scale_map(H, 40, 50))
        assert G.covisible_mask(M, (40, 50), (40, 50)).sum() == G.covisible_mask(H, (40, 50), (40, 50)).sum() > 0
    assert G.global_scale(-H, (40, 50), (40, 50)) == pytest.approx(G.global_scale(H, (40, 50), (40, 50)))


def test_warp_with_fill_of_another_channel_count():
    gray = np.full((40, 40), 100, np.uint8)
    rgb = np.full((20, 20, 3), 30, np.uint8)
    w1, _ = G.warp_image(gray, zoom(0.5), (40, 40), fill=rgb)
    w2, _ = G.warp_image(rgb, zoom(0.5), (40, 40), fill=gray)
    assert w1.shape == (40, 40) and w1[35, 35] == 30
    assert w2.shape == (40, 40, 3) and (w2[35, 35] == 100).all()
