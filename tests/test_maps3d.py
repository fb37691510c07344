"""Map evaluation on 3D scenes: per-point truth of a synthetic two-camera scene against the analytic
scale of the plane it shows, and the error factors of perfect and constant predictors."""

import json
import math

import cv2
import numpy as np
import pytest

from localscale.evaluation import maps3d
from localscale.evaluation import predictors as P
from localscale.evaluation.records import RecordFile
from localscale.geometry import homography_scale_at, homography_scale_map
from localscale.geometry.cameras import window_pixels
from localscale.training.real_pairs import CovisiblePair, save_covisible_pairs

K = np.array([[500.0, 0, 319.5], [0, 500, 239.5], [0, 0, 1]])
SIZE = (480, 640)


def _rot_y(deg):
    a = math.radians(deg)
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def _scene(seed=0, n=600, toward=2.0):
    """Points on a slanted plane seen by camera A (at the origin) and camera B (turned 10 degrees and
    ``toward`` units closer): their pixels in A and B and the plane's homography A -> B."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-4, 4, n), rng.uniform(-3, 3, n)
    X = np.c_[x, y, 8 + 0.15 * x]  # the plane z - 0.15 x = 8
    R, centre = _rot_y(-10), np.array([1.5, 0, toward])
    t = -R @ centre

    def project(P):
        p = P @ K.T
        return p[:, :2] / p[:, 2:]

    pa, pb = project(X), project(X @ R.T + t)
    inside = ((pa >= 0) & (pa < SIZE[::-1])).all(1) & ((pb >= 0) & (pb < SIZE[::-1])).all(1)
    normal = np.array([-0.15, 0, 1.0])
    d = 8 / np.linalg.norm(normal)
    H = K @ (R + np.outer(t, normal / np.linalg.norm(normal)) / d) @ np.linalg.inv(K)
    return pa[inside], pb[inside], H


def _pair(pa, pb, a="a.png", b="b.png", collection="synthetic"):
    # COLMAP's convention: the centre of the top-left pixel is (0.5, 0.5)
    return CovisiblePair(a, b, (pa + 0.5).astype(np.float32), (pb + 0.5).astype(np.float32), collection)


def _texture(seed):
    noise = np.random.default_rng(seed).integers(0, 255, (*SIZE, 3)).astype(np.uint8)
    return cv2.GaussianBlur(noise, (0, 0), 3)


def _kind_homography(lp, H):
    """The homography from A to the B the predictors see (the close-up window, turned)."""
    return H if lp.window is None else window_pixels(lp.window, SIZE[::-1], lp.turns) @ H


@pytest.mark.parametrize("kind", maps3d.KINDS)
def test_truth_matches_the_analytic_scale_of_the_plane(kind):
    pa, pb, H = _scene()
    img = _texture(1)
    lp = maps3d.labelled_pair(_pair(pa, pb), kind, img, img, seed=3)
    assert lp is not None and len(lp.xy_a) >= 20
    analytic = np.log(homography_scale_at(_kind_homography(lp, H), lp.xy_a))
    diff = np.abs(lp.log_truth - analytic)
    assert np.median(diff) < 0.03 and diff.max() < 0.1  # 8-neighbour ratios of a slanted plane
    assert 1.1 < np.exp(np.median(analytic)) / lp.zoom < 1.7  # B is closer: the plane looks bigger
    if kind != "as-is":
        assert 2.5 <= lp.zoom <= 6 and (lp.turns > 0) == (kind == "closeup-turned")
        # the close-up is B's window, enlarged and turned: its pixels at the points are B's there
        inv = np.linalg.inv(window_pixels(lp.window, SIZE[::-1], lp.turns))
        q = np.c_[pb, np.ones(len(pb))] @ window_pixels(lp.window, SIZE[::-1], lp.turns).T
        q = q[:, :2] / q[:, 2:]
        inside = (q >= 2).all(1) & (q[:, 0] < lp.image_b.shape[1] - 2) & (q[:, 1] < lp.image_b.shape[0] - 2)
        back = np.c_[q[inside], np.ones(inside.sum())] @ inv.T
        np.testing.assert_allclose(back[:, :2] / back[:, 2:], pb[inside], atol=1e-6)
        got = lp.image_b[np.rint(q[inside, 1]).astype(int), np.rint(q[inside, 0]).astype(int)].astype(float)
        want = img[np.rint(pb[inside, 1]).astype(int), np.rint(pb[inside, 0]).astype(int)].astype(float)
        assert np.abs(got - want).mean() < 8  # vs ~25 grey levels between unrelated pixels


def test_closeups_are_seeded_by_names_not_order():
    pa, pb, _ = _scene()
    img = _texture(2)
    one = maps3d.labelled_pair(_pair(pa, pb), "closeup-turned", img, img, seed=5)
    again = maps3d.labelled_pair(_pair(pa, pb), "closeup-turned", img, img, seed=5)
    other = maps3d.labelled_pair(_pair(pa, pb), "closeup-turned", img, img, seed=6)
    assert (one.window, one.turns, one.zoom) == (again.window, again.turns, again.zoom)
    assert one.window != other.window
    np.testing.assert_array_equal(one.log_truth, again.log_truth)
    few = maps3d.labelled_pair(_pair(pa[:10], pb[:10]), "as-is", img, img)
    assert few is None  # too few labelled points


def test_perfect_predictor_scores_one_and_constants_score_the_truth(monkeypatch):
    pa, pb, H = _scene()
    img = _texture(3)
    lp = maps3d.labelled_pair(_pair(pa, pb), "closeup", img, img, seed=1)
    monkeypatch.setattr(P, "PREDICTORS", dict(P.PREDICTORS))
    # the analytic map of the plane: the truth up to the labels' 8-neighbour approximation
    P.register_predictor("plane", lambda ctx: homography_scale_map(_kind_homography(lp, H), *SIZE))

    def painted(ctx):  # the labels themselves at their pixels
        m = np.ones(SIZE, np.float32)
        m[np.rint(lp.xy_a[:, 1]).astype(int), np.rint(lp.xy_a[:, 0]).astype(int)] = np.exp(lp.log_truth)
        return m

    P.register_predictor("painted", painted)
    models = P.ScaleModels()
    assert maps3d.score_pair(lp, "painted", models)["error"] == pytest.approx(1.0, abs=1e-5)
    assert maps3d.score_pair(lp, "plane", models)["error"] < 1.03
    one = maps3d.score_pair(lp, "one", models)["error"]
    assert one == pytest.approx(math.exp(np.abs(lp.log_truth).mean()), rel=1e-9)
    assert one > 2.4  # a close-up of 2.5-6x
    assert maps3d.error_factor(np.array([0.0, np.nan]), np.zeros(2)) == pytest.approx(64)


def test_collection_rows_summary_and_resume(tmp_path, monkeypatch):
    pairs = []
    for i in range(3):
        pa, pb, _ = _scene(seed=i, toward=1.0 + i)
        for name in (f"a{i}.png", f"b{i}.png"):
            cv2.imwrite(str(tmp_path / name), _texture(i))
        pairs.append(_pair(pa, pb, str(tmp_path / f"a{i}.png"), str(tmp_path / f"b{i}.png")))
    chosen = maps3d.choose_pairs(pairs, 2, seed=0, collection="synthetic")
    assert chosen == maps3d.choose_pairs(pairs, 2, seed=0, collection="synthetic") and len(chosen) == 2
    assert maps3d.choose_pairs(pairs, None, 0, "synthetic") == pairs
    calls = []
    monkeypatch.setattr(P, "PREDICTORS", dict(P.PREDICTORS))
    P.register_predictor("half", lambda ctx: calls.append(1) or 0.5)
    records = RecordFile(tmp_path / "r.jsonl", {"run": 1})

    def load(path):
        return cv2.imread(str(path))[..., ::-1].copy()

    kinds = ("as-is", "closeup")
    rows = maps3d.evaluate_collection("synthetic", pairs, kinds, ["one", "half"], P.ScaleModels(), load, records)
    assert len(rows) == 6 and not any(r["skipped"] for r in rows) and len(calls) == 6
    s = maps3d.summarise(rows, ["one", "half"])
    closeups = [r for r in rows if r["kind"] == "closeup"]
    assert s["all"]["closeup"]["one"] == pytest.approx(np.mean([r["one"]["error"] for r in closeups]))
    assert s["all"]["closeup"]["one"] > s["all"]["as-is"]["one"]
    assert s["collections"]["synthetic"]["as-is"]["pairs"] == 3
    assert "| all | closeup | 3 |" in maps3d.markdown(s, ["one", "half"])
    again = maps3d.evaluate_collection(
        "synthetic", pairs, kinds, ["one", "half"], P.ScaleModels(), load, RecordFile(tmp_path / "r.jsonl", {"run": 1})
    )
    assert again == rows and len(calls) == 6  # resumed from the records, nothing computed again
    other_run = RecordFile(tmp_path / "r.jsonl", {"run": 2})
    maps3d.evaluate_collection("synthetic", pairs[:1], ("as-is",), ["half"], P.ScaleModels(), load, other_run)
    assert len(calls) == 7  # other weights or options: computed again


def test_script_scores_labelled_collections(repo_script, tmp_path, capsys):
    mc = repo_script("eval/map_collections.py")
    pa, pb, _ = _scene()
    for name in ("a.png", "b.png"):
        cv2.imwrite(str(tmp_path / name), _texture(4))
    labels = tmp_path / "labels" / "synthetic"
    labels.mkdir(parents=True)
    save_covisible_pairs(labels / "pairs.npz", [_pair(pa, pb, str(tmp_path / "a.png"), str(tmp_path / "b.png"))])
    out = tmp_path / "res" / "maps3d.json"
    argv = ["--labels", str(labels.parent), "--predictors", "one", "scalenet", "--out", str(out)]
    assert mc.cli(argv) == 0
    doc = json.loads(out.read_text())
    assert set(doc["all"]) == set(maps3d.KINDS) and doc["skipped"] == 0
    assert doc["all"]["as-is"]["pairs"] == 1 and doc["all"]["closeup"]["one"] > 2.4
    assert math.isfinite(doc["all"]["as-is"]["scalenet"])
    assert doc["local_weights"] == "bundled"
    assert "| synthetic | closeup-turned | 1 |" in out.with_suffix(".md").read_text()
    capsys.readouterr()
    bad = tmp_path / "bad"
    for extra, message in (
        (["--labels", str(tmp_path / "nothing")], "label_collections.py"),
        (["--collections", "absent"], "absent"),
        (["--max-pairs", "-1"], "--max-pairs"),
        (["--zoom", "3", "2"], "--zoom"),
        (["--global-weights", str(tmp_path / "none.pt")], "none.pt"),
    ):
        args = ["--labels", str(labels.parent), "--out", str(bad / "x.json")] + extra
        assert mc.cli(args) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: ") and message in err[0], err
        assert not bad.exists()
