"""Cameras (COLMAP models, windows, quarter turns) and two-view geometry chosen as COLMAP does.

Scenes are synthetic: random 3D points (one plane, two planes, a volume) seen by two known
cameras with noise and outliers, and two rendered views of a randomly textured plane matched
with OpenCV SIFT. No data files.
"""

import json
import math

import cv2
import numpy as np
import pytest

from localscale.core.errors import LocalScaleError
from localscale.geometry.cameras import (
    Camera,
    CameraError,
    as_camera,
    cut_window,
    read_camera,
    read_cameras_txt,
    turn_rotation,
    window_camera,
    window_pixels,
)
from localscale.geometry.two_view import (
    CONFIGURATIONS,
    TwoViewConfig,
    TwoViewError,
    epipolar_errors,
    estimate_two_view_geometry,
    pose_auc,
    relative_pose_error,
)

CAM_A = Camera.parse("PINHOLE 640 480 500 505 320 240")
CAM_B = Camera.parse("SIMPLE_RADIAL 800 600 650 400 300 0.02")


def rotation(axis, deg):
    axis = np.asarray(axis, np.float64)
    return cv2.Rodrigues(axis / np.linalg.norm(axis) * math.radians(deg))[0]


R_AB = rotation([0.3, 1.0, 0.1], 10.0)
T_AB = np.array([-1.0, 0.15, 0.25])  # x_B = R x_A + t


def make_points(kind, rng, n=400):
    """``n x 3`` points in A's frame: one tilted plane, two planes meeting at a ridge, or a volume."""
    if kind == "plane":
        X = np.c_[rng.uniform(-2.5, 2.5, n), rng.uniform(-2, 2, n), np.zeros(n)]
        return X @ rotation([1, 0.2, 0], 25).T + [0, 0, 6.0]
    if kind == "two_planes":
        x = rng.uniform(-2.5, 2.5, n)
        return np.c_[x, rng.uniform(-2, 2, n), 6.0 + 0.8 * np.abs(x)]
    return np.c_[rng.uniform(-2.5, 2.5, n), rng.uniform(-2, 2, n), rng.uniform(4.0, 9.0, n)]


def observe(X, R, t, rng, cam_a=CAM_A, cam_b=CAM_B, noise=0.3, outliers=0.2):
    """Pixels of ``X`` in A and B (``x_B = R x_A + t``) with Gaussian noise; a share of B's points
    replaced by uniform outliers. Points outside either image are dropped."""
    xa = cam_a.project(X)
    xb = cam_b.project(X @ R.T + t)
    keep = (
        ((xa >= 0) & (xa < [cam_a.width - 1, cam_a.height - 1])).all(1)
        & ((xb >= 0) & (xb < [cam_b.width - 1, cam_b.height - 1])).all(1)
        & ((X @ R.T + t)[:, 2] > 0)
    )
    xa, xb = xa[keep] + rng.normal(0, noise, (keep.sum(), 2)), xb[keep] + rng.normal(0, noise, (keep.sum(), 2))
    k = int(outliers * len(xa))
    xb[:k] = rng.uniform([0, 0], [cam_b.width, cam_b.height], (k, 2))
    return xa, xb


# ---------------------------------------------------------------------------- cameras
def test_camera_models_give_opencv_intrinsics_in_pixel_centre_convention():
    cam = Camera.parse("1 OPENCV 1024 683 2322.9 2324.0 512 341.5 0.045 0.01 0.001 -0.002")
    assert cam.model == "OPENCV" and (cam.width, cam.height) == (1024, 683)
    np.testing.assert_allclose(cam.K(), [[2322.9, 0, 511.5], [0, 2324.0, 341.0], [0, 0, 1]])
    np.testing.assert_allclose(cam.K_colmap()[:2, 2], [512, 341.5])
    np.testing.assert_allclose(cam.dist(), [0.045, 0.01, 0.001, -0.002])
    assert Camera.parse("SIMPLE_RADIAL 100 80 90 50 40 -0.1").dist().tolist() == [-0.1, 0, 0, 0]
    assert Camera.parse("RADIAL 100 80 90 50 40 -0.1 0.05").dist().tolist() == [-0.1, 0.05, 0, 0]
    assert Camera.parse("SIMPLE_PINHOLE 100 80 90 50 40").focal_lengths == (90.0, 90.0)
    full = Camera.parse("FULL_OPENCV 100 80 90 91 50 40 0.1 0.01 0 0 0.001 0 0 0")
    assert full.dist().shape == (8,)


def test_normalize_inverts_projection_with_distortion():
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-1, 1, 50), rng.uniform(-0.8, 0.8, 50), rng.uniform(2, 5, 50)]
    for cam in (CAM_B, Camera.parse("OPENCV 640 480 400 410 330 250 -0.05 0.01 0.002 -0.001")):
        xy = cam.normalize(cam.project(X))
        np.testing.assert_allclose(xy, X[:, :2] / X[:, 2:], atol=1e-6)
        und = cam.undistort_points(cam.project(X))
        K = cam.K()
        np.testing.assert_allclose(und, (X[:, :2] / X[:, 2:]) * [K[0, 0], K[1, 1]] + K[:2, 2], atol=1e-3)


def test_camera_files_and_bad_cameras(tmp_path):
    txt = tmp_path / "cam.txt"
    txt.write_text("# a camera\n7 SIMPLE_RADIAL 640 480 600 320 240 0.01\n")
    assert read_camera(txt).params.tolist() == [600, 320, 240, 0.01]
    js = tmp_path / "cam.json"
    js.write_text(json.dumps(CAM_B.to_dict()))
    assert read_camera(js) == CAM_B
    assert as_camera(str(js)) == CAM_B and as_camera(CAM_B.to_line()) == CAM_B
    many = tmp_path / "cameras.txt"
    many.write_text("1 PINHOLE 640 480 500 500 320 240\n2 SIMPLE_PINHOLE 320 240 250 160 120\n")
    assert sorted(read_cameras_txt(many)) == [1, 2]

    bad = {
        "missing": tmp_path / "nope.txt",
        "empty": tmp_path / "empty.txt",
        "json": tmp_path / "bad.json",
        "count": tmp_path / "count.txt",
        "model": tmp_path / "model.txt",
        "focal": tmp_path / "focal.txt",
    }
    bad["empty"].write_text("# nothing\n")
    bad["json"].write_text("{not json")
    bad["count"].write_text("PINHOLE 640 480 500 320 240\n")
    bad["model"].write_text("FISHEYE_X 640 480 500 320 240\n")
    bad["focal"].write_text("SIMPLE_PINHOLE 640 480 -5 320 240\n")
    for name, path in bad.items():
        with pytest.raises(CameraError) as e:
            read_camera(path)
        assert str(path) in str(e.value) and "\n" not in str(e.value), name
    assert issubclass(CameraError, LocalScaleError)
    with pytest.raises(CameraError):
        Camera.parse("PINHOLE 640 480 500 500 320 nan")
    with pytest.raises(CameraError):
        Camera.from_dict({"model": "PINHOLE", "width": 640})


def test_prior_and_exif_focal(tmp_path):
    from PIL import Image

    prior = Camera.from_prior(1024, 683)
    assert prior.focal_lengths == (1.2 * 1024, 1.2 * 1024) and prior.principal_point == (512, 341.5)
    assert not prior.has_prior_focal_length

    img = Image.fromarray(np.zeros((400, 600, 3), np.uint8))
    exif = Image.Exif()
    exif.get_ifd(0x8769)[0xA405] = 28  # FocalLengthIn35mmFilm
    path = tmp_path / "exif.jpg"
    img.save(path, exif=exif)
    cam = Camera.from_exif(path)
    assert cam.has_prior_focal_length and (cam.width, cam.height) == (600, 400)
    assert cam.focal_lengths[0] == pytest.approx(28 / 36 * 600, rel=1e-3)  # 3:2 frame: f35 / 36 mm * W
    plain = tmp_path / "plain.jpg"
    img.save(plain)
    assert Camera.from_exif(plain).focal_lengths[0] == pytest.approx(720)
    with pytest.raises(CameraError):
        Camera.from_exif(plain, fallback_prior=False)
    with pytest.raises(CameraError):
        Camera.from_exif(tmp_path / "missing.jpg")


@pytest.mark.parametrize("turns", [0, 1, 2, 3])
def test_window_camera_projects_like_the_cut_resized_turned_image(turns):
    rng = np.random.default_rng(turns)
    cam = Camera.parse("OPENCV 640 480 500 510 330 235 -0.04 0.01 0.003 -0.002")
    X = np.c_[rng.uniform(-0.5, 0.5, 100), rng.uniform(-0.4, 0.4, 100), rng.uniform(2, 4, 100)]
    window, out_size = (150, 100, 200, 150), (600, 450)  # a 3x close-up
    win, R_turn = window_camera(cam, window, out_size, turns)
    M = window_pixels(window, out_size, turns)
    px = cam.project(X)
    expect = (M @ np.c_[px, np.ones(len(px))].T).T[:, :2]
    np.testing.assert_allclose(win.project(X @ R_turn.T), expect, atol=1e-6)
    assert (win.width, win.height) == (out_size if turns % 2 == 0 else out_size[::-1])
    np.testing.assert_allclose(turn_rotation(turns) @ turn_rotation(-turns), np.eye(3), atol=1e-12)


def test_cut_window_image_matches_its_pixel_map():
    img = np.zeros((120, 160), np.uint8)
    img[40, 70] = 255  # one bright pixel at (x, y) = (70, 40)
    cam = Camera.parse("PINHOLE 160 120 150 150 80 60")
    window, out_size = (50, 30, 40, 30), (120, 90)
    for turns in range(4):
        out, win, _ = cut_window(img, cam, window, out_size, turns)
        assert out.shape == ((90, 120) if turns % 2 == 0 else (120, 90))
        assert (win.width, win.height) == (out.shape[1], out.shape[0])
        y, x = np.unravel_index(np.argmax(cv2.GaussianBlur(out.astype(np.float32), (0, 0), 2)), out.shape)
        expect = window_pixels(window, out_size, turns) @ [70, 40, 1]
        assert abs(x - expect[0]) <= 1 and abs(y - expect[1]) <= 1
    with pytest.raises(CameraError):
        cut_window(img, cam, (150, 0, 40, 30), out_size)


def test_pycolmap_camera_round_trip_and_convention():
    pycolmap = pytest.importorskip("pycolmap")
    pc = CAM_B.to_pycolmap()
    assert Camera.from_pycolmap(pc) == CAM_B
    pts = np.array([[10.0, 20.0], [400.0, 300.0], [790.0, 10.0]])
    # COLMAP's pixel coordinates are ours + 0.5
    np.testing.assert_allclose(pc.cam_from_img(pts + 0.5), CAM_B.normalize(pts), atol=1e-6)
    for name in CONFIGURATIONS:
        assert hasattr(pycolmap.TwoViewGeometryConfiguration, name)


# ---------------------------------------------------------------------------- two-view geometry
@pytest.mark.parametrize(
    "kind, with_cameras, expected",
    [
        ("plane", True, "PLANAR"),
        ("plane", False, "PLANAR_OR_PANORAMIC"),
        ("two_planes", True, "CALIBRATED"),
        ("two_planes", False, "UNCALIBRATED"),
        ("volume", True, "CALIBRATED"),
        ("volume", False, "UNCALIBRATED"),
    ],
)
def test_configuration_follows_the_scene(kind, with_cameras, expected):
    rng = np.random.default_rng(1)
    xa, xb = observe(make_points(kind, rng), R_AB, T_AB, rng)
    cams = (CAM_A, CAM_B) if with_cameras else (None, None)
    g = estimate_two_view_geometry(xa, xb, *cams)
    assert g.configuration == expected
    assert g.num_inliers >= 0.7 * len(xa) and g.inliers.shape == (len(xa),)
    assert not g.inliers[: int(0.2 * len(xa))].mean() > 0.1  # the outliers are rejected
    if kind == "plane":
        assert g.model == "homography" and g.num_inliers_H > 0.8 * g.num_inliers_F
    else:
        assert g.num_inliers_H < 0.8 * g.num_inliers_F
    if with_cameras:
        rot, trans = relative_pose_error(g.R, g.t, R_AB, T_AB)
        assert rot < 1.0 and trans < 2.0, (rot, trans)
        assert g.reliable and g.tri_angle > 1.0
        assert np.linalg.norm(g.t) == pytest.approx(1.0)
    else:
        assert g.R is None and g.E is None


def test_pose_from_essential_matrix_within_a_degree():
    for seed in range(3):
        rng = np.random.default_rng(10 + seed)
        xa, xb = observe(make_points("volume", rng), R_AB, T_AB, rng, noise=0.5, outliers=0.3)
        g = estimate_two_view_geometry(xa, xb, CAM_A, CAM_B)
        assert g.configuration == "CALIBRATED" and g.pose_source == "E"
        rot, trans = relative_pose_error(g.R_E, g.t_E, R_AB, T_AB)
        assert rot < 1.0 and trans < 1.5, (seed, rot, trans)  # 0.5 px noise: t is the weaker part
        # cheirality: the sign of t is the true one, not only its line
        assert g.t_E @ T_AB / np.linalg.norm(T_AB) > 0.99


def test_pure_rotation_is_panoramic():
    rng = np.random.default_rng(2)
    R = rotation([0.1, 1, 0.2], 12)
    xa, xb = observe(make_points("volume", rng), R, np.zeros(3), rng)
    g = estimate_two_view_geometry(xa, xb, CAM_A, CAM_B)
    assert g.configuration == "PANORAMIC" and g.model == "homography"
    assert relative_pose_error(g.R, np.ones(3), R, np.ones(3))[0] < 1.0
    assert np.all(g.t == 0) and not g.reliable and "panoramic" in g.reasons[0]
    assert estimate_two_view_geometry(xa, xb).configuration == "PLANAR_OR_PANORAMIC"


def test_guessed_focal_lengths_give_no_essential_matrix():
    rng = np.random.default_rng(3)
    xa, xb = observe(make_points("volume", rng), R_AB, T_AB, rng)
    prior = Camera.from_prior(800, 600)
    g = estimate_two_view_geometry(xa, xb, CAM_A, prior)
    assert g.E is None and g.configuration == "UNCALIBRATED" and g.pose_source == "F"
    assert not g.reliable and "guess" in g.reasons[0]


def test_window_with_quarter_turn_gives_the_composed_pose():
    """B is a 3x close-up of a photo, turned by a quarter turn: its pose is R_turn @ (R, t)."""
    rng = np.random.default_rng(4)
    X = make_points("volume", rng, 4000)
    win, R_turn = window_camera(CAM_B, (250, 180, 300, 225), (900, 675), turns=1)
    xa, xb = observe(X, R_AB, T_AB, rng, cam_b=CAM_B, noise=0.0, outliers=0.0)
    Xb = X @ (R_turn @ R_AB).T + R_turn @ T_AB
    xw = win.project(Xb)
    inside = ((xw >= 0) & (xw < [win.width - 1, win.height - 1])).all(1) & (Xb[:, 2] > 0)
    xa_w = CAM_A.project(X[inside]) + rng.normal(0, 0.3, (inside.sum(), 2))
    xw = xw[inside] + rng.normal(0, 0.3, (inside.sum(), 2))
    assert len(xw) > 100
    g = estimate_two_view_geometry(xa_w, xw, CAM_A, win)
    rot, trans = relative_pose_error(g.R_E, g.t_E, R_turn @ R_AB, R_turn @ T_AB)
    assert rot < 1.0 and trans < 2.0, (rot, trans)


def test_bad_inputs_and_too_few_matches():
    rng = np.random.default_rng(5)
    with pytest.raises(TwoViewError):
        estimate_two_view_geometry(np.zeros((20, 2)), np.zeros((19, 2)))
    with pytest.raises(TwoViewError):
        estimate_two_view_geometry(np.zeros((20, 3)), np.zeros((20, 3)))
    pts = rng.uniform(0, 100, (20, 2))
    bad = pts.copy()
    bad[3, 1] = np.nan
    with pytest.raises(TwoViewError):
        estimate_two_view_geometry(pts, bad)
    with pytest.raises(LocalScaleError):
        estimate_two_view_geometry(pts, pts, config=TwoViewConfig(max_error=0))
    with pytest.raises(LocalScaleError):
        estimate_two_view_geometry(pts, pts, CAM_A, "NOT_A_MODEL 1 2 3")

    few = estimate_two_view_geometry(pts[:10], pts[:10] + 3, CAM_A, CAM_A)
    assert few.configuration == "DEGENERATE" and few.num_inliers == 0 and "10 matches" in few.reasons[0]
    empty = estimate_two_view_geometry(np.zeros((0, 2)), np.zeros((0, 2)))
    assert empty.configuration == "DEGENERATE" and not empty.reliable
    noise = estimate_two_view_geometry(
        rng.uniform(0, 640, (200, 2)), rng.uniform(0, 640, (200, 2)), CAM_A, CAM_A, TwoViewConfig(max_error=1.0)
    )
    assert noise.configuration == "DEGENERATE" or noise.num_inliers < 0.3 * 200
    json.dumps(noise.to_dict())


def test_to_dict_is_json():
    rng = np.random.default_rng(6)
    xa, xb = observe(make_points("volume", rng), R_AB, T_AB, rng)
    d = json.loads(json.dumps(estimate_two_view_geometry(xa, xb, CAM_A, CAM_B).to_dict()))
    assert d["configuration"] == "CALIBRATED" and len(d["R"]) == 3 and len(d["inlier_indices"]) == d["num_inliers"]


def test_pose_error_and_auc():
    R = rotation([0, 0, 1], 3.0)
    t = np.array([1.0, 0, 0])
    assert relative_pose_error(R, t, np.eye(3), t) == pytest.approx((3.0, 0.0))
    assert relative_pose_error(np.eye(3), -t, np.eye(3), t)[1] == pytest.approx(0.0)  # sign folded
    assert relative_pose_error(np.eye(3), [math.cos(0.1), math.sin(0.1), 0], np.eye(3), t)[1] == pytest.approx(
        math.degrees(0.1)
    )
    assert relative_pose_error(None, None, np.eye(3), t) == (180.0, 180.0)
    assert pose_auc([0.0] * 4) == pytest.approx([1, 1, 1])
    assert pose_auc([180.0] * 4) == pytest.approx([0, 0, 0])
    # one pair at 2.5 deg: recall rises linearly from 0 at 0 to 1 at 2.5 (SuperGlue's curve)
    assert pose_auc([2.5], (5,)) == pytest.approx([0.75])
    assert pose_auc([2.5, 180.0], (5, 10)) == pytest.approx([0.375, 0.4375])


def test_epipolar_errors_tell_correct_matches_from_wrong_ones():
    """Under the true pose the noisy correct matches lie within 5e-4 (SuperGlue's precision) and
    the uniform outliers beyond it; under another pose the correct ones do not."""
    rng = np.random.default_rng(3)
    xa, xb = observe(make_points("volume", rng), R_AB, T_AB, rng, noise=0.05, outliers=0.25)
    k = int(0.25 * len(xa))
    err = epipolar_errors(xa, xb, CAM_A, CAM_B, R_AB, T_AB)
    assert err.shape == (len(xa),)
    assert np.mean(err[k:] < 5e-4) > 0.95
    assert np.mean(err[:k] < 5e-4) < 0.1
    assert np.allclose(epipolar_errors(xa, xb, CAM_A, CAM_B, R_AB, 3 * T_AB), err)  # scale-free in t
    wrong = epipolar_errors(xa, xb, CAM_A, CAM_B, R_AB @ rotation([0, 1, 0], 5.0), T_AB)
    assert np.mean(wrong[k:] < 5e-4) < 0.2
    assert epipolar_errors(np.zeros((0, 2)), np.zeros((0, 2)), CAM_A, CAM_B, R_AB, T_AB).shape == (0,)
    with pytest.raises(ValueError, match="differ in length"):
        epipolar_errors(xa, xb[:-1], CAM_A, CAM_B, R_AB, T_AB)


# ---------------------------------------------------------------------------- rendered images
def _texture(rng, size=1024):
    """Random multi-scale blob texture (uint8), rich in SIFT keypoints."""
    tex = np.zeros((size, size), np.float32)
    for sigma in (1.5, 3, 6, 12):
        tex += cv2.GaussianBlur(rng.normal(0, 1, (size, size)).astype(np.float32), (0, 0), sigma) * sigma
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    return (255 * tex).astype(np.uint8)


def test_sift_on_two_rendered_views_of_a_textured_plane():
    rng = np.random.default_rng(7)
    tex = _texture(rng)
    # the texture lies on a plane: texel (u, v) -> X = origin + s (u e1 + v e2), in A's frame
    n_rot = rotation([1, 0.3, 0], 20)
    e1, e2, s = n_rot[:, 0], n_rot[:, 1], 10.0 / 1024  # a 10 x 10 plane, 7 in front of A
    origin = np.array([0.0, 0.0, 7.0]) - 512 * s * (e1 + e2)
    cam_a = Camera.parse("PINHOLE 640 480 520 520 320 240")
    cam_b = Camera.parse("PINHOLE 640 480 560 560 320 240")
    R = rotation([0.1, 1, 0.05], 8)
    t = np.array([-0.8, 0.1, 0.1])
    plane_a = np.c_[s * e1, s * e2, origin]  # texel -> A's frame (homogeneous)
    H_a = cam_a.K() @ plane_a
    H_b = cam_b.K() @ (R @ plane_a + np.c_[np.zeros((3, 2)), t])
    img_a = cv2.warpPerspective(tex, H_a, (640, 480), flags=cv2.INTER_LINEAR)
    img_b = cv2.warpPerspective(tex, H_b, (640, 480), flags=cv2.INTER_LINEAR)

    sift = cv2.SIFT_create(4096)
    ka, da = sift.detectAndCompute(img_a, None)
    kb, db = sift.detectAndCompute(img_b, None)
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
    good = [m for m, n2 in knn if m.distance < 0.8 * n2.distance]
    xa = np.float64([ka[m.queryIdx].pt for m in good])
    xb = np.float64([kb[m.trainIdx].pt for m in good])
    assert len(xa) > 200

    g = estimate_two_view_geometry(xa, xb, cam_a, cam_b)
    assert g.configuration == "PLANAR" and g.pose_source == "H"
    rot, trans = relative_pose_error(g.R, g.t, R, t)
    assert rot < 1.0 and trans < 1.0, (rot, trans)
    # the homography is the plane's: A -> B = H_b H_a^-1
    H_true = H_b @ np.linalg.inv(H_a)
    pts = xa[g.inliers][:50]
    proj = cv2.perspectiveTransform(pts[None], H_true)[0]
    est = cv2.perspectiveTransform(pts[None], g.H)[0]
    assert np.median(np.linalg.norm(proj - est, axis=1)) < 1.0


def test_cameras_and_two_view_work_without_pycolmap(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "pycolmap", None)  # import pycolmap -> ImportError
    with pytest.raises(CameraError, match="pip install"):
        CAM_A.to_pycolmap()
    rng = np.random.default_rng(8)
    xa, xb = observe(make_points("volume", rng), R_AB, T_AB, rng)
    g = estimate_two_view_geometry(xa, xb, CAM_A.to_line(), CAM_B.to_dict())
    assert g.configuration == "CALIBRATED"
    with pytest.raises(CameraError):
        g.pycolmap_configuration()
