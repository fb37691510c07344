"""Faults around ``localscale reconstruct``'s output folder: a run never deletes or replaces an
input, never mixes with another run or with what a killed run left, and never leaves a summary
that does not describe the folder. Kills are real (SIGKILL of a subprocess at a named point)."""

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import cv2
import pytest

pytest.importorskip("pycolmap")
pytest.importorskip("h5py")

os.environ.setdefault("OMP_NUM_THREADS", "1")

from localscale.sfm.synthetic import write_scene  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FAST = ["--matcher", "sift", "--num-keypoints", "800", "--no-progress", "--num-threads", "1"]

#: runs ``localscale.cli.main(argv)`` and kills itself (SIGKILL) when ``module.attr`` is called
#: the ``nth`` time, before or after the call
KILL_DRIVER = """
import importlib, os, signal, sys
module, attr, nth, when = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
m = importlib.import_module(module)
real, calls = getattr(m, attr), [0]
def killer(*args, **kwargs):
    calls[0] += 1
    if calls[0] == nth and when == "before":
        os.kill(os.getpid(), signal.SIGKILL)
    out = real(*args, **kwargs)
    if calls[0] == nth and when == "after":
        os.kill(os.getpid(), signal.SIGKILL)
    return out
setattr(m, attr, killer)
from localscale.cli import main
sys.exit(main(sys.argv[5:]))
"""


def run_cli(argv):
    from localscale.cli import main

    return main(argv)


def killed_run(argv, point: str, nth: int = 1, when: str = "before") -> int:
    """Run ``localscale argv`` in a subprocess killed at ``point`` (``module:attr``); returns its pid."""
    module, attr = point.split(":")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    cmd = [sys.executable, "-c", KILL_DRIVER, module, attr, str(nth), when, *argv]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == -signal.SIGKILL, f"not killed at {point} (exit {proc.returncode}): {err[-2000:]}"
    return proc.pid


def snapshot(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def leftovers(out: Path) -> list:
    return sorted(p.name for p in out.iterdir() if ".tmp" in p.name or ".new" in p.name or ".old" in p.name)


def error_lines(err: str) -> list:
    return [line for line in err.splitlines() if line.startswith("error:")]


@pytest.fixture(scope="module")
def five(tmp_path_factory):
    folder = tmp_path_factory.mktemp("five")
    write_scene(folder, num_views=5, shape=(120, 160), seed=3)
    return folder


@pytest.fixture(scope="module")
def finished(five, tmp_path_factory):
    """A finished run of four of the five views: ``(images folder, OUT)``."""
    base = tmp_path_factory.mktemp("finished")
    images = base / "images"
    images.mkdir()
    for i in range(4):
        shutil.copy(five / f"view_{i}.png", images)
    assert run_cli(["reconstruct", str(images), "-o", str(base / "out"), *FAST]) == 0
    return images, base / "out"


@pytest.fixture
def finished_copy(finished, tmp_path):
    images, out = finished
    shutil.copytree(images, tmp_path / "images")
    shutil.copytree(out, tmp_path / "out")
    return tmp_path / "images", tmp_path / "out"


# ---------------------------------------------------------------- inputs are never deleted or replaced


@pytest.mark.parametrize("overwrite", [False, True])
def test_an_images_folder_where_the_run_writes_is_refused_and_kept(five, tmp_path, capsys, overwrite):
    out = tmp_path / "out"
    shutil.copytree(five, out / "sparse")
    before = snapshot(out)
    code = run_cli(["reconstruct", str(out / "sparse"), "-o", str(out), *FAST] + ["--overwrite"] * overwrite)
    err = capsys.readouterr().err
    assert code == 2 and len(error_lines(err)) == 1, err
    assert "images folder" in error_lines(err)[0] and "--overwrite" not in err
    assert snapshot(out) == before  # the photos are there, nothing was written


@pytest.mark.parametrize("what", ["image", "pairs file", "camera file", "input file"])
def test_an_input_inside_a_replaced_path_is_refused_and_kept(finished_copy, tmp_path, what):
    from localscale.sfm import OutputFolderError, reconstruct

    images, out = finished_copy
    kwargs = {}
    if what == "image":  # an image file that is a link to a file in OUT/sparse
        flipped = cv2.flip(cv2.imread(str(images / "view_0.png")), 1)  # not a copy of a photo (copies are skipped)
        cv2.imwrite(str(out / "sparse" / "mine.png"), flipped)
        os.symlink(out / "sparse" / "mine.png", images / "view_9.png")
    elif what == "pairs file":
        kwargs["pairs"] = str(out / "pairs.txt")
    elif what == "camera file":
        (out / "sparse" / "camera.txt").write_text("1 PINHOLE 160 120 150 150 80 60\n")
        kwargs["camera_file"] = str(out / "sparse" / "camera.txt")
    else:  # weights the caller loaded
        (out / "sparse" / "weights.pt").write_bytes(b"weights")
        kwargs["input_files"] = [out / "sparse" / "weights.pt"]
    before = snapshot(out)
    with pytest.raises(OutputFolderError, match=what):
        reconstruct(images, out, matcher="sift", num_keypoints=800, overwrite=True, show_progress=False, **kwargs)
    assert snapshot(out) == before


# ---------------------------------------------------------------- one error line, not a traceback


@pytest.mark.parametrize("command", ["reconstruct", "predict", "match"])
def test_a_symlink_loop_as_output_or_images_is_one_error_line(five, tmp_path, capsys, command):
    loop = tmp_path / "loop"
    os.symlink(loop, loop)
    a, b = str(five / "view_0.png"), str(five / "view_1.png")
    inputs = {"reconstruct": [str(five)], "predict": [a, b], "match": [a, b]}[command]
    code = run_cli([command, *inputs, "-o", str(loop)] + (FAST if command == "reconstruct" else []))
    err = capsys.readouterr().err
    assert code == 2 and len(error_lines(err)) == 1 and "link loop" in err, err
    if command == "reconstruct":
        code = run_cli([command, str(loop), "-o", str(tmp_path / "out"), *FAST])
        err = capsys.readouterr().err
        assert code == 2 and len(error_lines(err)) == 1 and "link loop" in err, err
        assert not (tmp_path / "out").exists()


def test_a_file_name_that_is_not_utf8_is_skipped_with_a_warning(five, tmp_path, capsys):
    images = tmp_path / "images"
    shutil.copytree(five, images)
    bad = os.path.join(os.fsencode(images), b"k\xff002.png")
    try:
        os.rename(os.fsencode(images / "view_4.png"), bad)
    except OSError:
        pytest.skip("this file system takes only UTF-8 names")
    assert run_cli(["reconstruct", str(images), "-o", str(tmp_path / "out"), *FAST]) == 0
    err = capsys.readouterr().err
    assert "not valid UTF-8" in err and "k\\xff002.png" in err, err
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["images"] == 4 and summary["registered"] == 4
    assert run_cli(["reconstruct", str(images), "-o", str(tmp_path / "out"), *FAST]) == 0  # and it resumes


# ---------------------------------------------------------------- temporaries of a killed run


def test_temporary_names_are_unique_per_write(tmp_path):
    from localscale.core.outputs import temporary_name

    assert temporary_name(tmp_path / "a.h5") != temporary_name(tmp_path / "a.h5")


def test_a_run_killed_in_the_database_write_reruns_even_with_its_pid(five, tmp_path, monkeypatch, capsys):
    out = tmp_path / "out"
    argv = ["reconstruct", str(five), "-o", str(out), *FAST]
    pid = killed_run(argv, "localscale.sfm.database:read_group", nth=2)  # two cameras' rows written
    assert any(p.name.startswith(".database.") for p in out.iterdir()), "the kill left no temporary file"
    monkeypatch.setattr(os, "getpid", lambda: pid)  # a container restart gives the rerun the same pid
    assert run_cli(argv) == 0, capsys.readouterr().err
    assert leftovers(out) == []
    assert json.loads((out / "summary.json").read_text())["registered"] == 5


# ---------------------------------------------------------------- the summary describes the folder


def _database_images(out: Path) -> int:
    from localscale.sfm import read_database

    return len(read_database(out / "database.db").images)


@pytest.mark.parametrize(
    "point, nth, when",
    [
        ("localscale.sfm.extract:extract_features", 1, "before"),
        ("localscale.sfm.database:read_group", 3, "before"),
        ("localscale.sfm.mapping:_best_of_trials", 1, "before"),
        ("localscale.sfm.mapping:replace_dir", 1, "before"),
        ("localscale.sfm.mapping:replace_dir", 1, "after"),
    ],
)
def test_a_killed_resume_leaves_no_summary_that_does_not_describe_the_folder(
    finished_copy, five, point, nth, when, capsys
):
    from localscale.sfm import read_models

    images, out = finished_copy
    shutil.copy(five / "view_4.png", images)  # a fifth photo, then resume
    before = snapshot(images)
    killed_run(["reconstruct", str(images), "-o", str(out), *FAST], point, nth, when)
    assert snapshot(images) == before
    assert not (out / "summary.json").exists() and not (out / "reconstruction.png").exists()
    models = read_models(out / "sparse")  # the old model or the new one, whole, never none
    assert models and models[0].num_reg_images() in (4, 5)
    assert run_cli(["reconstruct", str(images), "-o", str(out), *FAST]) == 0, capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["images"] == summary["registered"] == _database_images(out) == 5
    assert read_models(out / "sparse")[0].num_reg_images() == 5 and leftovers(out) == []


# ---------------------------------------------------------------- one run at a time


def test_a_second_run_on_a_held_folder_is_refused_and_writes_nothing(finished_copy, capsys):
    fcntl = pytest.importorskip("fcntl")
    images, out = finished_copy
    with open(out / ".lock", "a") as held:  # another run holds the folder
        fcntl.flock(held, fcntl.LOCK_EX)
        before = snapshot(out)
        for extra in ([], ["--overwrite"]):
            code = run_cli(["reconstruct", str(images), "-o", str(out), *FAST, *extra])
            err = capsys.readouterr().err
            assert code == 2 and len(error_lines(err)) == 1 and "another run" in err, err
            assert snapshot(out) == before
    assert run_cli(["reconstruct", str(images), "-o", str(out), *FAST]) == 0  # free again


# ---------------------------------------------------------------- a full disk


@pytest.mark.parametrize("failing_open", [1, 2], ids=["database write", "mapping"])
def test_sqlite_failing_on_a_full_disk_is_one_error_line(five, tmp_path, monkeypatch, capsys, failing_open):
    """pycolmap reports SQLite failing to open a database on a full disk as RuntimeError("No
    registered database factory succeeded."): the database write opens it first, the mapping next."""
    import pycolmap

    real_open, calls = pycolmap.Database.open, [0]

    def open_on_a_full_disk(*args, **kwargs):
        calls[0] += 1
        if calls[0] == failing_open:
            raise RuntimeError("No registered database factory succeeded.")
        return real_open(*args, **kwargs)

    monkeypatch.setattr(pycolmap.Database, "open", staticmethod(open_on_a_full_disk))
    out = tmp_path / "out"
    code = run_cli(["reconstruct", str(five), "-o", str(out), *FAST])
    err = capsys.readouterr().err
    assert code == 2 and len(error_lines(err)) == 1 and "No registered database factory" in err, err
    assert not (out / "summary.json").exists() and leftovers(out) == []
    monkeypatch.undo()
    assert run_cli(["reconstruct", str(five), "-o", str(out), *FAST]) == 0  # with room again
