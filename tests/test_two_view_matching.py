"""Two-view geometry inside matching: verification by COLMAP's model choice, the relative pose of
``match_pair`` with cameras, ``auto``'s hypothesis from a fundamental matrix, the CLI's cameras."""

import json
import math

import numpy as np
import pytest

from localscale.cli import main
from localscale.geometry.cameras import Camera
from localscale.matching import VerificationConfig, match_pair, verify_matches
from localscale.matching.auto import geometry_hypothesis
from localscale.sfm.synthetic import arc_cameras, random_texture, render_view

CAM = Camera.parse("PINHOLE 640 480 500 500 320 240")


def _rotation_y(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _angle(R1, R2) -> float:
    return math.degrees(math.acos(np.clip((np.trace(R1.T @ R2) - 1) / 2, -1, 1)))


def _observe(X, R, t, rng, noise=0.3):
    K = CAM.K()
    xa = X @ K.T
    xb = (X @ R.T + t) @ K.T
    pa = xa[:, :2] / xa[:, 2:] + rng.normal(0, noise, (len(X), 2))
    pb = xb[:, :2] / xb[:, 2:] + rng.normal(0, noise, (len(X), 2))
    return pa, pb


def _scene(kind, rng, n=300):
    xy = rng.uniform(-2, 2, (n, 2))
    z = 6 + (rng.uniform(-1.5, 1.5, n) if kind == "3d" else 0.0)
    return np.c_[xy, np.full(n, 6.0) if kind == "plane" else z]


@pytest.mark.parametrize("kind, model", [("3d", "essential"), ("plane", "homography")])
def test_two_view_verification_chooses_the_model_and_gives_the_pose(kind, model):
    rng = np.random.default_rng(0)
    R, t = _rotation_y(8), np.array([1.0, 0.1, 0.2])
    pa, pb = _observe(_scene(kind, rng), R, t, rng)
    v = verify_matches(pa, pb, (480, 640), (480, 640), None, VerificationConfig(model="two_view"), CAM, CAM)
    assert v.verified and v.model == model and v.two_view is not None
    assert _angle(v.two_view.R, R) < 1.0
    assert math.degrees(math.acos(np.clip(v.two_view.t @ (t / np.linalg.norm(t)), -1, 1))) < 3.0
    d = v.to_dict()
    assert json.loads(json.dumps(d))["two_view"]["configuration"] == v.two_view.configuration
    back = v.swapped()  # seen from B: x_A = R^T x_B - R^T t
    assert np.allclose(back.two_view.R, v.two_view.R.T) and np.allclose(back.two_view.t, -v.two_view.R.T @ v.two_view.t)


def test_homography_verification_of_a_3d_scene_keeps_fewer_inliers_than_two_view():
    rng = np.random.default_rng(1)
    pa, pb = _observe(_scene("3d", rng), _rotation_y(10), np.array([1.0, 0.0, 0.3]), rng)
    h = verify_matches(pa, pb, (480, 640), (480, 640), None, VerificationConfig())
    g = verify_matches(pa, pb, (480, 640), (480, 640), None, VerificationConfig(model="two_view"))
    assert g.model == "fundamental" and g.two_view.configuration == "UNCALIBRATED"
    assert g.num_inliers > h.num_inliers + 50


@pytest.mark.parametrize("turn", [1, 2, 3])
def test_geometry_hypothesis_of_a_fundamental_matrix_finds_the_quarter_turn(turn):
    rng = np.random.default_rng(2)
    pa, pb = _observe(_scene("3d", rng), _rotation_y(6), np.array([0.8, 0.1, 0.1]), rng)
    # B turned by `turn` quarter turns (counter-clockwise, as np.rot90), then shrunk by 2
    h, w = 480, 640
    for _ in range(turn):
        pb = np.c_[pb[:, 1], (w - 1) - pb[:, 0]]
        h, w = w, h
    pb = pb * 0.5
    shape_b = (round(h * 0.5), round(w * 0.5))
    v = verify_matches(pa, pb, (480, 640), shape_b, None, VerificationConfig(model="two_view", coverage_of="either"))
    assert v.verified and v.model == "fundamental"
    hyp = geometry_hypothesis(v)
    assert hyp is not None and (hyp.turn + turn) % 4 == 0
    assert 0.35 < hyp.scale < 0.7


@pytest.fixture(scope="module")
def two_views(tmp_path_factory):
    rng = np.random.default_rng(0)
    textures = [random_texture(rng), random_texture(rng)]
    cams = arc_cameras(3, shape=(360, 480), focal=420.0, spread_deg=30.0)
    folder = tmp_path_factory.mktemp("views")
    import cv2

    paths = []
    for i in (0, 2):
        p = folder / f"v{i}.png"
        cv2.imwrite(str(p), cv2.cvtColor(render_view(cams[i], textures), cv2.COLOR_RGB2BGR))
        paths.append(p)
    ca, cb = cams[0], cams[2]
    R = cb.R @ ca.R.T
    t = cb.t - R @ ca.t
    camera = f"PINHOLE 480 360 420 420 {(480 - 1) / 2 + 0.5} {(360 - 1) / 2 + 0.5}"
    return paths, camera, R, t / np.linalg.norm(t)


def test_match_pair_with_cameras_returns_the_relative_pose(two_views):
    (a, b), camera, R, t = two_views
    res = match_pair(a, b, "none", matcher="sift", camera_a=camera, camera_b=camera)
    assert res.relative_pose is not None and res.verification.verified
    R_est, t_est = res.relative_pose
    assert _angle(R_est, R) < 2.0
    assert math.degrees(math.acos(np.clip(t_est @ t, -1, 1))) < 5.0
    plain = match_pair(a, b, "none", matcher="sift")
    assert plain.verification is None and plain.relative_pose is None


def test_cli_match_with_a_camera_writes_the_pose(two_views, tmp_path, capsys):
    (a, b), camera, R, _ = two_views
    out = tmp_path / "out"
    assert (
        main(["match", str(a), str(b), "-o", str(out), "--matcher", "sift", "--correction", "none", "--camera", camera])
        == 0
    )
    geo = json.loads((out / "geometry.json").read_text())
    assert geo["two_view"]["configuration"] in ("CALIBRATED", "UNCALIBRATED")
    assert _angle(np.array(geo["two_view"]["R"]), R) < 2.0
    assert "two-view geometry:" in capsys.readouterr().out
    for bad_args in (
        ["--camera", camera, "--camera-a", camera],  # both kinds at once
        ["--camera", str(tmp_path / "missing.txt")],  # no such camera file
        ["--camera", "PINHOLE 100 100 80 80 50 50"],
    ):  # not the images' shape
        bad = tmp_path / "bad"
        assert (
            main(["match", str(a), str(b), "-o", str(bad), "--matcher", "sift", "--correction", "none", *bad_args]) == 2
        )
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error:"), err
        assert not bad.exists()
