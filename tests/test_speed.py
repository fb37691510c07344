"""The fast paths give the results of the plain ones: batched description, patches of a subset of
keypoints, work shared between methods in the HPatches evaluation, lazy imports of the CLI."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from localscale.features import HardNetDescriptor, ScaleCorrectedPatches, SIFTPatchDescriptor, image_to_gray_tensor
from localscale.features.descriptors import default_batch_size
from localscale.features.detector import HessianDetector
from localscale.io import load_image, read_homography
from localscale.matching import NO_GATE, match_descriptors, match_pair, reprojection_errors, scale_maps_for_pair
from localscale.matching.config import MatchConfig

ASSETS = Path(__file__).resolve().parent.parent / "localscale" / "assets"


@pytest.fixture(scope="module")
def gray_and_keypoints():
    g = image_to_gray_tensor(load_image(ASSETS / "kodim01_a.jpg"))
    kps, _ = HessianDetector(400)(g)
    return g, kps


@pytest.mark.parametrize("cls", [HardNetDescriptor, SIFTPatchDescriptor])
def test_batched_describe_equals_per_patch_describe(cls, gray_and_keypoints):
    g, kps = gray_and_keypoints
    desc = cls.from_pretrained() if cls is HardNetDescriptor else cls().eval()
    # radii from 16 to 64 px: several pyramid levels; more patches than one default batch
    radii = 16 + 48 * torch.rand(len(kps), generator=torch.Generator().manual_seed(0))
    patches, _ = ScaleCorrectedPatches().patches_from_radii(g, kps, radii)
    assert len(patches) > default_batch_size()
    single = torch.cat([desc.describe(patches[i : i + 1]) for i in range(len(patches))])
    for bs in (None, 7, 1000):
        batched = desc.describe(patches, batch_size=bs)
        assert batched.shape == single.shape
        torch.testing.assert_close(batched, single, atol=1e-5, rtol=0)
    out = desc.describe(patches)
    out[0] = 0  # an ordinary tensor, not an inference-mode one
    assert not desc.training


@pytest.mark.parametrize("orientation", ["upright", "gradient"])
def test_patches_of_a_subset_are_rows_of_the_full_set(orientation, gray_and_keypoints):
    g, kps = gray_and_keypoints
    cutter = ScaleCorrectedPatches(orientation=orientation)
    smap = np.exp2(np.linspace(-3, 1, g.shape[-1], dtype=np.float32))[None].repeat(g.shape[-2], 0)
    full, lafs, radii = cutter(g, kps, smap)
    assert radii.min() == 16 and radii.max() > 64
    idx = torch.arange(3, len(kps), 5)
    sub, sub_lafs = cutter.patches_from_radii(g, kps[idx], radii[idx])
    torch.testing.assert_close(sub, full[idx], atol=1e-6, rtol=0)
    torch.testing.assert_close(sub_lafs, lafs[:, idx])


def test_default_batch_size():
    assert 64 <= default_batch_size("cpu") <= 256
    assert default_batch_size("cuda") >= 1024


@pytest.fixture(scope="module")
def tiny_models():
    from localscale.models import LocalScaleNet, ScaleNet

    torch.manual_seed(0)
    return LocalScaleNet(width=0.125, image_size=64).eval(), ScaleNet(width=0.125, image_size=64).eval()


@pytest.fixture(scope="module")
def tiny_seqs(tmp_path_factory, photos):
    from localscale.evaluation import make_sequences

    root = tmp_path_factory.mktemp("seqs")
    make_sequences([photos["astronaut"], photos["coffee"]], root, num_images=3, size=160, seed=1)
    return root


def test_evaluation_sharing_gives_the_per_method_results(tiny_seqs, tiny_models):
    """``evaluate`` reuses keypoints, encodings, predictions and descriptors between methods;
    its records must equal each method computed on its own."""
    from localscale.evaluation import evaluate, load_hpatches, make_pairs

    local, glob = tiny_models
    methods = ["none", "global", "local", "fused", "gt", "gt_gated"]
    pairs = make_pairs(load_hpatches(tiny_seqs))
    res = evaluate(
        pairs, methods, "hardnet", local, glob, None, progress=False, descriptor="sift", num_features=150, gate=NO_GATE
    )
    recs = {(r["pair"], r["method"]): r for r in res["records"]}
    desc = SIFTPatchDescriptor().eval()
    cutter = ScaleCorrectedPatches()
    corrected = 0
    for p in pairs:
        a, b = load_image(p.image_a), load_image(p.image_b)
        ga, gb = image_to_gray_tensor(a), image_to_gray_tensor(b)
        ka, kb = HessianDetector(150)(ga)[0], HessianDetector(150)(gb)[0]
        for m in methods:
            if m == "gt_gated":
                sa, sb = NO_GATE.apply_pair(*scale_maps_for_pair(a, b, "gt", p.H))
            else:
                sa, sb = scale_maps_for_pair(a, b, m, p.H, local, glob, NO_GATE)
            corrected += sa is not None
            da = desc.describe(cutter(ga, ka, sa)[0])
            db = desc.describe(cutter(gb, kb, sb)[0])
            _, idx = match_descriptors(da, db)
            err = reprojection_errors(ka.numpy(), kb.numpy(), idx.numpy(), p.H)
            r = recs[(p.name, m)]
            assert r["num_matches"] == len(idx), (p.name, m)
            assert r["num_correct_5px"] == int((err < 5).sum()), (p.name, m)
    assert corrected >= 4 * len(pairs)


def test_matcher_describes_each_radius_once(tiny_seqs):
    from localscale.io import load_image
    from localscale.matching.matcher import Matcher

    path = sorted(tiny_seqs.glob("*/1.png"))[0]
    img = load_image(path)
    m = Matcher(MatchConfig(descriptor="sift", num_features=120))
    f0 = m.extract(img, None, key=str(path))
    n = len(f0)
    assert m.described == n
    smap = np.full(img.shape[:2], 0.5, np.float32)
    smap[:, : img.shape[1] // 2] = 2.0  # left half S > 1: base radius, reused
    f1 = m.extract(img, smap, key=str(path))
    kps = torch.from_numpy(f0.keypoints)
    left = kps[:, 0] < img.shape[1] / 2 - 2
    right = kps[:, 0] > img.shape[1] / 2 + 2
    assert n < m.described < 2 * n
    torch.testing.assert_close(f1.descriptors[left], f0.descriptors[left])
    g = image_to_gray_tensor(img)
    direct = SIFTPatchDescriptor().eval().describe(ScaleCorrectedPatches()(g, kps, smap)[0])
    torch.testing.assert_close(f1.descriptors, direct, atol=1e-5, rtol=0)
    assert not torch.allclose(f1.descriptors[right], f0.descriptors[right])
    before = m.described
    again = m.extract(img, smap, key=str(path))
    m.extract(img, 1.0, key=str(path))
    assert m.described == before and again.seconds > 0  # cached features still carry their cost
    m.extract(img, smap)  # no key: no cache
    assert m.described == before + n


def test_corrections_beat_no_correction_on_the_bundled_pair():
    """On the bundled strong-perspective pair (HardNet, 1000 keypoints) every scale correction
    matches better than none, and the ground-truth map is at least as good as the predicted maps."""
    from localscale.matching import models_for_correction

    a, b = ASSETS / "kodim01_a.jpg", ASSETS / "kodim01_b.jpg"
    H = read_homography(ASSETS / "H_a_b.txt")
    acc = {}
    for corr in ("none", "global", "local", "fused", "gt"):
        lm, gm = models_for_correction(corr)
        acc[corr] = match_pair(a, b, corr, H=H, local_model=lm, global_model=gm).accuracy(5.0)
    assert all(acc[c] > acc["none"] + 0.02 for c in ("global", "local", "fused", "gt")), acc
    assert acc["gt"] >= max(acc["local"], acc["global"]) - 0.02, acc


def test_help_imports_no_heavy_module():
    code = (
        "import sys\nfrom localscale.cli import main\n"
        "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
        "print(sorted(m for m in ('torch', 'kornia', 'cv2', 'matplotlib', 'numpy') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().splitlines()[-1] == "[]", out


def test_lazy_package_names():
    import localscale
    import localscale.features as features

    assert set(features.__all__) <= set(dir(features))
    assert all(getattr(features, n) is not None for n in features.__all__)
    assert localscale.LocalScaleNet.__name__ == "LocalScaleNet"
    with pytest.raises(AttributeError):
        _ = features.no_such_name


def test_benchmark_throughput_code_path_runs_on_cpu(repo_script):
    """``eval/benchmark.py --pairs-per-second`` (the CUDA throughput section) on the CPU: both rates
    positive and finite; the CUDA-only calls are skipped there."""
    bench = repo_script("eval/benchmark.py")
    from localscale.matching.matcher import Matcher
    from localscale.models import LocalScaleNet

    torch.manual_seed(0)
    local = LocalScaleNet(width=0.125, feature_dim=16, image_size=64).eval()
    a, b, H = bench.test_pair((160, 120))
    out = bench.pairs_per_second(a, b, H, local, Matcher(MatchConfig(num_features=100)), "cpu", 3)
    assert out["pairs"] == 3 and out["map_batch"] == 3 and out["device"] == "cpu"
    assert 0 < out["match_pair_local_pairs_per_s"] < float("inf") and 0 < out["scale_map_batched_pairs_per_s"] < float(
        "inf"
    )
