"""Which pairs a reconstruction matches: ``--pairs auto`` (every pair up to a number of images,
retrieval beyond), ``exhaustive``, ``--pairs-nearest``; on synthetic ``features.h5`` files."""

import json

import numpy as np
import pytest

pytest.importorskip("h5py")

from localscale.core.errors import LocalScaleError  # noqa: E402
from localscale.sfm import pairs as pairs_mod  # noqa: E402
from localscale.sfm.config import PairsConfig, ReconstructConfig  # noqa: E402
from localscale.sfm.h5io import H5Writer  # noqa: E402
from localscale.sfm.pairs import (  # noqa: E402
    AUTO_EXHAUSTIVE_MAX,
    AUTO_NEAREST,
    PairsRule,
    pairs_of_features,
    pairs_rule,
    read_pairs,
)


def fake_features(path, num_images: int, seed: int = 0):
    """``features.h5`` with made-up descriptors (128 x 64 per image): images in groups of 4 share a
    descriptor pattern, so retrieval has something to find."""
    rng = np.random.default_rng(seed)
    bases = rng.normal(size=(num_images // 4 + 1, 128, 64)).astype(np.float32)
    w = H5Writer(path)
    names = [f"img_{i:03d}.jpg" for i in range(num_images)]
    for i, n in enumerate(names):
        d = bases[i // 4] + 0.3 * rng.normal(size=(128, 64)).astype(np.float32)
        w.add(n, {"keypoints": rng.uniform(0, 100, (64, 2)).astype(np.float32), "descriptors": d})
    w.flush()
    return names


def test_auto_is_every_pair_up_to_n_images_and_retrieval_beyond():
    auto = PairsConfig()
    assert auto.pairs == "auto" and ReconstructConfig().pairs == auto
    assert pairs_rule(auto, 2) == PairsRule("exhaustive")
    assert pairs_rule(auto, AUTO_EXHAUSTIVE_MAX) == PairsRule("exhaustive")
    assert pairs_rule(auto, AUTO_EXHAUSTIVE_MAX + 1) == PairsRule("retrieval", AUTO_NEAREST)
    # asked for explicitly, exhaustive is every pair whatever the number of images
    assert pairs_rule(PairsConfig("exhaustive"), 10 * AUTO_EXHAUSTIVE_MAX) == PairsRule("exhaustive")
    # --pairs-nearest sets K, and applies whatever the number of images
    assert pairs_rule(PairsConfig(pairs_nearest=7), 3) == PairsRule("retrieval", 7)
    assert pairs_rule(PairsConfig(pairs_nearest=7), 10 * AUTO_EXHAUSTIVE_MAX) == PairsRule("retrieval", 7)
    assert pairs_rule(PairsConfig("my_pairs.txt"), 1000) == PairsRule("file")
    assert str(PairsRule("retrieval", 7)) == "retrieval (7 nearest)"
    assert AUTO_NEAREST < AUTO_EXHAUSTIVE_MAX


def test_the_pairs_step_applies_the_rule(tmp_path, monkeypatch):
    monkeypatch.setattr(pairs_mod, "AUTO_EXHAUSTIVE_MAX", 8)
    monkeypatch.setattr(pairs_mod, "AUTO_NEAREST", 3)
    small, big = tmp_path / "small.h5", tmp_path / "big.h5"
    fake_features(small, 8)
    names = fake_features(big, 16)
    out = tmp_path / "pairs.txt"
    pairs_of_features(small, out)
    assert len(read_pairs(out)) == 8 * 7 // 2
    pairs_of_features(big, out)
    got = read_pairs(out)
    assert 16 * 3 // 2 <= len(got) <= 16 * 3 < 16 * 15 // 2
    assert {n for p in got for n in p} == set(names)
    # the images of a group of 4 (alike descriptors) are each other's nearest
    assert {("img_000.jpg", "img_001.jpg"), ("img_000.jpg", "img_002.jpg")} <= {tuple(sorted(p)) for p in got}
    pairs_of_features(big, out, ReconstructConfig.from_flat(pairs="exhaustive"))
    assert len(read_pairs(out)) == 16 * 15 // 2
    pairs_of_features(small, out, ReconstructConfig.from_flat(pairs_nearest=2))
    assert len(read_pairs(out)) <= 8 * 2 < 8 * 7 // 2
    # the same features give the same pairs (a resumed run's pairs.txt does not change)
    again = tmp_path / "again.txt"
    pairs_of_features(big, again)
    pairs_of_features(big, out)
    assert again.read_text() == out.read_text()


@pytest.mark.parametrize(
    "options, message",
    [
        (dict(pairs="nope.txt"), "--pairs must be 'auto', 'exhaustive' or a pairs file; file not found: nope.txt"),
        (dict(pairs="exhaustive", pairs_nearest=5), "give it without --pairs exhaustive"),
        (dict(pairs_nearest=0), "--pairs-nearest must be an integer >= 1, got 0"),
        (dict(pairs_nearest=2.5), "--pairs-nearest must be an integer >= 1"),
    ],
)
def test_bad_pairs_options_are_one_clear_error(options, message):
    with pytest.raises(LocalScaleError, match=message.replace("(", r"\(").replace(")", r"\)")):
        ReconstructConfig.from_flat(**options).check()


def test_the_pairs_step_refuses_a_bad_value_in_one_line(tmp_path, capsys):
    f = tmp_path / "features.h5"
    fake_features(f, 4)
    assert pairs_mod.main([str(f), str(tmp_path / "pairs.txt"), "--pairs", "bogus"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: --pairs must be 'auto', 'exhaustive'")


def test_a_configuration_from_before_auto_keeps_its_pairs(tmp_path):
    # pairs_nearest once applied to the default "exhaustive": it is auto with pairs_nearest now
    old = ReconstructConfig.from_dict({"pairs": {"pairs": "exhaustive", "pairs_nearest": 10}})
    assert old.pairs == PairsConfig("auto", 10) and pairs_rule(old.pairs, 5) == PairsRule("retrieval", 10)
    old.check()
    every = ReconstructConfig.from_dict({"pairs": {"pairs": "exhaustive", "pairs_nearest": None}})
    assert pairs_rule(every.pairs, 1000) == PairsRule("exhaustive")
    saved = tmp_path / "run.json"
    saved.write_text(json.dumps({"config": {"pairs": {"pairs": "exhaustive", "pairs_nearest": 3}}}))
    features = tmp_path / "features.h5"
    fake_features(features, 12)
    assert pairs_mod.main([str(features), str(tmp_path / "pairs.txt"), "--config", str(saved)]) == 0
    assert len(read_pairs(tmp_path / "pairs.txt")) <= 12 * 3
