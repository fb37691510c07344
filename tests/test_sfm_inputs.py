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
    assert weight_options("none", "sift")["matcher_weights_sha256"] == {}
