"""The reconstruction's options in one place (ReconstructConfig) and its steps run alone, from files."""

import json
import subprocess
import sys

import pytest

pytest.importorskip("pycolmap")
pytest.importorskip("h5py")

from localscale.core.errors import LocalScaleError  # noqa: E402
from localscale.sfm import RESULT_OPTIONS, ReconstructConfig, reconstruct  # noqa: E402
from localscale.sfm.synthetic import write_scene  # noqa: E402

OPTS = dict(num_threads=1, show_progress=False, plot=False)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scene")
    write_scene(folder, num_views=4, shape=(240, 320), seed=0)
    return folder


@pytest.fixture(scope="module")
def run(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("sfm") / "out"
    conf = ReconstructConfig.from_flat(matcher="sift", num_keypoints=1024)
    return out, conf, reconstruct(scene, out, conf, **OPTS)


def test_the_config_is_the_run_json_and_the_keywords_map_into_it(run, scene, tmp_path):
    out, conf, summary = run
    saved = json.loads((out / "run.json").read_text())
    assert ReconstructConfig.from_dict(saved["config"]) == conf
    assert saved["options"]["matcher"] == "sift" and saved["options"]["num_keypoints"] == 1024
    assert summary["registered"] == 4
    # today's keyword arguments are the same run: resumed, not refused
    again = reconstruct(scene, out, matcher="sift", num_keypoints=1024, **OPTS)
    assert again["run"] == "resume" and again["points"] == summary["points"]
    # the options a resume compares come from the config's fields
    for name in ("matcher", "max_side", "num_keypoints", "pairs", "pairs_nearest", "correction", "merge_px"):
        assert name in RESULT_OPTIONS
    assert "mapper" not in RESULT_OPTIONS and "local_weights_sha256" in RESULT_OPTIONS
    with pytest.raises(LocalScaleError, match="unknown reconstruction option 'matchr'"):
        reconstruct(scene, tmp_path / "x", matchr="sift", **OPTS)
    with pytest.raises(LocalScaleError, match="conf must be a ReconstructConfig"):
        reconstruct(scene, tmp_path / "x", "sift", **OPTS)  # the matcher was the third argument once
    with pytest.raises(LocalScaleError, match="--max-side must be an integer >= 16"):
        ReconstructConfig.from_flat(max_side=3).check()
    assert not (tmp_path / "x").exists()


def test_auto_pairs_record_their_rule_and_a_resumed_run_keeps_it(run, scene, tmp_path, monkeypatch):
    from localscale.sfm import pairs

    out, conf, summary = run
    saved = json.loads((out / "run.json").read_text())["options"]
    assert (saved["pairs"], saved["pairs_rule"], saved["pairs_rule_nearest"]) == ("auto", "exhaustive", None)
    assert summary["options"]["pairs_rule"] == "exhaustive" and summary["pairs"] == 6
    before = (out / "pairs.txt").read_text()
    monkeypatch.setattr(pairs, "AUTO_EXHAUSTIVE_MAX", 3)  # 4 images: retrieval now
    monkeypatch.setattr(pairs, "AUTO_NEAREST", 1)
    again = reconstruct(scene, out, conf, **OPTS)
    assert again["run"] == "resume" and (out / "pairs.txt").read_text() == before
    assert again["options"]["pairs_rule"] == "exhaustive"
    assert any("keeps its pairs rule, exhaustive" in w for w in again["warnings"])
    fresh = reconstruct(scene, tmp_path / "fresh", conf, **OPTS)
    assert (fresh["options"]["pairs_rule"], fresh["options"]["pairs_rule_nearest"]) == ("retrieval", 1)
    assert 2 <= fresh["pairs"] <= 4


def test_each_step_runs_alone_from_files_and_gives_the_run(run, scene, tmp_path):
    from localscale.sfm import database, extract, geometry, mapping, match, pairs
    from localscale.sfm.mapping import model_stats, read_models

    out, _, summary = run
    steps = tmp_path / "steps"
    flags = ["--matcher", "sift", "--num-keypoints", "1024"]
    assert extract.main([str(scene), str(steps / "features.h5"), *flags]) == 0
    assert pairs.main([str(steps / "features.h5"), str(steps / "pairs.txt")]) == 0
    assert (steps / "pairs.txt").read_text() == (out / "pairs.txt").read_text()
    assert match.main([str(scene), str(steps), "--config", str(out / "run.json")]) == 0
    assert geometry.main([str(scene), str(steps)]) == 0
    assert database.main([str(scene), str(steps)]) == 0
    assert mapping.main([str(scene), str(steps), "--num-threads", "1"]) == 0
    stats = model_stats(read_models(steps / "sparse")[0])
    assert (stats["registered"], stats["points"], stats["observations"]) == (
        summary["registered"],
        summary["points"],
        summary["observations"],
    )


def test_a_step_refuses_bad_input_in_one_line(scene, tmp_path, capsys):
    from localscale.sfm import match

    assert match.main([str(scene), str(tmp_path), "--correction", "bogus"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: correction must be one of")
    assert list(tmp_path.iterdir()) == []


def test_a_step_runs_as_a_module():
    proc = subprocess.run(
        [sys.executable, "-m", "localscale.sfm.geometry", "--help"], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0 and "geometries.h5" in proc.stdout


def test_each_pairs_geometry_is_estimated_once_over_reruns(run, scene, tmp_path, monkeypatch):
    import shutil

    from localscale.sfm import geometry

    out, conf, summary = run
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    calls = []
    real = geometry.estimate_pair
    monkeypatch.setattr(geometry, "estimate_pair", lambda *a, **k: calls.append(1) or real(*a, **k))
    again = reconstruct(scene, copy, conf, **OPTS)
    assert again["run"] == "resume" and calls == []  # every pair's stored geometry kept
    assert again["pairs_verified"] == summary["pairs_verified"] and again["points"] == summary["points"]
    # another camera is another input: estimated again
    other = conf.replace(camera_file=str(_camera(tmp_path)))
    reconstruct(scene, copy, other, overwrite=True, **OPTS)
    assert len(calls) == summary["pairs"]


def _camera(tmp_path):
    path = tmp_path / "camera.txt"
    path.write_text("1 PINHOLE 320 240 300 300 160 120\n")
    return path


def test_auto_estimates_each_pairs_geometry_once_and_the_geometry_step_takes_it(scene, tmp_path, monkeypatch):
    """With ``auto``, the pairs kept as they are get their two-view geometry in the match step, from
    the geometry step's own estimator; the geometry step takes it: one estimate per pair, none by
    the package's other estimator, and the model is the one a plain geometry step makes."""
    from localscale.matching import verification
    from localscale.sfm import geometry

    calls, other = [], []
    real, real_other = geometry.estimate_pair, verification.estimate_two_view_geometry
    monkeypatch.setattr(geometry, "estimate_pair", lambda *a, **k: calls.append(1) or real(*a, **k))
    monkeypatch.setattr(
        verification, "estimate_two_view_geometry", lambda *a, **k: other.append(1) or real_other(*a, **k)
    )
    conf = ReconstructConfig.from_flat(matcher="sift", num_keypoints=1024, correction="auto")
    summary = reconstruct(scene, tmp_path / "auto", conf, **OPTS)
    g = summary["geometry"]
    kept = [p for p in summary["matching"]["pairs"] if p["chosen"] == "as they are"]
    assert summary["pairs"] == 6 and len(kept) == 6 and summary["registered"] == 4
    assert g["from_matching"] == 6 and g["estimated"] == 0 and len(calls) == 6 and other == []
    # the stored geometries are those the geometry step estimates from the files
    again = geometry.verify_files(scene, tmp_path / "auto", conf, show_progress=False)
    assert again.reused == 6
    (tmp_path / "auto" / "geometries.h5").unlink()
    fresh = geometry.verify_files(scene, tmp_path / "auto", conf, show_progress=False)
    assert fresh.from_matching == 6 and fresh.estimated == 0
    monkeypatch.setattr(geometry, "read_matched_geometries", lambda path: {})
    (tmp_path / "auto" / "geometries.h5").unlink()
    own = geometry.verify_files(scene, tmp_path / "auto", conf, show_progress=False)
    assert own.estimated == 6 and own.verified == fresh.verified == 6
    for key, stored in fresh.pairs.items():  # same configuration, inliers within a few (RANSAC on reordered matches)
        assert own.pairs[key]["config"] == stored["config"]
        assert abs(own.pairs[key]["inliers"] - stored["inliers"]) <= 0.05 * stored["matches"], (
            key,
            own.pairs[key],
            stored,
        )
