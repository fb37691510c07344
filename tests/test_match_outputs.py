"""``match``'s output files are all written or none: a write that fails (a full disk) or a stop
removes those the run wrote already, and the inputs stay as they were."""

import errno
import hashlib
import os
import shutil

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "1")

from localscale.cli import main  # noqa: E402
from localscale.sfm.synthetic import write_scene  # noqa: E402


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pair")
    write_scene(folder, num_views=6, shape=(240, 320), seed=0)
    return folder / "view_0.png", folder / "view_1.png"


def _digest(paths) -> dict:
    return {str(p): hashlib.sha256(p.read_bytes()).hexdigest() for p in paths}


def test_a_failed_write_leaves_none_of_the_files(pair, tmp_path, capsys, monkeypatch):
    import localscale.matching.pipeline as pipeline

    camera = tmp_path / "camera.txt"
    camera.write_text("SIMPLE_PINHOLE 320 240 300 160 120\n")
    inputs = _digest([*pair, camera])
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")

    def full_disk(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(out / "matches.png"))

    monkeypatch.setattr(pipeline, "draw_matches", full_disk)
    argv = ["match", str(pair[0]), str(pair[1]), "-o", str(out), "--matcher", "sift", "--camera", str(camera)]
    assert main(argv) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert lines[-1].startswith("error:") and "No space left on device" in lines[-1]
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]  # matches.npz removed, the user's file kept
    assert _digest([*pair, camera]) == inputs

    monkeypatch.undo()
    assert main(argv) == 0
    assert {"matches.npz", "matches.png", "geometry.json"} <= {p.name for p in out.iterdir()}
    shutil.rmtree(out)
