"""Bad input to ``localscale reconstruct``: one ``error:`` line, exit code 2 and nothing written;
skipped files and untrustworthy results flagged with ``warning:``. Runs the command in-process
(``localscale.cli.main`` once it has the command, else the command's own ``main``)."""

import os

import numpy as np
import pytest

pytest.importorskip("pycolmap")
pytest.importorskip("h5py")

os.environ.setdefault("OMP_NUM_THREADS", "1")

from localscale.sfm.synthetic import write_scene  # noqa: E402

FAST = ["--matcher", "sift", "--num-keypoints", "1500", "--no-progress", "--num-threads", "1"]


def run_cli(argv):
    from localscale.cli import main

    return main(["reconstruct", *argv])


def error_lines(err: str) -> list:
    return [line for line in err.splitlines() if line.startswith("error:")]


@pytest.fixture(scope="module")
def views(tmp_path_factory):
    folder = tmp_path_factory.mktemp("views")
    write_scene(folder, num_views=5, shape=(240, 320), seed=3)
    return folder


def _refused(argv, capsys, out=None, match=""):
    code = run_cli(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    lines = error_lines(err)
    assert len(lines) == 1, err
    assert match in lines[0], lines[0]
    if out is not None:
        assert not out.exists() or not any(out.iterdir()), "something was written"
    return lines[0]


def test_empty_folder(tmp_path, capsys):
    (tmp_path / "imgs").mkdir()
    _refused([str(tmp_path / "imgs"), "-o", str(tmp_path / "out"), *FAST], capsys, tmp_path / "out", "no usable images")


def test_missing_folder(tmp_path, capsys):
    _refused([str(tmp_path / "nope"), "-o", str(tmp_path / "out"), *FAST], capsys, tmp_path / "out", "not found")


def test_single_image(tmp_path, capsys):
    write_scene(tmp_path / "imgs", num_views=1, shape=(60, 80))
    _refused(
        [str(tmp_path / "imgs"), "-o", str(tmp_path / "out"), *FAST], capsys, tmp_path / "out", "only one usable image"
    )


def test_only_unreadable_files(tmp_path, capsys):
    d = tmp_path / "imgs"
    d.mkdir()
    (d / "a.jpg").write_bytes(b"not a jpeg at all")
    (d / "b.png").write_bytes(b"")
    (d / "readme.txt").write_text("hello")
    msg = _refused([str(d), "-o", str(tmp_path / "out"), *FAST], capsys, tmp_path / "out", "no usable images")
    assert "2 unreadable" in msg


def test_clashing_names(tmp_path, capsys):
    d = tmp_path / "imgs"
    write_scene(d / "x", num_views=2, shape=(60, 80))
    os.replace(d / "x" / "view_1.png", d / "x-view_0.png")  # x/view_0.png and x-view_0.png
    _refused([str(d), "-o", str(tmp_path / "out"), *FAST], capsys, tmp_path / "out", "clash")


def test_bad_files_are_skipped_with_warnings_and_stems_kept_apart(views, tmp_path, capsys):
    import shutil

    import cv2

    d = tmp_path / "imgs"
    shutil.copytree(views, d)
    (d / "notes.txt").write_text("x")
    (d / "broken.jpg").write_bytes(b"\xff\xd8\xff\xe0 truncated")
    img = cv2.imread(str(d / "view_0.png"))
    cv2.imwrite(str(d / "view_0.jpg"), img)  # same stem, other extension: a sixth view
    out = tmp_path / "out"
    code = run_cli([str(d), "-o", str(out), *FAST])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "warning: skipped 1 file(s) that are not images" in captured.err
    assert "warning: skipped broken.jpg" in captured.err
    assert "view_0.jpg and view_0.png differ only in their extension" in captured.err
    import json

    summary = json.loads((out / "summary.json").read_text())
    assert summary["images"] == 6 and summary["registered"] >= 5
    assert any("differ only in their extension" in w for w in summary["warnings"])
    assert "| registered |" in captured.out


def test_non_empty_output_folder(views, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("keep me")
    _refused([str(views), "-o", str(out), *FAST], capsys, None, "not empty")
    assert sorted(p.name for p in out.iterdir()) == ["mine.txt"]
    assert run_cli([str(views), "-o", str(out), *FAST, "--overwrite"]) == 0
    capsys.readouterr()
    assert (out / "mine.txt").read_text() == "keep me"  # --overwrite replaces only our files
    assert (out / "sparse" / "0").is_dir()
    # our own run, same options: resumed; other options: refused, nothing changed
    assert run_cli([str(views), "-o", str(out), *FAST]) == 0
    assert "resume" in (out / "summary.json").read_text()
    capsys.readouterr()
    before = (out / "summary.json").read_bytes()
    _refused(
        [str(views), "-o", str(out), *FAST[:2], "--num-keypoints", "99", "--no-progress"], capsys, None, "other options"
    )
    assert (out / "summary.json").read_bytes() == before


def test_output_is_a_file(views, tmp_path, capsys):
    f = tmp_path / "out"
    f.write_text("x")
    _refused([str(views), "-o", str(f), *FAST], capsys, None, "")
    assert f.read_text() == "x"


def test_camera_file_missing_or_malformed(views, tmp_path, capsys):
    out = tmp_path / "out"
    _refused(
        [str(views), "-o", str(out), *FAST, "--camera", str(tmp_path / "none.txt")],
        capsys,
        out,
        "camera file not found",
    )
    bad = tmp_path / "cameras.txt"
    bad.write_text("# COLMAP\n1 PINHOLE 320 240 300 300\n")
    _refused([str(views), "-o", str(out), *FAST, "--camera", str(bad)], capsys, out, "PINHOLE takes 4")
    bad.write_text("1 FISHEYE_WHAT 320 240 300\n")
    _refused([str(views), "-o", str(out), *FAST, "--camera", str(bad)], capsys, out, "not supported")
    bad.write_text("1 PINHOLE three 240 300 300 160 120\n")
    _refused([str(views), "-o", str(out), *FAST, "--camera", str(bad)], capsys, out, "must be numbers")
    bad.write_text("1 PINHOLE 400 400 300 300 200 200\n")
    _refused([str(views), "-o", str(out), *FAST, "--camera", str(bad)], capsys, out, "another aspect ratio")
    bad.write_text("1 PINHOLE 320 240 300 300 160 120\n2 PINHOLE 320 240 300 300 160 120\n")
    _refused([str(views), "-o", str(out), *FAST, "--camera", str(bad)], capsys, out, "2 cameras")


def test_good_camera_file_is_used(views, tmp_path, capsys):
    cam = tmp_path / "cameras.txt"
    cam.write_text("# the rendering camera, at twice the size\n1 PINHOLE 640 480 600 600 319.5 239.5\n")
    out = tmp_path / "out"
    assert run_cli([str(views), "-o", str(out), *FAST, "--camera", str(cam)]) == 0
    capsys.readouterr()
    import pycolmap

    rec = pycolmap.Reconstruction(out / "sparse" / "0")
    (camera,) = rec.cameras.values()
    assert camera.model.name == "PINHOLE" and (camera.width, camera.height) == (320, 240)
    assert abs(camera.focal_length_x - 300) < 15  # rescaled to the images, refined near the truth


def test_bad_pairs_options(views, tmp_path, capsys):
    out = tmp_path / "out"
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("view_0.png view_9.png\n")
    _refused([str(views), "-o", str(out), *FAST, "--pairs", str(pairs)], capsys, out, "view_9.png")
    pairs.write_text("view_0.png\n")
    _refused(
        [str(views), "-o", str(out), *FAST, "--pairs", str(pairs)], capsys, out, "expected two images (names or paths)"
    )
    _refused([str(views), "-o", str(out), *FAST, "--pairs", str(tmp_path / "nope.txt")], capsys, out, "not found")
    pairs.write_text("view_0.png view_1.png\n")
    _refused(
        [str(views), "-o", str(out), *FAST, "--pairs", str(pairs), "--pairs-nearest", "2"],
        capsys,
        out,
        "--pairs-nearest",
    )


def test_auto_per_pair_needs_auto(views, tmp_path, capsys):
    out = tmp_path / "out"
    _refused(
        [str(views), "-o", str(out), *FAST, "--auto-per-pair"], capsys, out, "--auto-per-pair needs --correction auto"
    )


def test_disconnected_images_are_flagged(views, tmp_path, capsys):
    """Images that share nothing with the others: the run ends, and says which were not registered."""
    import shutil

    import cv2

    d = tmp_path / "imgs"
    shutil.copytree(views, d)
    rng = np.random.default_rng(7)
    for i in range(2):
        noise = cv2.GaussianBlur((rng.random((240, 320, 3)) * 255).astype(np.uint8), (5, 5), 0)
        cv2.imwrite(str(d / f"noise_{i}.png"), noise)
    out = tmp_path / "out"
    assert run_cli([str(d), "-o", str(out), *FAST]) == 0
    err = capsys.readouterr().err
    assert "warning: only 5 of 7 images registered" in err and "noise_0.png" in err


def test_command_in_a_fresh_process(views, tmp_path):
    """The installed command as a user runs it: a new interpreter, nothing imported before."""
    import json
    import subprocess
    import sys

    out = tmp_path / "out"
    done = subprocess.run(
        [sys.executable, "-m", "localscale", "reconstruct", str(views), "-o", str(out), *FAST],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["registered"] == 5, summary["registered"]


def test_global_mapper_with_nothing_to_calibrate_says_so(tmp_path, capsys):
    """Images that share nothing: the global mapper's view-graph calibration has no pair to use; the
    run says the calibration failed and that no model was built, and exits with 1."""
    import json

    import cv2

    d = tmp_path / "imgs"
    d.mkdir()
    rng = np.random.default_rng(3)
    for i in range(3):
        cv2.imwrite(str(d / f"noise_{i}.png"), (rng.random((240, 320, 3)) * 255).astype(np.uint8))
    out = tmp_path / "out"
    assert run_cli([str(d), "-o", str(out), *FAST, "--mapper", "global"]) == 1
    err = capsys.readouterr().err
    assert "warning: the view-graph calibration failed" in err and "warning: no model" in err
    assert json.loads((out / "summary.json").read_text())["view_graph_calibrated"] is False


@pytest.mark.parametrize(
    "option, match",
    [
        ("ba_refine_extra_params", "--mapper-option takes NAME=VALUE"),
        ("=1", "--mapper-option takes NAME=VALUE"),
        ("no_such_option=1", "incremental mapper has no option 'no_such_option'"),
        ("mapper.abs_pose_min_num_inliers=few", "takes an integer"),
    ],
)
def test_bad_mapper_option(views, tmp_path, capsys, option, match):
    out = tmp_path / "out"
    _refused([str(views), "-o", str(out), *FAST, "--mapper-option", option], capsys, out, match)
