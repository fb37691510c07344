"""The pose evaluation's geometric bound (:mod:`localscale.evaluation.pose`, method ``points:SIGMA``):
the true projections of the shared 3D points, into a close-up cut from B and turned."""

import math
from pathlib import Path

import numpy as np
import pytest

from localscale.core.errors import LocalScaleError
from localscale.evaluation import pose, pose_data
from localscale.geometry.cameras import Camera, window_camera
from localscale.geometry.two_view import TwoViewConfig, estimate_two_view_geometry, relative_pose_error


def _rot_y(deg):
    a = math.radians(deg)
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(3)
    X = np.c_[rng.uniform(-2, 2, 400), rng.uniform(-1.5, 1.5, 400), rng.uniform(6, 10, 400)]
    cam = Camera.parse("PINHOLE 640 480 500 500 320 240")
    R_b = _rot_y(-12)
    t_b = -R_b @ np.array([1.5, 0.0, 0.0])
    ids = set(range(len(X)))
    views = {
        "a": pose_data.View("a", Path("a.jpg"), cam, np.eye(3), np.zeros(3), ids),
        "b": pose_data.View("b", Path("b.jpg"), cam, R_b, t_b, ids),
    }
    return pose_data.Collection("synthetic", views, dict(enumerate(X)))


def test_shared_points_land_in_the_turned_close_up(scene):
    col = scene
    a, b = col.views["a"], col.views["b"]
    window, turns = (200, 150, 213, 160), 1
    cam_w, R_turn = window_camera(b.camera, window, (640, 480), turns)
    pa, pb = pose_data.shared_points_in_view(col, a, b, cam_w, R_turn)
    all_a = pose_data.covisible_projections(col, a, b)[2]
    assert 10 < len(pa) < len(all_a) / 2  # only the points the window shows
    assert ((pb >= 0) & (pb < [cam_w.width, cam_w.height])).all()
    # the same points, seen in B, fall inside the window
    in_b = np.array([col.points[i] for i in sorted(a.point_ids)]) @ b.R.T + b.t
    in_window = b.camera.project(in_b)
    x0, y0, w, h = window
    inside = (in_window[:, 0] >= x0) & (in_window[:, 0] < x0 + w) & (in_window[:, 1] >= y0) & (in_window[:, 1] < y0 + h)
    assert abs(inside.sum() - len(pa)) <= 2  # pixel-edge rounding of the window's camera
    # without noise the pose protocol recovers the true relative pose of A and the close-up
    oracle = pose.make_method("points:0", 1024, {})
    oracle.tell_points(pa, pb, "pair")
    img_a, img_w = np.zeros((480, 640, 3), np.uint8), np.zeros((480, 640, 3), np.uint8)
    qa, qb = oracle.match("a", img_a, "b", img_w)
    np.testing.assert_allclose(qa, pa)
    R, t = pose_data.relative_pose(a, b)
    R, t = R_turn @ R, R_turn @ t
    g = estimate_two_view_geometry(qa, qb, a.camera, cam_w, TwoViewConfig())
    assert max(relative_pose_error(g.R_E, g.t_E, R, t)) < 1.0


def test_noise_is_seeded_per_pair_and_scaled():
    oracle = pose.make_method("points:0.5", 1024, {})
    pa = np.tile([[100.0, 100.0]], (2000, 1))
    oracle.tell_points(pa, pa.copy(), "pair")
    small = np.zeros((480, 640, 3), np.uint8)
    qa, _ = oracle.match("a", small, "b", small)
    qa2, _ = oracle.match("a", small, "b", small)
    np.testing.assert_array_equal(qa, qa2)  # the same pair, the same noise
    assert 0.45 < (qa - pa).std() < 0.55  # an image within max_side: sigma in its pixels
    big = np.zeros((2048, 1536, 3), np.uint8)  # twice max_side: the matcher's pixel is two of the image's
    qb, _ = oracle.match("a", big, "b", big)
    assert 0.9 < (qb - pa).std() < 1.1


def test_bad_oracle_spec_is_refused():
    with pytest.raises(LocalScaleError, match="points:SIGMA"):
        pose.make_method("points:abc", 1024, {})
    with pytest.raises(LocalScaleError, match="noise >= 0"):
        pose.make_method("points:-1", 1024, {})
