"""reconstruct on inputs at the edge of what it takes: two views, duplicate photos, thin strips,
16-bit images, implausible cameras, and a resume with other weights. Rendered scenes, no data files."""

import json
import os
import shutil

import cv2
import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")
pytest.importorskip("h5py")

os.environ.setdefault("OMP_NUM_THREADS", "1")

from localscale.cli import main  # noqa: E402
from localscale.sfm import reconstruct  # noqa: E402
from localscale.sfm.synthetic import arc_cameras, write_scene  # noqa: E402

#: the rendered views' own camera (cameras.txt convention: principal point at the image centre)
TRUE_CAMERA = "SIMPLE_PINHOLE 320 240 300 160 120"


@pytest.fixture(scope="module")
def views(tmp_path_factory):
    """Six rendered views on an arc, 8 degrees apart."""
    folder = tmp_path_factory.mktemp("views")
    write_scene(folder, num_views=6, shape=(240, 320), seed=0)
    return folder


def _folder_of(views, tmp_path, names, name="images"):
    folder = tmp_path / name
    folder.mkdir()
    for n in names:
        shutil.copy(views / n, folder / n)
    return folder


def _rotation_error_deg(rec, cams) -> float:
    """Angle between the model's relative rotation of view_0 -> view_1 and the true one."""
    R = {im.name: im.cam_from_world().rotation.matrix() for im in rec.images.values() if im.has_pose}
    d = (R["view_1.png"] @ R["view_0.png"].T) @ (cams[1].R @ cams[0].R.T).T
    return float(np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1))))


@pytest.mark.parametrize("mapper", ["incremental", "global"])
def test_two_views_make_a_two_view_model(views, tmp_path, mapper):
    folder = _folder_of(views, tmp_path, ["view_0.png", "view_1.png"])
    camera = tmp_path / "camera.txt"
    camera.write_text(TRUE_CAMERA + "\n")
    summary = reconstruct(
        folder, tmp_path / "out", matcher="sift", camera_file=camera, mapper=mapper, num_threads=1, show_progress=False
    )
    assert summary["pairs_verified"] == 1
    assert summary["registered"] == 2 and summary["points"] >= 50
    assert summary["mean_reprojection_error"] < 1.0
    assert not any("no model" in w for w in summary["warnings"])
    rec = pycolmap.Reconstruction(tmp_path / "out" / "sparse" / "0")
    assert _rotation_error_deg(rec, arc_cameras(6, (240, 320))) < 2.0  # the true relative rotation is 14 degrees


def test_a_pair_without_an_initial_geometry_says_why(views, tmp_path, capsys):
    folder = tmp_path / "images"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(2):  # two unrelated noise images: nothing verifies
        cv2.imwrite(str(folder / f"noise_{i}.png"), rng.integers(0, 255, (240, 320, 3), dtype=np.uint8))
    code = main(["reconstruct", str(folder), "-o", str(tmp_path / "out"), "--matcher", "sift", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 1
    assert "warning: no model: the mapper registered no images (no pair verified)" in err


def _other_scalenet(path):
    """A ScaleNet checkpoint with other weights (the bundled one, one bias nudged)."""
    import torch

    from localscale.models import ScaleNet
    from localscale.models.base import WEIGHTS_DIR

    ckpt = torch.load(WEIGHTS_DIR / ScaleNet.default_weights, map_location="cpu", weights_only=False)
    name = next(k for k, v in ckpt["state_dict"].items() if k.endswith("bias") and v.is_floating_point())
    ckpt["state_dict"][name] = ckpt["state_dict"][name] + 1e-3
    torch.save(ckpt, path)
    return path


def test_a_rerun_with_other_weights_is_refused_and_the_weights_are_recorded(views, tmp_path, capsys):
    folder = _folder_of(views, tmp_path, ["view_0.png", "view_1.png", "view_2.png"])
    out = tmp_path / "out"
    base = ["reconstruct", str(folder), "-o", str(out), "--matcher", "sift", "--correction", "global", "--no-progress"]
    assert main(base) == 0
    run = json.loads((out / "run.json").read_text())["options"]
    summary = json.loads((out / "summary.json").read_text())["options"]
    assert len(run["global_weights_sha256"]) == 64 and run["local_weights_sha256"] is None  # global: ScaleNet only
    assert summary["global_weights_sha256"] == run["global_weights_sha256"]
    capsys.readouterr()
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}

    other = _other_scalenet(tmp_path / "other.pt")
    assert main(base + ["--global-weights", str(other)]) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and "global_weights_sha256" in lines[0]
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before  # nothing written

    assert main(base + ["--global-weights", str(other), "--overwrite"]) == 0
    again = json.loads((out / "run.json").read_text())["options"]
    from localscale.sfm.weights import file_sha256

    assert again["global_weights_sha256"] == file_sha256(other) != run["global_weights_sha256"]


def test_the_matcher_weight_files_are_recorded():
    from localscale.sfm.weights import matcher_weight_files, weight_options

    try:
        files = [p.name for p in matcher_weight_files("aliked-lightglue")]
    except Exception:
        pytest.skip("the ALIKED/LightGlue weight package is not installed")
    assert files == ["aliked-n16.pth", "aliked_lightglue.pth"]
    options = weight_options("none", "aliked-lightglue")
    assert sorted(options["matcher_weights_sha256"]) == sorted(files)
    assert options["local_weights_sha256"] is None and options["global_weights_sha256"] is None
    assert weight_options("none", "sift")["matcher_weights_sha256"] is None


def _reconstruct_cli(folder, out, capsys, *extra):
    code = main(["reconstruct", str(folder), "-o", str(out), "--matcher", "sift", "--no-progress", *extra])
    return code, capsys.readouterr().err


def test_duplicate_photos_are_kept_once(views, tmp_path, capsys):
    folder = _folder_of(views, tmp_path, ["view_0.png", "view_1.png", "view_2.png"])
    shutil.copy(views / "view_1.png", folder / "view_1_copy.png")
    shutil.copy(views / "view_2.png", folder / "again.png")
    code, err = _reconstruct_cli(folder, tmp_path / "out", capsys)
    assert code == 0 and "Traceback" not in err
    line = next(line for line in err.splitlines() if "duplicate" in line)
    assert line.startswith("warning: skipped 2 duplicate image(s)")
    assert "view_1_copy.png (= view_1.png)" in line and "view_2.png (= again.png)" in line
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["images"] == 3 and summary["registered"] == 3
    assert any("duplicate" in w for w in summary["warnings"])
    run = json.loads((tmp_path / "out" / "run.json").read_text())
    assert sorted(run["images"]) == ["again.png", "view_0.png", "view_1.png"]


def test_a_long_thin_strip_is_skipped_with_a_warning(views, tmp_path, capsys):
    folder = _folder_of(views, tmp_path, ["view_0.png", "view_1.png", "view_2.png"])
    rng = np.random.default_rng(0)
    cv2.imwrite(str(folder / "strip.png"), rng.integers(0, 255, (20, 20000, 3), dtype=np.uint8))
    code, err = _reconstruct_cli(folder, tmp_path / "out", capsys)
    assert code == 0
    line = next(line for line in err.splitlines() if "strip.png" in line)
    assert line.startswith("warning: skipped strip.png:") and "1024x1" in line and "too thin" in line
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["images"] == 3 and any("strip.png" in w and "too thin" in w for w in summary["warnings"])


def test_a_16_bit_png_is_a_warning_line_and_in_the_summary(views, tmp_path, capfd):
    folder = _folder_of(views, tmp_path, ["view_0.png", "view_1.png", "view_2.png"])
    rgb = cv2.imread(str(views / "view_3.png"))
    cv2.imwrite(str(folder / "deep.png"), rgb.astype(np.uint16) * 257)
    code = main(["reconstruct", str(folder), "-o", str(tmp_path / "out"), "--matcher", "sift", "--no-progress"])
    err = capfd.readouterr().err
    assert code == 0
    assert "UserWarning" not in err and "io.py" not in err
    lines = [line for line in err.splitlines() if "16-bit" in line]
    assert len(lines) == 1 and lines[0].startswith("warning: deep.png") and "rescaled to 8 bit" in lines[0]
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["registered"] == 4 and any("deep.png" in w and "16-bit" in w for w in summary["warnings"])


BAD_CAMERAS = {
    "principal point": "SIMPLE_RADIAL 320 240 300 1e308 120 0",
    "radial distortion": "SIMPLE_RADIAL 320 240 300 160 120 1e9",
    "focal length": "SIMPLE_PINHOLE 320 240 1e9 160 120",
    "tangential distortion": "OPENCV 320 240 300 300 160 120 0 0 5 0",
}


@pytest.mark.parametrize("what", sorted(BAD_CAMERAS))
def test_implausible_cameras_are_refused(views, tmp_path, capsys, what):
    folder = _folder_of(views, tmp_path, ["view_0.png", "view_1.png"])
    camera = tmp_path / "camera.txt"
    camera.write_text(BAD_CAMERAS[what] + "\n")
    out = tmp_path / "out"
    code, err = _reconstruct_cli(folder, out, capsys, "--camera", str(camera))
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1, err
    assert lines[0].startswith(f"error: camera file {camera}: {what}")
    assert not out.exists()
    code = main(
        ["match", str(folder / "view_0.png"), str(folder / "view_1.png"), "-o", str(out), "--camera", str(camera)]
    )
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error:") and what in lines[0]
    assert not out.exists()


@pytest.mark.parametrize(
    "line",
    [
        "SIMPLE_RADIAL 320 240 100 160 120 -0.2",  # wide angle
        "PINHOLE 320 240 9000 9000 160 120",  # long telephoto
        "PINHOLE 320 240 300 300 -100 250",  # a crop off the centre
        "FULL_OPENCV 320 240 300 300 160 120 20 5 0 0 1 20 5 1",  # rational model, large terms that cancel
    ],
)
def test_plausible_cameras_are_accepted(line):
    from localscale.geometry.cameras import as_camera

    assert as_camera(line).to_line().split()[0] == line.split()[0]


@pytest.mark.parametrize("mapper", ["incremental", "global"])
def test_two_views_among_unrelated_images_make_a_model(views, tmp_path, mapper):
    folder = _folder_of(views, tmp_path, ["view_0.png", "view_1.png"])
    noise = np.random.default_rng(1).integers(0, 255, (240, 320, 3), dtype=np.uint8)
    cv2.imwrite(str(folder / "noise.png"), noise)
    summary = reconstruct(folder, tmp_path / "out", matcher="sift", mapper=mapper, num_threads=1, show_progress=False)
    assert summary["pairs_verified"] == 1
    assert summary["registered"] == 2 and summary["unregistered_images"] == ["noise.png"]
    assert summary["mapping_runs"][-1]["two_views"] is True
