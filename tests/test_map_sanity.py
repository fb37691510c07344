"""Sanity pairs (zooms, quarter turns, rotations of one photo) and their report."""

import dataclasses
import json
import math

import cv2
import numpy as np
import pytest

from localscale.core.errors import LocalScaleError
from localscale.evaluation import predictors as P
from localscale.evaluation.sanity import (
    SanityCase,
    default_cases,
    evaluate_photo,
    magnification,
    make_sanity_pair,
    markdown,
    score_map,
    summarise,
)


@pytest.fixture(scope="module")
def photo(photos):
    return cv2.resize(photos["coffee"], (240, 160), interpolation=cv2.INTER_AREA)


def _back_to_a(pair):
    """B resampled at ``H(x)`` for every pixel x of A (what A should look like where B shows it)."""
    h, w = pair.image_a.shape[:2]
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    q = np.stack([xs, ys, np.ones_like(xs)], -1) @ pair.H.T
    mx, my = (q[..., 0] / q[..., 2]).astype(np.float32), (q[..., 1] / q[..., 2]).astype(np.float32)
    return cv2.remap(pair.image_b, mx, my, cv2.INTER_LINEAR).astype(np.float64)


def _content_error(pair):
    """Mean absolute difference between A and B brought back by ``H``, inside the visible region
    (away from its border)."""
    inner = cv2.erode(pair.visible.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    return np.abs(_back_to_a(pair) - pair.image_a.astype(np.float64))[inner].mean()


@pytest.mark.parametrize(
    "case",
    [SanityCase(3), SanityCase(1 / 3), SanityCase(turns=1), SanityCase(turns=2), SanityCase(rotation=30)]
    + [SanityCase(2, 1), SanityCase(0.5, 0, 45.0), SanityCase(4, 3, 0)],
    ids=lambda c: c.name,
)
def test_pair_truth_and_content_follow_the_homography(photo, case):
    pair = make_sanity_pair(photo, case)
    assert pair.image_a.shape == photo.shape
    np.testing.assert_allclose(pair.truth[pair.visible], case.zoom, rtol=1e-5)
    # B shows A's content where H sends it (a wrong H leaves differences of tens of grey levels)
    assert _content_error(pair) < 6
    wrong = dataclasses.replace(pair, H=pair.H @ magnification(1.2, photo.shape[:2]))
    assert _content_error(wrong) > 3 * _content_error(pair)


def test_visible_region_of_a_window(photo):
    h, w = photo.shape[:2]
    zoom_in = make_sanity_pair(photo, SanityCase(4))  # B shows the central quarter (sides) of A
    assert abs(zoom_in.visible.mean() - 1 / 16) < 0.01
    ys, xs = np.nonzero(zoom_in.visible)
    assert abs(xs.mean() - (w - 1) / 2) < 1 and abs(ys.mean() - (h - 1) / 2) < 1
    assert make_sanity_pair(photo, SanityCase(1 / 4)).visible.all()  # A is a window of B: all seen
    assert make_sanity_pair(photo, SanityCase(turns=1)).visible.all()
    rotated = make_sanity_pair(photo, SanityCase(rotation=45)).visible.mean()
    assert 0.4 < rotated < 0.9  # the corners of A leave B's frame


def test_swapping_the_window_inverts_the_pair(photo):
    z = 3.0
    fwd, back = make_sanity_pair(photo, SanityCase(z)), make_sanity_pair(photo, SanityCase(1 / z))
    np.testing.assert_array_equal(fwd.image_a, back.image_b)  # the photo
    np.testing.assert_array_equal(fwd.image_b, back.image_a)  # its enlarged window
    Hi = np.linalg.inv(back.H)
    np.testing.assert_allclose(fwd.H / fwd.H[2, 2], Hi / Hi[2, 2], atol=1e-9)
    assert np.median(fwd.truth[fwd.visible]) == pytest.approx(z)
    assert np.median(back.truth[back.visible]) == pytest.approx(1 / z)
    turned = make_sanity_pair(photo, SanityCase(turns=1))
    assert turned.image_b.shape[:2] == photo.shape[1::-1]
    np.testing.assert_array_equal(turned.image_b, np.rot90(photo))


def test_default_cases_cover_both_directions_turns_and_rotations():
    cases = default_cases()
    names = [c.name for c in cases]
    for z in (1.5, 2, 3, 4, 6, 8):
        assert f"zoom {z:g}" in names and f"zoom 1/{z:g}" in names
    assert {"turn 90", "turn 180", "turn 270", "rot 30", "rot 45", "zoom 4 + turn 90", "zoom 1/2 + rot 45"} <= set(
        names
    )
    assert len(set(names)) == len(names)
    assert {c.group for c in cases} == {"identity", "zoom", "turn", "rotation", "combined"}
    with pytest.raises(LocalScaleError, match="zoom must be positive"):
        SanityCase(0)


def test_score_map_passes_within_ten_percent():
    truth = np.full((20, 30), 4.0, np.float32)
    vis = np.zeros((20, 30), bool)
    vis[5:15, 10:20] = True
    assert score_map(4.3, truth, vis)["pass"] and score_map(4 / 1.09, truth, vis)["pass"]
    assert not score_map(4.5, truth, vis)["pass"] and not score_map(4 / 1.12, truth, vis)["pass"]
    pred = np.where(vis, 4.0, 0.1).astype(np.float32)  # only the visible region counts
    s = score_map(pred, truth, vis)
    assert s["pass"] and s["ratio"] == pytest.approx(1.0) and s["error"] == pytest.approx(1.0)
    off = score_map(np.full((20, 30), 2.0), truth, vis)
    assert off["ratio"] == pytest.approx(0.5) and off["error"] == pytest.approx(2.0)


def test_report_fails_constant_one_on_zooms_and_passes_the_oracle(photo):
    cases = default_cases(zooms=(2, 6), turns=(1,), rotations=(30,), combined_zooms=(3,))
    names = ["one", "correction:gt"]
    rows = evaluate_photo("coffee", photo, cases, names, P.ScaleModels())
    assert len(rows) == len(cases)
    for r in rows:
        assert r["correction:gt"]["pass"], r["case"]
        assert r["one"]["pass"] == (r["truth"] == pytest.approx(1.0)), r["case"]
    summary = summarise(rows + [dict(r, photo="again") for r in rows], names)
    assert summary["passed"]["one"]["zoom"] == [0, 8] and summary["passed"]["one"]["turn"] == [2, 2]
    assert summary["passed"]["correction:gt"]["combined"] == [8, 8]
    table = markdown(summary, names)
    assert "| zoom 6 | 6 | 1 (0/2) | 6 (2/2) |" in table
    assert "| passed: all | | 6/22 | 22/22 |" in table


def test_predictor_registry_and_plugged_function(monkeypatch, tmp_path):
    with pytest.raises(LocalScaleError, match="unknown predictor"):
        P.check_predictors(["local", "nonsense"])
    for bad in ("nomodule", "json:no_such_function", "no_such_module_xyz:f"):
        with pytest.raises(LocalScaleError, match="--system"):
            P.load_function(bad)
    (tmp_path / "plug_maps.py").write_text(
        "import numpy as np\n"
        "class Out:\n"
        "    def __init__(self, s): self.scale = s\n"
        "def system(a, b, local_model=None, global_model=None):\n"
        "    return Out(np.full(a.shape[:2], 2.0, np.float32))\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(P, "PREDICTORS", dict(P.PREDICTORS))
    models, names = P.prepare(["one"], system="plug_maps:system")
    assert names == ["one", "system"]
    models._loaded.update({"local": object(), "global": object()})  # the function gets the models, unused here
    a = np.zeros((12, 16, 3), np.uint8)
    out = P.predict("system", P.PairContext(a, a, models))
    assert out.shape == (12, 16) and float(out.mean()) == 2.0
    assert P.predict("one", P.PairContext(a, a, models)) == 1.0


def test_script_writes_the_table_and_resumes(repo_script, tmp_path, photo, monkeypatch):
    ms = repo_script("eval/map_sanity.py")
    folder = tmp_path / "photos"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"p{i}.png"), np.roll(photo, 20 * i, 1)[..., ::-1])
    out = tmp_path / "res" / "sanity.json"
    argv = [str(folder), "--held-out", "--predictors", "local", "one", "--zooms", "3", "--turns", "1"]
    argv += ["--rotations", "--combined-zooms", "--out", str(out)]
    assert ms.cli(argv) == 0
    doc = json.loads(out.read_text())
    assert [p.rsplit("/", 1)[-1] for p in doc["photos"]] == ["p0.png"]  # every 10th, sorted
    assert [c["case"] for c in doc["cases"]] == ["identity", "zoom 3", "zoom 1/3", "turn 90"]
    local = {c["case"]: c["local"]["median"] for c in doc["cases"]}
    assert all(math.isfinite(v) and v > 0 for v in local.values())
    assert local["zoom 3"] > local["zoom 1/3"]  # the network sees which way the zoom goes
    assert "| zoom 3 | 3 |" in out.with_suffix(".md").read_text()
    records = out.with_suffix(".records.jsonl").read_text().splitlines()
    assert len(records) == 8  # 4 cases x 2 predictors
    monkeypatch.setattr(ms.sanity, "predict", lambda *a, **k: pytest.fail("a resumed run computed a record again"))
    assert ms.cli(argv) == 0
    assert json.loads(out.read_text())["cases"] == doc["cases"]


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--per-folder", "0"], "--per-folder"),
        (["--zooms", "0.5"], "factors > 1"),
        (["--predictors", "bogus"], "unknown predictor"),
        (["--local-weights", "missing.pt"], "missing.pt"),
        (["--system", "nomodule"], "--system"),
    ],
)
def test_script_refuses_bad_input(repo_script, tmp_path, photo, capsys, extra, message):
    ms = repo_script("eval/map_sanity.py")
    cv2.imwrite(str(tmp_path / "p.png"), photo)
    out = tmp_path / "res" / "s.json"
    assert ms.cli([str(tmp_path / "p.png"), "--out", str(out)] + extra) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and message in err[0]
    assert not (tmp_path / "res").exists()


def test_script_scores_a_training_checkpoint(repo_script, tmp_path, photo):
    """``--local-weights`` scores the given checkpoint (a training run's ``last.pt`` with its train
    state), and a bundled run's records in the same file are not reused for it."""
    import torch

    from localscale import LocalScaleNet, scales
    from localscale.checkpoint import checkpoint_dict

    ms = repo_script("eval/map_sanity.py")
    net = LocalScaleNet.from_pretrained()
    ckpt = checkpoint_dict(net)
    ckpt["state_dict"]["head.out.bias"] = ckpt["state_dict"]["head.out.bias"].clone()
    ckpt["state_dict"]["head.out.bias"][scales.NUM_BINS - 1] += 30.0  # every pixel: the largest bin
    ckpt["train_state"] = {"step": 3}
    torch.save(ckpt, tmp_path / "last.pt")
    cv2.imwrite(str(tmp_path / "p.png"), photo)
    out = tmp_path / "s.json"
    argv = [str(tmp_path / "p.png"), "--predictors", "local", "--zooms", "--turns", "--rotations"]
    argv += ["--combined-zooms", "--out", str(out)]
    assert ms.cli(argv) == 0
    bundled = json.loads(out.read_text())["cases"][0]["local"]["median"]
    assert ms.cli(argv + ["--local-weights", str(tmp_path / "last.pt")]) == 0
    doc = json.loads(out.read_text())
    assert doc["local_weights"] == str(tmp_path / "last.pt")
    assert 0.8 < bundled < 1.25 and doc["cases"][0]["local"]["median"] > 4 * bundled


def test_script_keeps_photos_of_the_same_name_apart(repo_script, tmp_path, photo):
    ms = repo_script("eval/map_sanity.py")
    for i, folder in enumerate(("one", "two")):
        (tmp_path / folder).mkdir()
        cv2.imwrite(str(tmp_path / folder / "01.png"), np.rot90(photo, 2 * i)[..., ::-1])
    out = tmp_path / "s.json"
    argv = [str(tmp_path / "one"), str(tmp_path / "two"), "--predictors", "one", "--zooms", "2", "--turns"]
    assert ms.cli(argv + ["--rotations", "--combined-zooms", "--out", str(out)]) == 0
    assert len(out.with_suffix(".records.jsonl").read_text().splitlines()) == 2 * 3  # 2 photos x 3 cases
    assert [c["photos"] for c in json.loads(out.read_text())["cases"]] == [2, 2, 2]
