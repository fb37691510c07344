"""HPatches loader, splits, protocol and the synthetic sequence generator."""

import json
import shutil

import cv2
import numpy as np
import pytest
import torch

from localscale.cli import main as cli_main
from localscale.core.errors import LocalScaleError
from localscale.evaluation import (
    evaluate,
    load_hpatches,
    make_pairs,
    make_sequences,
    perspective_split,
    rotation_split,
    scale_split,
)
from localscale.geometry import homography_rotation, orient_homography


@pytest.fixture(scope="module")
def tiny_root(tmp_path_factory, photos):
    root = tmp_path_factory.mktemp("hp")
    imgs = [photos["astronaut"], photos["coffee"]]
    make_sequences(imgs, root, num_images=3, size=128, seed=0)
    # rename to HPatches-like names; add an illumination sequence and a ppm/jpg one
    (root / "s_000").rename(root / "v_astro")
    (root / "s_001").rename(root / "coffee")
    shutil.copytree(root / "v_astro", root / "i_light")
    for k in (1, 2, 3):
        img = cv2.imread(str(root / "coffee" / f"{k}.png"))
        (root / "coffee" / f"{k}.png").unlink()
        cv2.imwrite(str(root / "coffee" / f"{k}.{'ppm' if k != 3 else 'jpg'}"), img)
    (root / "not_a_sequence").mkdir()
    return root


def test_loader_layouts(tiny_root):
    seqs = load_hpatches(tiny_root)
    assert [s.name for s in seqs] == ["coffee", "v_astro"]
    assert sorted(seqs[0].homographies) == [2, 3] and seqs[0].images[1].suffix == ".ppm"
    assert [s.name for s in load_hpatches(tiny_root, include_illumination=True)] == ["coffee", "i_light", "v_astro"]
    assert [s.name for s in load_hpatches(tiny_root, exclude=["coffee"])] == ["v_astro"]
    with pytest.raises(LocalScaleError):
        load_hpatches(tiny_root / "missing")
    with pytest.raises(LocalScaleError):
        load_hpatches(tiny_root / "not_a_sequence")


def test_splits_and_sign(tiny_root):
    pairs = make_pairs(load_hpatches(tiny_root))
    assert len(pairs) == 4
    for p in pairs:
        assert p.perspective_split in ("easy", "medium", "hard") and p.scale_split.startswith("scale")
        assert np.isfinite(p.log2_scale) and p.covisible > 0.2
    assert perspective_split(0.05) == "easy" and perspective_split(0.2) == "medium" and perspective_split(0.3) == "hard"
    assert scale_split(0.1) == "scale<2x" and scale_split(-1.5) == "scale2-4x" and scale_split(2) == "scale>4x"
    assert rotation_split(10) == "rot<30" and rotation_split(-60) == "rot30-90" and rotation_split(180) == "rot>90"
    c, sn = np.cos(np.radians(120)), np.sin(np.radians(120))
    R = np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1.0]])
    assert abs(homography_rotation(R, (100, 100)) - 120) < 1e-6
    assert abs(homography_rotation(np.diag([3.0, 3.0, 1.0]), (100, 100))) < 1e-9
    H = np.array([[2.0, 0, 3], [0, 2, 1], [1e-4, 0, 1]])
    assert np.allclose(orient_homography(-H, (100, 100)), H) and np.allclose(orient_homography(H, (100, 100)), H)


def test_whole_eval_tiny(tiny_root, tmp_path):
    from localscale.models import LocalScaleNet

    torch.manual_seed(0)
    pairs = make_pairs(load_hpatches(tiny_root))
    local = LocalScaleNet(width=0.125, image_size=64).eval()
    res = evaluate(
        pairs,
        ["none", "local", "gt"],
        "hardnet",
        descriptor="sift",
        num_features=150,
        local_model=local,
        progress=False,
    )
    s = res["summary"]
    assert s["all"]["num_pairs"] == 4 and len(res["records"]) == 12
    assert all(r["seconds"] > 0 and r["matcher"] == "hardnet" for r in res["records"])
    for m in ("none", "local", "gt"):
        mma = s["all"][m]["mma"]
        assert len(mma) == 10 and all(0 <= v <= 1 for v in mma) and np.all(np.diff(mma) >= -1e-9)
    assert s["all"]["gt"]["mma"][4] > s["all"]["none"]["mma"][4]
    with pytest.raises(LocalScaleError):
        evaluate(pairs, ["local"], "hardnet")
    from localscale.models import ScaleNet

    res = evaluate(
        pairs[:1],
        ["global", "gt_gated"],
        "hardnet",
        descriptor="sift",
        num_features=100,
        global_model=ScaleNet(width=0.125, image_size=64).eval(),
        progress=False,
    )
    assert set(res["summary"]["all"]) >= {"global", "gt_gated"}


def test_main_writes_outputs(tiny_root, tmp_path):
    out = tmp_path / "out"
    # weights the user names must load: a missing file is an error before anything is computed
    assert (
        cli_main(
            [
                "eval-hpatches",
                str(tiny_root),
                "-o",
                str(out),
                "--methods",
                "none",
                "gt",
                "local",
                "--descriptor",
                "sift",
                "--num-features",
                "100",
                "--local-weights",
                str(tmp_path / "missing.pt"),
            ]
        )
        == 2
    )
    assert not out.exists()
    assert (
        cli_main(
            [
                "eval-hpatches",
                str(tiny_root),
                "-o",
                str(out),
                "--methods",
                "none",
                "gt",
                "--matcher",
                "hardnet",
                "sift",
                "--descriptor",
                "sift",
                "--num-features",
                "100",
            ]
        )
        == 0
    )
    doc = json.loads((out / "results_hardnet-sift.json").read_text())
    assert doc["methods"] == ["none", "gt"] and doc["skipped"] == []
    assert len(doc["splits"]) == 4 and (out / "splits.csv").is_file() and (out / "results_hardnet-sift.md").is_file()
    assert (out / "mma_hardnet-sift_all.png").stat().st_size > 0
    sift = json.loads((out / "results_sift.json").read_text())
    assert sift["matcher"] == "sift" and sift["matcher_config"]["extractor"] == "sift"
    assert sift["matcher_config"]["num_features"] == 100  # --num-features applies to every matcher
    assert "hardnet-sift" in (out / "results.md").read_text() and "sift" in (out / "results.md").read_text()


def test_gate_options(tiny_root, tmp_path):
    import argparse

    from localscale.cli.options import add_hpatches_options
    from localscale.evaluation.hpatches import gate_from_args

    parse = add_hpatches_options(argparse.ArgumentParser()).parse_args
    gate = gate_from_args(parse([str(tiny_root)]))
    assert gate.weighting == "reliability" and gate.consistency
    gate = gate_from_args(parse([str(tiny_root), "--gate-weighting", "none", "--gate-pair", "0.5", "--no-consistency"]))
    assert (gate.weighting, gate.min_pair_log2, gate.consistency) == ("none", 0.5, False)
    with pytest.raises(SystemExit):
        parse([str(tiny_root), "--gate-weighting", "median"])


def test_cropped_sequences_show_real_surroundings(photos, tmp_path):
    """``crop < 1``: image 1 is the photo's centre; image k = the whole photo warped so that
    ``H_1_k`` still maps image 1 onto it, with the photo (not the fill) around that footprint."""
    gray = np.full_like(photos["astronaut"], 128)  # the fill photo
    imgs = [photos["astronaut"], gray, gray, gray]  # image k of sequence 0 is filled from imgs[k]
    for crop in (1.0, 0.6):
        d = make_sequences(imgs, tmp_path / f"c{crop}", num_images=3, size=128, seed=4, crop=crop)[0]
        one = cv2.imread(str(d / "1.png"))
        assert max(one.shape[:2]) == 128
        fill_share = []
        for k in (2, 3):
            H = np.loadtxt(d / f"H_1_{k}")
            b = cv2.imread(str(d / f"{k}.png"))
            size = b.shape[1::-1]
            footprint = cv2.warpPerspective(np.ones(one.shape[:2], np.uint8), H, size)
            inside = cv2.erode(footprint, np.ones((5, 5), np.uint8)) > 0
            ncc = np.corrcoef(
                cv2.warpPerspective(one, H, size)[inside].ravel().astype(float), b[inside].ravel().astype(float)
            )[0, 1]
            assert ncc > 0.9, ncc  # H_1_k maps image 1 onto image k
            grow = lambda n: cv2.dilate(footprint, np.ones((n, n), np.uint8)) > 0  # noqa: E731
            around = grow(21) & ~grow(7)  # a ring just outside image 1's footprint
            if around.sum() > 50:
                fill_share.append((np.abs(b[around].astype(int) - 128) <= 1).all(1).mean())
        assert fill_share
        if crop == 1.0:
            assert min(fill_share) > 0.95  # only the fill around image 1
        else:
            assert np.mean(fill_share) < 0.5  # mostly the photo's surroundings
    with pytest.raises(ValueError):
        make_sequences(imgs, tmp_path / "bad", crop=0)


def test_refined_and_opencv_sift_with_homography_accuracy(tiny_root):
    from localscale.evaluation.report import matching_table
    from localscale.models import LocalScaleNet

    torch.manual_seed(0)
    pairs = make_pairs(load_hpatches(tiny_root))[:2]
    local = LocalScaleNet(width=0.125, image_size=64).eval()
    methods = ["none", "refined", "gt"]
    res = evaluate(pairs, methods, "hardnet", descriptor="sift", num_features=150, local_model=local, progress=False)
    for r in res["records"]:
        assert r["corner_error"] >= 0
    ref = [r for r in res["records"] if r["method"] == "refined"]
    assert all("verified" in r and r["passes"] >= 1 for r in ref)
    for m in methods:
        v = res["summary"]["all"][m]
        assert len(v["h_auc"]) == 3 and all(0 <= x <= 1 for x in v["h_auc"]) and 0 <= v["h_solved"] <= 1
    sift = evaluate(pairs, ["none"], "sift", progress=False)
    assert sift["summary"]["all"]["none"]["h_auc"][2] > 0
    assert "H AUC@5" in matching_table(res["summary"], methods, list(range(1, 11)))
    with pytest.raises(LocalScaleError):
        evaluate(pairs, ["refined"], "hardnet")
