"""Registered images whose pose is not to be trusted (localscale.sfm.registration_check): an image
with implausible intrinsics or far from every image it shares points with is registered again with
a plausible focal length, or left out and reported; summary.json's placement against a reference
model; the new options' bad values. A rendered scene, no data files."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from localscale.sfm import reconstruct  # noqa: E402
from localscale.sfm.mapping import model_stats  # noqa: E402
from localscale.sfm.registration_check import check_registrations, closeup_sources  # noqa: E402
from localscale.sfm.synthetic import write_scene  # noqa: E402


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scene")
    cameras = write_scene(folder, num_views=6, shape=(240, 320), seed=0)
    table = folder.parent / f"{folder.name}_truth.txt"  # the true cameras: 'name K R t' lines
    table.write_text(
        "".join(
            f"view_{i}.png " + " ".join(f"{v:.9f}" for v in [*c.K.ravel(), *c.R.ravel(), *c.t.ravel()]) + "\n"
            for i, c in enumerate(cameras)
        )
    )
    out = tmp_path_factory.mktemp("sfm") / "out"
    summary = reconstruct(
        folder,
        out,
        matcher="sift",
        num_keypoints=2048,
        camera_mode="per_image",
        num_threads=1,
        show_progress=False,
    )
    return folder, out, summary, table


def _model(out):
    return pycolmap.Reconstruction(out / "sparse" / "0")


def _centre(rec, name):
    return next(np.asarray(im.projection_center()) for im in rec.images.values() if im.name == name)


def test_summary_counts_the_images_placed_right_against_a_reference(run, tmp_path, capsys):
    """One camera for the six views: each sits within 5% of the spread of its true centre; moving
    one true centre by 30% of the spread makes that one image wrong (and a warning)."""
    folder, _, _, table = run
    lines = table.read_text().splitlines()
    centres = {}
    for ln in lines:
        f = ln.split()
        R, t = np.array(f[10:19], float).reshape(3, 3), np.array(f[19:22], float)
        centres[f[0]] = -R.T @ t
    c = np.array(list(centres.values()))
    spread = np.median(np.linalg.norm(c - c.mean(0), axis=1))
    f = lines[4].split()  # view_4: its centre moved by 0.3 x the spread along the camera's x axis
    t = np.array(f[19:22], float) - np.array([0.3 * spread, 0, 0])
    moved = tmp_path / "moved.txt"
    moved.write_text("\n".join(lines[:4] + [" ".join(f[:19] + [f"{v:.9f}" for v in t])] + lines[5:]) + "\n")
    common = dict(matcher="sift", num_keypoints=2048, num_threads=1, show_progress=False, camera_mode="single")
    summary = reconstruct(folder, tmp_path / "out", reference_model=table, **common)
    p = summary["placement"]
    assert p["reference"] == "model" and (p["placed_right"], p["checked"], p["wrong"]) == (6, 6, [])
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["placement"]["placed_right"] == 6
    assert summary["suspect_images"] == [] and summary["left_out_images"] == []
    capsys.readouterr()
    summary = reconstruct(folder, tmp_path / "out", reference_model=moved, **common)  # resumed
    assert (summary["placement"]["placed_right"], summary["placement"]["wrong"]) == (5, ["view_4.png"])
    assert 0.25 < summary["placement"]["errors"]["view_4.png"] < 0.45  # over the moved reference's spread
    assert "warning: 5 of 6 images placed right against the reference model; not: view_4.png" in capsys.readouterr().err


def test_an_image_with_implausible_intrinsics_is_left_out_and_reported(run, capsys):
    from localscale.sfm.summary import flag

    _, out, summary, _ = run
    rec = _model(out)
    image = next(im for im in rec.images.values() if im.name == "view_2.png")
    rec.cameras[image.camera_id].params = [3e7, *list(rec.cameras[image.camera_id].params)[1:]]
    assert model_stats(rec)["bogus_cameras"] == ["view_2.png"]
    reports = check_registrations(rec, {}, {}, reregister=False)
    assert reports == [{"image": "view_2.png", "reason": reports[0]["reason"], "action": "left out"}]
    assert "implausible intrinsics" in reports[0]["reason"]
    stats = model_stats(rec)
    assert stats["registered"] == 5 and "view_2.png" not in stats["registered_images"]
    assert stats["bogus_cameras"] == []
    flag({**summary, "registered": 5, "suspect_images": reports, "unregistered_images": ["view_2.png"]})
    err = capsys.readouterr().err
    assert "warning: 1 registered image(s) left out of the model" in err and "view_2.png" in err


def test_a_suspect_image_is_registered_again_with_its_plausible_focal_length(run):
    _, out, _, _ = run
    rec = _model(out)
    image = next(im for im in rec.images.values() if im.name == "view_3.png")
    camera = rec.cameras[image.camera_id]
    focal, before = float(camera.params[0]), _centre(rec, "view_3.png")
    camera.params = [3e7, *list(camera.params)[1:]]
    reports = check_registrations(rec, {"view_3.png": focal}, {})
    assert [(r["image"], r["action"]) for r in reports] == [("view_3.png", "re-registered")]
    assert model_stats(rec)["registered"] == 6 and model_stats(rec)["bogus_cameras"] == []
    spread = np.median([np.linalg.norm(_centre(rec, n) - before) for n in ("view_0.png", "view_5.png")])
    assert np.linalg.norm(_centre(rec, "view_3.png") - before) < 0.02 * spread


def test_an_image_far_from_the_images_it_shares_points_with_is_placed_again(run):
    _, out, _, _ = run
    rec = _model(out)
    image = next(im for im in rec.images.values() if im.name == "view_1.png")
    before = _centre(rec, "view_1.png")
    pose = image.cam_from_world()
    far = pycolmap.Rigid3d(pose.rotation, pose.translation + np.array([0.0, 0.0, 1e4]))
    rec.frames[image.frame_id].rig_from_world = far
    assert np.linalg.norm(_centre(rec, "view_1.png") - before) > 1000
    reports = check_registrations(rec, {}, {})
    assert [(r["image"], r["action"]) for r in reports] == [("view_1.png", "re-registered")]
    assert "from every image it shares points with" in reports[0]["reason"]
    assert np.linalg.norm(_centre(rec, "view_1.png") - before) < 0.05


def test_closeups_are_found_by_zoom_and_a_turning_camera():
    from types import SimpleNamespace

    from localscale.matching.auto.graph import Relation

    pairs = [
        SimpleNamespace(a="c.jpg", b="p1.jpg", relation=Relation(0.25, 2, 50)),  # c shows 4 x larger
        SimpleNamespace(a="p0.jpg", b="c.jpg", relation=Relation(3.9, 2, 80)),
        SimpleNamespace(a="p0.jpg", b="p2.jpg", relation=Relation(2.5, 0, 90)),  # walked closer: not a zoom
        SimpleNamespace(a="p0.jpg", b="p1.jpg", relation=Relation(1.1, 0, 90)),
    ]
    geometry = {
        ("c.jpg", "p1.jpg"): {"config": "PLANAR_OR_PANORAMIC", "inliers": 50},
        ("p0.jpg", "c.jpg"): {"config": "UNCALIBRATED", "inliers": 80},
        ("p0.jpg", "p2.jpg"): {"config": "UNCALIBRATED", "inliers": 90},
        ("p0.jpg", "p1.jpg"): {"config": "CALIBRATED", "inliers": 90},
    }
    assert closeup_sources(pairs, geometry) == {"c.jpg": ("p1.jpg", 4.0)}


@pytest.mark.parametrize(
    "args, message",
    [
        (["--suspect-images", "drop"], "--suspect-images: invalid choice"),
        (["--reference-model", "no/such/model"], "reference model not found"),
        (["--final-distortion", "all"], "--final-distortion: invalid choice"),
    ],
)
def test_bad_new_options_are_one_error_line(run, tmp_path, args, message):
    folder = run[0]
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "localscale", "reconstruct", str(folder), "-o", str(out), "--matcher", "sift", *args]
    p = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": os.getcwd()})
    errors = [ln for ln in p.stderr.splitlines() if ln.startswith("error:")]  # an argument error: usage first
    assert p.returncode == 2 and len(errors) == 1 and message in errors[0], p.stderr
    assert "Traceback" not in p.stderr and p.stderr.rstrip().splitlines()[-1] == errors[0]
    assert not out.exists()


@pytest.mark.parametrize(
    "option, message",
    [({"suspect_images": "drop"}, "--suspect-images must be one of"), ({"final_distortion": 1}, "--final-distortion")],
)
def test_bad_new_option_values_are_refused_by_the_api(run, tmp_path, option, message):
    from localscale.core.errors import LocalScaleError

    with pytest.raises(LocalScaleError, match=message):
        reconstruct(run[0], tmp_path / "out", matcher="sift", show_progress=False, **option)
    assert not (tmp_path / "out").exists()


def test_the_final_bundle_adjustment_refines_the_photos_distortion_not_the_closeups(run, tmp_path):
    """A final bundle adjustment refines every camera's distortion but those of the images kept
    (close-ups), and the model stays right; ``final_distortion="photos"`` runs it in ``reconstruct``."""
    import shutil

    from localscale.sfm.refine import refine_distortion

    folder, out, _, _ = run
    again = tmp_path / "out"
    shutil.copytree(out, again)
    common = dict(matcher="sift", num_keypoints=2048, camera_mode="per_image", num_threads=1, show_progress=False)
    summary = reconstruct(folder, again, final_distortion="photos", **common)
    assert summary["run"] == "resume" and summary["registered"] == 6
    assert summary["distortion_refined"] == [f"view_{i}.png" for i in range(6)]
    assert summary["options"]["final_distortion"] == "photos"
    rec = _model(out)
    keep = "view_0.png"
    before = {im.name: np.array(rec.cameras[im.camera_id].params) for im in rec.images.values()}
    refined = refine_distortion(rec, keep={keep}, num_threads=1)
    assert refined == sorted(n for n in before if n != keep)
    after = {im.name: np.array(rec.cameras[im.camera_id].params) for im in rec.images.values()}
    assert np.array_equal(after[keep], before[keep])
    assert all(after[n][3] != 0.0 for n in refined)  # k1 was 0 (fixed while mapping), now refined
    assert model_stats(rec)["bogus_cameras"] == [] and model_stats(rec)["mean_reprojection_error"] < 1.5


def test_the_picture_marks_a_far_camera_instead_of_shrinking_the_others(run, tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from localscale.sfm.viz import _set_limits, far_cameras, plot_reconstruction

    ring = np.array([[np.cos(a), np.sin(a)] for a in np.linspace(0, 6, 8)])
    far = np.vstack([ring, [[7500.0, 0.0]]])
    assert far_cameras(far).tolist() == [False] * 8 + [True] and not far_cameras(ring).any()
    fig, ax = plt.subplots()
    _set_limits(ax, ring)
    assert ax.get_xlim()[1] < 2 and ax.get_ylim()[1] < 2  # the view holds the ring, not the far camera
    plt.close(fig)
    _, out, _, _ = run
    rec = _model(out)
    image = next(im for im in rec.images.values() if im.name == "view_1.png")
    pose = image.cam_from_world()
    rec.frames[image.frame_id].rig_from_world = pycolmap.Rigid3d(pose.rotation, pose.translation + [0.0, 0.0, 1e4])
    names = sorted(im.name for im in rec.images.values())
    assert plot_reconstruction(tmp_path / "r.png", rec, names, {}, "far").stat().st_size > 10_000


def test_a_closeups_guessed_camera_starts_at_its_zoom_without_distortion():
    from localscale.geometry.cameras import Camera
    from localscale.sfm.cameras import CameraSetup
    from localscale.sfm.registration_check import closeup_focal_priors

    cams = {1: Camera.from_prior(640, 480), 2: Camera.from_prior(640, 480), 3: Camera.from_focal(640, 480, 500.0)}
    setup = CameraSetup(cams, {"p.jpg": 1, "c.jpg": 2, "e.jpg": 3}, "per_image", "exif")
    assert closeup_focal_priors(setup, {"c.jpg": ("p.jpg", 4.0), "e.jpg": ("p.jpg", 3.0)}) == ["c.jpg"]
    c = setup.camera("c.jpg")
    assert c.model == "SIMPLE_PINHOLE" and c.focal_lengths[0] == pytest.approx(4 * 1.2 * 640)
    assert setup.camera("e.jpg").focal_lengths[0] == 500.0  # a known focal length stays
    single = CameraSetup({1: Camera.from_prior(640, 480)}, {"p.jpg": 1, "c.jpg": 1}, "single", "exif")
    assert closeup_focal_priors(single, {"c.jpg": ("p.jpg", 4.0)}) == []


def test_a_closeup_far_from_its_photo_is_left_out_when_it_cannot_be_placed_there(run):
    """An image said to be a close-up of another photo (one place, zoom 1) while the model puts them
    apart: re-registered at the zoom's focal length it stays apart, so it is left out."""
    _, out, _, _ = run
    rec = _model(out)
    focal = {im.name: rec.cameras[im.camera_id].mean_focal_length() for im in rec.images.values()}
    zoom = focal["view_5.png"] / focal["view_0.png"]
    reports = check_registrations(rec, {}, {"view_5.png": ("view_0.png", zoom)})
    assert [(r["image"], r["action"]) for r in reports] == [("view_5.png", "left out")]
    assert "from its photo's centre" in reports[0]["reason"]
    assert model_stats(rec)["registered"] == 5
