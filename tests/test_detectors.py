"""The detector registry: every single-scale detector on the bundled example, and the evaluation
and ``match`` with a swapped detector."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from localscale.cli import main as cli_main
from localscale.core.errors import LocalScaleError
from localscale.evaluation import evaluate, load_hpatches, make_pairs, make_sequences
from localscale.features import DETECTORS, detect, detect_keypoints, get_detector
from localscale.matching import match_pair

ASSETS = Path(__file__).resolve().parent.parent / "localscale" / "assets"
IMAGE = ASSETS / "kodim01_a.jpg"


def _available(name):
    return name != "akaze" or hasattr(cv2, "AKAZE_create")


@pytest.fixture(scope="module")
def example():
    from localscale.io import load_image

    return load_image(IMAGE)


@pytest.mark.parametrize("name", DETECTORS)
def test_every_detector_gives_top_k_keypoints_inside_the_image(name, example):
    if not _available(name):
        pytest.skip(f"OpenCV {cv2.__version__} has no AKAZE")
    h, w = example.shape[:2]
    kps, resp = detect(example, name, num_features=300)
    assert kps.dtype == np.float32 and kps.ndim == 2 and kps.shape[1] == 2 and resp.shape == (len(kps),)
    assert 100 <= len(kps) <= 300
    assert (kps >= 0).all() and (kps[:, 0] <= w - 1).all() and (kps[:, 1] <= h - 1).all()
    assert np.all(np.diff(resp) <= 0), "strongest first"
    assert len(np.unique(kps, axis=0)) == len(kps), "no repeated positions"
    few, _ = detect(example, name, num_features=20)
    assert len(few) == 20
    # a path and a tensor give the same keypoints; a tensor gives tensors
    kp_path, _ = detect(IMAGE, name, num_features=300)
    assert np.array_equal(kp_path, kps)
    gray = torch.from_numpy(example.astype(np.float32) / 255).permute(2, 0, 1)
    kt, rt = detect(gray, name, num_features=300)
    assert isinstance(kt, torch.Tensor) and kt.shape[1] == 2 and len(kt) <= 300


def test_hessian_is_the_default_detector(example):
    a, ra = detect(example, num_features=200)
    b, rb = detect_keypoints(example, num_features=200)
    assert np.array_equal(a, b) and np.array_equal(ra, rb)


def test_unknown_detector_and_missing_akaze_are_errors():
    with pytest.raises(LocalScaleError, match="unknown detector 'fast'"):
        get_detector("fast")
    with pytest.raises(LocalScaleError):
        get_detector("orb", num_features=0)
    if not hasattr(cv2, "AKAZE_create"):
        with pytest.raises(LocalScaleError, match="AKAZE"):
            get_detector("akaze")


@pytest.fixture(scope="module")
def tiny_root(tmp_path_factory, photos):
    root = tmp_path_factory.mktemp("hp_det")
    make_sequences([photos["astronaut"], photos["coffee"]], root, num_images=3, size=128, seed=0)
    return root


def test_eval_with_orb(tiny_root, tmp_path):
    pairs = make_pairs(load_hpatches(tiny_root))
    res = evaluate(
        pairs, ["none", "gt"], "hardnet", descriptor="sift", num_features=100, detector="orb", progress=False
    )
    s = res["summary"]["all"]
    assert all(0 <= v <= 1 for m in ("none", "gt") for v in s[m]["mma"])
    assert 0 < s["none"]["num_features"] <= 100 and s["gt"]["mma"][4] >= s["none"]["mma"][4]
    with pytest.raises(LocalScaleError, match="unknown detector"):
        evaluate(pairs, ["none"], "hardnet", descriptor="sift", detector="nope", progress=False)
    out = tmp_path / "out"
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
                "--descriptor",
                "sift",
                "--num-features",
                "100",
                "--detector",
                "orb",
            ]
        )
        == 0
    )
    doc = json.loads((out / "results_hardnet-orb-sift.json").read_text())
    assert doc["matcher_config"]["detector"] == "orb" and doc["summary"]["all"]["none"]["num_features"] <= 100


def test_cli_unknown_detector_is_a_one_line_error(tiny_root, tmp_path, capsys):
    seq = tiny_root / "s_000"
    for argv in (
        ["eval-hpatches", str(tiny_root), "-o", str(tmp_path / "e"), "--detector", "nope"],
        [
            "match",
            str(seq / "1.png"),
            str(seq / "2.png"),
            "-o",
            str(tmp_path / "m"),
            "--detector",
            "nope",
            "--correction",
            "none",
        ],
    ):
        assert cli_main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: unknown detector 'nope'"), err


def test_match_with_another_detector(tiny_root, tmp_path):
    seq = tiny_root / "s_000"
    res = match_pair(
        seq / "1.png", seq / "2.png", "gt", H=seq / "H_1_2", descriptor="sift", num_features=80, detector="gftt"
    )
    assert res.meta["detector"] == "gftt" and 0 < len(res.keypoints_a) <= 80 and len(res.matches) > 0
    assert (
        cli_main(
            [
                "match",
                str(seq / "1.png"),
                str(seq / "2.png"),
                "-o",
                str(tmp_path / "m"),
                "--detector",
                "orb",
                "--correction",
                "none",
                "--descriptor",
                "sift",
                "--num-features",
                "80",
            ]
        )
        == 0
    )
    assert (tmp_path / "m" / "matches.npz").is_file()


def test_detector_table_script_runs_resumes_and_rebuilds(tiny_root, tmp_path, capsys, repo_script):
    mod = repo_script("eval/detector_table.py")
    out = tmp_path / "t"
    args = [
        str(tiny_root),
        "-o",
        str(out),
        "--detectors",
        "orb",
        "gftt",
        "--descriptors",
        "sift",
        "--num-features",
        "60",
        "--quiet",
    ]
    assert mod.main(args) == 0
    rows = json.loads((out / "table.json").read_text())["rows"]
    assert [(r["detector"], r["descriptor"]) for r in rows] == [("gftt", "sift"), ("orb", "sift")]
    assert all(0 <= r["mma5_none"] <= 1 and 0 <= r["mma5_local"] <= 1 for r in rows)
    md = (out / "table.md").read_text()
    assert "| orb + sift |" in md and "MMA@5 local" in md and "matches none" in md
    capsys.readouterr()
    assert mod.main(args) == 0  # kept, not run again
    assert capsys.readouterr().out.count("exists, kept") == 2
    assert mod.main(args + ["--detectors", "nope"]) == 2
    assert capsys.readouterr().err.startswith("error: unknown detector 'nope'")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_local_max_is_the_square_max_pool(dtype):
    from localscale.features.detector import local_max

    r = torch.randn(37, 53, dtype=dtype)
    for radius in (1, 3):
        want = torch.nn.functional.max_pool2d(r[None, None], 2 * radius + 1, stride=1, padding=radius)[0, 0]
        assert torch.equal(local_max(r, radius), want)
