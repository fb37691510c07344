"""Geometric verification, refined scale maps, the second matching pass, homography accuracy."""

import json
from pathlib import Path

import numpy as np
import pytest

from localscale.cli import main
from localscale.geometry import covisible_mask, homography_scale_at, homography_scale_map, project
from localscale.io import load_image, read_homography
from localscale.matching.metrics import corner_error, homography_auc
from localscale.matching.pipeline import match_pair, match_refined_pair
from localscale.matching.refinement import refine_scale_map
from localscale.matching.verification import VerificationConfig, local_affine_scales, verify_matches

ASSETS = Path(__file__).resolve().parents[1] / "localscale" / "assets"


@pytest.fixture(scope="module")
def example():
    a, b = load_image(ASSETS / "kodim01_a.jpg"), load_image(ASSETS / "kodim01_b.jpg")
    return a, b, read_homography(ASSETS / "H_a_b.txt")


def _points(H, shape, n, rng):
    pa = rng.uniform([0, 0], [shape[1] - 1, shape[0] - 1], (n, 2))
    return pa, project(H, pa)


def test_exact_homography_gives_the_analytic_map_over_its_support(example, rng):
    a, b, H = example
    pa, pb = _points(H, a.shape[:2], 200, rng)
    net = np.full(a.shape[:2], 1.3, np.float32)
    v = verify_matches(pa, pb, a.shape, b.shape, net)
    assert v.verified and v.model == "homography" and v.num_inliers >= 195, v.reasons
    ref = refine_scale_map(net, v)
    gt = homography_scale_map(H, *a.shape[:2])
    sup = ref.source > 0.999
    assert sup.mean() > 0.3
    assert np.nanmax(np.abs(np.log2(ref.scale[sup] / gt[sup]))) < 1e-3
    far = ref.source < 1e-3  # far from the support: the network map
    assert np.allclose(ref.scale[far], 1.3, rtol=1e-3)
    assert ref.verified and ref.H is not None and ref.inliers.sum() == v.num_inliers


def test_refined_map_of_the_example_pair_matches_the_ground_truth(example):
    a, b, H = example
    res = match_pair(a, b, "none", H, descriptor="sift", num_features=500, refine=True)
    assert res.verification.verified and res.refined_a.verified
    gt = homography_scale_map(H, *a.shape[:2])
    sup = (res.refined_a.source > 0.999) & np.isfinite(gt)
    assert sup.mean() > 0.3
    err = np.abs(np.log2(res.refined_a.scale[sup] / gt[sup]))
    assert np.median(err) < 0.02 and err.max() < 0.1
    assert corner_error(res.verification.H, H, a.shape) < 5.0


def test_no_valid_matches_keeps_the_network_map(rng):
    a = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)
    b = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)
    net_a = np.exp2(rng.normal(0, 0.3, a.shape[:2])).astype(np.float32)
    net_b = np.exp2(rng.normal(0, 0.3, b.shape[:2])).astype(np.float32)
    res = match_refined_pair(a, b, net_a, net_b, descriptor="sift", num_features=300)
    assert not res.verification.verified and res.verification.reasons
    assert res.meta["passes"] == 1
    for ref, net in ((res.refined_a, net_a), (res.refined_b, net_b)):
        assert not ref.verified
        assert (ref.source == 0).all()
        np.testing.assert_array_equal(ref.scale, net)


def test_random_correspondences_are_not_verified(rng):
    pa = rng.uniform(0, 300, (300, 2))
    pb = rng.uniform(0, 300, (300, 2))
    for model in ("homography", "fundamental", "auto"):
        v = verify_matches(pa, pb, (300, 300), (300, 300), None, VerificationConfig(model=model))
        assert not v.verified and v.reasons
    assert not verify_matches(pa[:3], pb[:3], (300, 300), (300, 300)).verified


def test_disagreement_with_the_network_is_a_reason(example, rng):
    a, b, H = example
    pa, pb = _points(H, a.shape[:2], 100, rng)
    v = verify_matches(pa, pb, a.shape, b.shape, np.full(a.shape[:2], 16.0))
    assert not v.verified and any("disagree" in r for r in v.reasons)


def test_second_pass_never_lowers_the_inlier_count(example):
    a, b, H = example
    for desc in ("sift", "hardnet"):
        one = match_pair(a, b, "none", H, descriptor=desc, refine=True, max_passes=1)
        more = match_pair(a, b, "none", H, descriptor=desc, refine=True, max_passes=3)
        counts = more.meta["inlier_counts"]
        assert counts[0] == one.verification.num_inliers
        assert more.verification.num_inliers == max(counts) >= counts[0]
        assert more.accuracy(5.0) >= 0.8
        assert len(more.radii_a) == len(more.keypoints_a)


def test_fundamental_path_with_local_affine_scales(rng):
    # two fronto-parallel planes at different depths, camera moves sideways and forward: no single
    # homography, one fundamental matrix; each plane's scale is that of its own homography
    K = np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
    c, s = np.cos(0.05), np.sin(0.05)
    R, t = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]), np.array([0.4, 0.2, -1.0])
    pa, pb, truth = [], [], []
    for z, x0 in ((4.0, 0), (9.0, 160)):  # left half of A on the near plane, right half on the far one
        Hz = K @ (R + np.outer(t, [0, 0, 1]) / z) @ np.linalg.inv(K)
        uv = rng.uniform([x0, 0], [x0 + 160, 240], (150, 2))
        pa.append(uv), pb.append(project(Hz, uv)), truth.append(homography_scale_at(Hz, uv))
    pa, pb, truth = np.concatenate(pa), np.concatenate(pb), np.concatenate(truth)
    assert abs(np.log2(truth[:150].mean() / truth[150:].mean())) > 0.15
    cfg = VerificationConfig(model="fundamental")
    v = verify_matches(pa, pb, (240, 320), (240, 320), None, cfg)
    assert v.model == "fundamental" and v.F is not None and v.verified, v.reasons
    good = v.inliers
    assert np.median(np.abs(np.log2(v.local_scales[good] / truth[good]))) < 0.02
    ref = refine_scale_map(np.full((240, 320), 2.0, np.float32), v, config=cfg)
    assert ref.verified and ref.source.max() == pytest.approx(1.0)
    at = np.clip(np.round(pa[good]).astype(int), 0, [319, 239])
    assert np.median(np.abs(np.log2(ref.scale[at[:, 1], at[:, 0]] / truth[good]))) < 0.1
    # 'auto' tries the homography first and falls back to F
    assert verify_matches(pa, pb, (240, 320), (240, 320), None, VerificationConfig(model="auto")).model == "fundamental"


def test_local_affine_scales_of_an_affine_map(rng):
    A = np.array([[1.5, 0.2], [-0.1, 1.2]])
    pa = rng.uniform(0, 100, (40, 2))
    s, ok = local_affine_scales(pa, pa @ A.T + 5, neighbours=6, threshold=0.1)
    assert ok.all() and np.allclose(s, np.sqrt(abs(np.linalg.det(A))))


def test_corner_error_and_auc():
    H = np.array([[1.2, 0.1, 5], [0.0, 0.9, -3], [1e-4, 0, 1]])
    assert corner_error(H, H, (100, 200)) == pytest.approx(0.0, abs=1e-9)
    shift = np.array([[1, 0, 3.0], [0, 1, 4.0], [0, 0, 1]])
    assert corner_error(shift, np.eye(3), (100, 200)) == pytest.approx(5.0)
    assert corner_error(None, np.eye(3), (100, 200)) == np.inf
    assert homography_auc([0.0, 0.0], (5.0,)) == [pytest.approx(1.0)]
    assert homography_auc([np.inf, np.inf], (5.0,)) == [0.0]
    # one perfect pair and one failure: half the area; one pair at 2.5 px: the recall rises linearly
    # from 0 to 1 over [0, 2.5] px, so AUC@t = (t - 1.25) / t
    assert homography_auc([0.0, np.inf], (5.0,))[0] == pytest.approx(0.5)
    assert homography_auc([2.5], (5.0, 10.0)) == [pytest.approx(0.75), pytest.approx(0.875)]


def test_cli_match_and_predict_refine(tmp_path, capsys):
    a, b, h = ASSETS / "kodim01_a.jpg", ASSETS / "kodim01_b.jpg", ASSETS / "H_a_b.txt"
    assert (
        main(
            [
                "match",
                str(a),
                str(b),
                "-o",
                str(tmp_path / "m"),
                "--correction",
                "none",
                "--descriptor",
                "sift",
                "--num-features",
                "400",
                "--H",
                str(h),
                "--refine",
            ]
        )
        == 0
    )
    for f in ("matches.npz", "refined_scale.npy", "refined_source.npy", "refined_scale_b.npy", "geometry.json"):
        assert (tmp_path / "m" / f).is_file(), f
    geo = json.loads((tmp_path / "m" / "geometry.json").read_text())
    assert geo["verified"] and geo["model"] == "homography" and len(geo["H"]) == 3
    assert np.load(tmp_path / "m" / "refined_scale.npy").shape == (427, 640)
    assert "refine:" in capsys.readouterr().out
    assert main(["predict", str(a), str(b), "-o", str(tmp_path / "p"), "--refine", "--matcher", "hardnet"]) == 0
    assert (tmp_path / "p" / "kodim01_a_kodim01_b_refined_scale.npy").is_file()
    assert json.loads((tmp_path / "p" / "kodim01_a_kodim01_b_geometry.json").read_text())["verified"]
    capsys.readouterr()
    assert main(["predict", "--pairs", str(tmp_path / "x.txt"), "--refine", "-o", str(tmp_path / "q")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and "--refine" in err[0]


def test_cli_predict_search_refine_seeds_the_refinement_with_both_searched_maps(tmp_path, capsys):
    a, b, h = ASSETS / "kodim01_a.jpg", ASSETS / "kodim01_b.jpg", ASSETS / "H_a_b.txt"
    assert main(["predict", str(a), str(b), "-o", str(tmp_path), "--search", "--refine"]) == 0
    err = capsys.readouterr().err
    assert "window pairs scored; kept" in err
    assert json.loads((tmp_path / "kodim01_a_kodim01_b_geometry.json").read_text())["verified"]
    refined = np.load(tmp_path / "kodim01_a_kodim01_b_refined_scale.npy")
    truth = homography_scale_map(read_homography(h), *refined.shape)
    inside = covisible_mask(read_homography(h), refined.shape, load_image(b).shape[:2])
    assert np.exp(np.abs(np.log(refined / truth))[inside]).mean() < 1.05


def test_seed_geometry_refines_when_the_first_pass_fails(example, rng):
    import torch

    from localscale.matching.refinement import describe_and_match, refine_passes

    a, b, H = example
    kp = rng.uniform([0, 0], [639, 426], (300, 2))
    calls = []

    def describe(scale_map):  # descriptors that match nothing consistently
        calls.append(scale_map)
        return kp, torch.nn.functional.normalize(torch.randn(300, 16), dim=1)

    pa, pb = _points(H, a.shape[:2], 100, rng)
    net = np.ones(a.shape[:2], np.float32)
    out = refine_passes(
        describe_and_match(describe, describe), a.shape[:2], b.shape[:2], None, None, net, net, seed=lambda: (pa, pb)
    )
    assert out.seed is not None and out.seed.verified and out.refined_a.verified
    assert out.passes == 2 and calls[2] is out.refined_a.scale  # second pass cut with the refined maps
    gt = homography_scale_map(H, *a.shape[:2])
    sup = out.refined_a.source > 0.999
    assert np.nanmax(np.abs(np.log2(out.refined_a.scale[sup] / gt[sup]))) < 1e-3
    no = refine_passes(describe_and_match(describe, describe), a.shape[:2], b.shape[:2], None, None, net, net)
    assert no.passes == 1 and not no.refined_a.verified and (no.refined_a.source == 0).all()
