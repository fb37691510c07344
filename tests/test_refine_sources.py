"""Refined maps of 3D scenes: the dense map of the verified matches, and the source layer."""

import numpy as np

from localscale.geometry import homography_scale_map, project
from localscale.maps.files import write_refinement
from localscale.matching.refinement import (
    SOURCE_HOMOGRAPHY,
    SOURCE_MATCHES,
    SOURCE_NETWORK,
    matches_scale_map,
    refine_scale_map,
)
from localscale.matching.verification import VerificationConfig, verify_matches

SHAPE = (480, 640)
K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
#: camera B: moved 1.5 forward and 0.3 sideways (X_B = X_A + T, no rotation)
T = np.array([-0.3, 0.1, -1.5])
#: two fronto-parallel planes in front of A: depth 3 left of the image centre, depth 8 right of it
DEPTHS = (3.0, 8.0)


def _plane_homography(depth: float) -> np.ndarray:
    """``K (I + T n^T / d) K^-1``: A -> B for the plane ``z = d``."""
    return K @ (np.eye(3) + np.outer(T, [0, 0, 1.0]) / depth) @ np.linalg.inv(K)


def two_plane_scene(rng, n=600, box=(0, 0, SHAPE[1], SHAPE[0])):
    """Matches of the two-plane scene inside ``box`` of A, and the true map over A."""
    x0, y0, x1, y1 = box
    pa = rng.uniform([x0, y0], [x1 - 1, y1 - 1], (n, 2))
    left = pa[:, 0] < SHAPE[1] / 2
    pb = np.where(left[:, None], project(_plane_homography(DEPTHS[0]), pa), project(_plane_homography(DEPTHS[1]), pa))
    truth = homography_scale_map(_plane_homography(DEPTHS[1]), *SHAPE)
    truth[:, : SHAPE[1] // 2] = homography_scale_map(_plane_homography(DEPTHS[0]), *SHAPE)[:, : SHAPE[1] // 2]
    return pa, pb, truth


def test_match_based_map_equals_the_analytic_map_of_a_homography(rng):
    H = np.array([[1.6, 0.15, -90], [-0.1, 1.5, -60], [4e-4, 2e-4, 1.0]])
    pa = rng.uniform([0, 0], [SHAPE[1] - 1, SHAPE[0] - 1], (500, 2))
    scale, dist = matches_scale_map(pa, project(H, pa), SHAPE)
    gt = homography_scale_map(H, *SHAPE)
    near = dist < 30
    assert near.mean() > 0.75
    err = np.abs(np.log2(scale[near] / gt[near]))
    assert np.median(err) < 0.01 and np.percentile(err, 99) < 0.05, (np.median(err), np.percentile(err, 99))


def test_match_based_map_beats_one_homography_on_a_two_plane_scene(rng):
    import cv2

    pa, pb, truth = two_plane_scene(rng)
    v = verify_matches(pa, pb, SHAPE, SHAPE, None, VerificationConfig(model="fundamental"))
    assert v.verified and v.model == "fundamental", v.reasons
    ref = refine_scale_map(None, v)
    H, _ = cv2.findHomography(pa, pb, cv2.RANSAC, 3.0)
    single = homography_scale_map(H, *SHAPE)
    ok = ref.source_layer == SOURCE_MATCHES
    assert ok.mean() > 0.8
    err_matches = np.exp(np.abs(np.log(ref.scale[ok] / truth[ok]))).mean()
    err_single = np.exp(np.abs(np.log(single[ok] / truth[ok]))).mean()
    assert err_matches < 1.05 and err_single > 1.15, (err_matches, err_single)


def test_pixels_far_from_the_matches_keep_the_network_shape_at_the_verified_level(rng):
    """Away from the matches of a 3D scene the network's map keeps its shape (a slope here) but
    takes the level of the verified geometry: a network off by a constant factor is corrected."""
    pa, pb, truth = two_plane_scene(rng, 300, box=(40, 40, 300, 220))
    net = np.tile(np.linspace(0.5, 0.8, SHAPE[1], dtype=np.float32), (SHAPE[0], 1))
    v = verify_matches(pa, pb, SHAPE, SHAPE, None, VerificationConfig(model="fundamental"))
    assert v.verified, v.reasons
    ref = refine_scale_map(net, v)
    far = ref.source_layer == SOURCE_NETWORK
    assert far[-60:, -60:].all()  # the corner opposite the matches
    xy = np.round(pa[v.inliers]).astype(int)
    level = np.median(np.log2(truth[xy[:, 1], xy[:, 0]] / net[xy[:, 1], xy[:, 0]]))
    assert level > 0.5  # the network is far off
    np.testing.assert_allclose(ref.scale[-60:, -60:], net[-60:, -60:] * 2**level, rtol=0.03)
    near = ref.source_layer == SOURCE_MATCHES
    assert near[60:200, 60:280].all()
    assert np.median(np.abs(np.log2(ref.scale[near] / truth[near]))) < 0.05


def test_homography_pixels_are_labelled_homography_and_the_layer_is_written(rng, tmp_path):
    H = _plane_homography(DEPTHS[0])
    pa = rng.uniform([0, 0], [SHAPE[1] - 1, SHAPE[0] - 1], (200, 2))
    v = verify_matches(pa, project(H, pa), SHAPE, SHAPE, None)
    ref = refine_scale_map(None, v)
    assert v.model == "homography" and (ref.source_layer == SOURCE_HOMOGRAPHY).mean() > 0.9
    paths = write_refinement(tmp_path, "x_", ref)
    names = {p.name for p in paths}
    assert {"x_refined_source.npy", "x_refined_source.png", "x_refined_weight.npy"} <= names
    layer = np.load(tmp_path / "x_refined_source.npy")
    assert layer.dtype == np.uint8 and np.array_equal(layer, ref.source_layer)
    np.testing.assert_array_equal(np.load(tmp_path / "x_refined_weight.npy"), ref.source)
