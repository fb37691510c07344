"""Pruning before LightGlue (:mod:`localscale.sfm.prune`), LightGlue's run-time precision, and their options."""

import numpy as np
import pytest

from localscale.core.errors import LocalScaleError
from localscale.matching import Matcher, match_config
from localscale.sfm.config import ReconstructConfig
from localscale.sfm.prune import mutual_nn_count, skip_pair


def _texture(seed: int, shape=(160, 208)) -> np.ndarray:
    import cv2

    rng = np.random.default_rng(seed)
    img = np.full((*shape, 3), 128, np.uint8)
    for _ in range(60):
        c = tuple(int(v) for v in rng.integers(0, 256, 3))
        x, y = int(rng.integers(0, shape[1])), int(rng.integers(0, shape[0]))
        if rng.random() < 0.5:
            cv2.circle(img, (x, y), int(rng.integers(3, 14)), c, -1)
        else:
            cv2.rectangle(img, (x, y), (x + int(rng.integers(4, 20)), y + int(rng.integers(4, 20))), c, -1)
    return img


@pytest.fixture(scope="module")
def features():
    m = Matcher(match_config("aliked-lightglue", num_features=256, max_side=256))
    a = _texture(0)
    b = np.ascontiguousarray(np.roll(a, (6, 9), axis=(0, 1)))  # the same scene, shifted
    c = _texture(1)  # another scene
    return m, [m.extract(im) for im in (a, b, c)]


def test_prune_skips_unrelated_pair_and_keeps_matching_pair(features):
    _, (fa, fb, fc) = features
    same, other = mutual_nn_count(fa.descriptors, fb.descriptors), mutual_nn_count(fa.descriptors, fc.descriptors)
    assert same > 4 * max(other, 1)
    assert skip_pair(fa.descriptors, fc.descriptors, min_mnn=16)
    assert not skip_pair(fa.descriptors, fb.descriptors, min_mnn=16)
    assert not skip_pair(fa.descriptors, fc.descriptors, min_mnn=0)  # 0: never skips


@pytest.mark.parametrize("precision", ["bf16", "int8"])
def test_lightglue_precision_matches_as_fp32(features, precision):
    m, (fa, fb, _) = features
    fast = Matcher(match_config("aliked-lightglue", num_features=256, max_side=256, lightglue_precision=precision))
    exact = Matcher(match_config("aliked-lightglue", num_features=256, max_side=256, lightglue_precision="fp32"))
    ref = {tuple(r) for r in exact.match_features(fa, fb)[0]}
    got = {tuple(r) for r in fast.match_features(fa, fb)[0]}
    assert len(ref) >= 10 and len(ref & got) >= 0.8 * len(ref)


@pytest.mark.parametrize(
    "make, text",
    [
        (lambda: ReconstructConfig.from_flat(prune_mnn=-1).check(), "--prune-mnn must be an integer >= 0"),
        (lambda: ReconstructConfig.from_flat(prune_mnn=2.5).check(), "--prune-mnn must be an integer >= 0"),
        (lambda: match_config("aliked-lightglue", lightglue_precision="fp16"), "lightglue_precision must be one of"),
    ],
)
def test_bad_speed_options_are_one_line_errors(make, text):
    with pytest.raises(LocalScaleError) as e:
        make()
    assert text in str(e.value) and "\n" not in str(e.value)


def test_run_before_the_speed_options_resumes_as_fp32_without_pruning(tmp_path):
    import json

    from localscale.sfm.outdir import OutputFolderError
    from localscale.sfm.reconstruction import _output_state

    old = ReconstructConfig().options()
    del old["lightglue_precision"], old["prune_mnn"]  # a run.json written before these options
    (tmp_path / "run.json").write_text(json.dumps({"options": old}))
    (tmp_path / "features.h5").write_bytes(b"")
    assert _output_state(tmp_path, ReconstructConfig.from_flat(lightglue_precision="fp32").options(), False) == "resume"
    with pytest.raises(OutputFolderError, match="lightglue_precision: 'fp32' there, 'auto' now"):
        _output_state(tmp_path, ReconstructConfig().options(), False)


def test_auto_precision_is_bf16_only_on_a_cpu_that_has_it(monkeypatch):
    import localscale.matching.lightglue as lg

    monkeypatch.setattr(lg, "cpu_has_bf16", lambda: False)
    assert lg.resolve_precision("auto", "cpu") == "fp32"
    monkeypatch.setattr(lg, "cpu_has_bf16", lambda: True)
    assert lg.resolve_precision("auto", "cpu") == "bf16"
    assert lg.resolve_precision("auto", "cuda") == "fp32"
    assert lg.resolve_precision("int8", "cpu") == "int8"
