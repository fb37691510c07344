"""HardNet precisions (fp32 / bf16 / int8) and narrower HardNets."""

import pytest
import torch

from localscale.core.errors import CheckpointError, LocalScaleError
from localscale.features import HardNetDescriptor, ScaleCorrectedPatches, image_to_gray_tensor
from localscale.features.descriptors import SlimHardNet
from localscale.features.detector import HessianDetector
from localscale.features.quantization import OBSERVED, calibrate_int8, int8_available
from localscale.matching.config import MatchConfig
from localscale.matching.matcher import Matcher

needs_int8 = pytest.mark.skipif(not int8_available(), reason="no x86 quantised engine in this PyTorch")


@pytest.fixture(scope="module")
def real_patches(photos):
    """Hessian keypoint patches of two scikit-image photos the descriptor never saw."""
    out = []
    for name in ("astronaut", "coffee"):
        gray = image_to_gray_tensor(photos[name])
        kps = HessianDetector(400)(gray)[0]
        out.append(ScaleCorrectedPatches()(gray, kps, None)[0])
    return torch.cat(out)


@needs_int8
def test_shipped_int8_agrees_with_fp32_on_real_patches(real_patches):
    model = HardNetDescriptor.from_pretrained()
    assert set(model.int8_ranges) == set(OBSERVED)
    assert model.resolved_precision("cpu") == "int8" and model.resolved_precision("cuda") == "fp32"
    d8 = model.describe(real_patches)
    d32 = model.set_precision("fp32").describe(real_patches)
    assert not torch.equal(d8, d32)  # the int8 path really ran
    assert torch.allclose(d8.norm(dim=1), torch.ones(len(d8)), atol=1e-4)
    err = (d8 - d32).norm(dim=1)
    assert err.mean() < 0.06 and err.quantile(0.99) < 0.2, (err.mean(), err.quantile(0.99))
    # each int8 descriptor finds its own fp32 descriptor as nearest neighbour among all patches
    assert ((d8 @ d32.T).argmax(1) == torch.arange(len(d8))).float().mean() > 0.97


def test_bf16_close_to_fp32(real_patches):
    model = HardNetDescriptor.from_pretrained(precision="fp32")
    d32 = model.describe(real_patches[:200])
    d16 = model.set_precision("bf16").describe(real_patches[:200])
    assert d16.dtype == torch.float32 and (d16 - d32).norm(dim=1).mean() < 0.05


@needs_int8
def test_calibration_snapshot_save_and_reload(real_patches, tmp_path):
    torch.manual_seed(0)
    model = HardNetDescriptor((8, 16, 32)).eval()
    with pytest.raises(LocalScaleError, match="int8 activation ranges"):
        model.set_precision("int8")
    model.calibrate_int8(real_patches[:300])
    x = real_patches[300:500]
    d8, d32 = model.set_precision("int8").describe(x), model.set_precision("fp32").describe(x)
    assert (d8 - d32).norm(dim=1).mean() < 0.1
    model.save(tmp_path / "w.pt", half=False)
    loaded = HardNetDescriptor.from_pretrained(tmp_path / "w.pt")
    assert loaded.widths == (8, 16, 32) and loaded.int8_ranges == model.int8_ranges
    assert torch.allclose(loaded.describe(x), model.set_precision("int8").describe(x), atol=1e-5)
    # train() drops the quantised snapshot: changed weights reach the int8 path
    before = model.describe(x)
    model.train()
    with torch.no_grad():
        model.net.features[0].weight.mul_(-1)
    assert not torch.allclose(model.eval().describe(x), before, atol=1e-3)


def test_bad_precision_and_ranges(tmp_path):
    with pytest.raises(LocalScaleError, match="precision must be one of"):
        HardNetDescriptor(precision="int4")
    with pytest.raises(LocalScaleError, match="descriptor_precision"):
        MatchConfig(descriptor_precision="fp16").check()
    model = HardNetDescriptor((8, 16, 32))
    model.int8_ranges = {name: [0.1, 0, 0, 127] for name in OBSERVED}
    model.save(tmp_path / "ok.pt")
    assert HardNetDescriptor.from_pretrained(tmp_path / "ok.pt").int8_ranges is not None
    for bad in ({"quant": [-1.0, 0, 0, 127]}, {name: ["x", 0, 0, 127] for name in OBSERVED}):
        model.int8_ranges = bad
        model.save(tmp_path / "bad.pt")
        with pytest.raises(CheckpointError, match="int8"):
            HardNetDescriptor.from_pretrained(tmp_path / "bad.pt")
    ckpt = torch.load(tmp_path / "ok.pt", weights_only=True)
    ckpt["widths"] = [8, 16]
    torch.save(ckpt, tmp_path / "widths.pt")
    with pytest.raises(CheckpointError, match="widths"):
        HardNetDescriptor.from_pretrained(tmp_path / "widths.pt")


def test_slim_layout_loads_hardnet_weights():
    torch.manual_seed(0)
    full = HardNetDescriptor(precision="fp32").eval()
    slim = SlimHardNet((32, 64, 128), dropout=0.3).eval()
    slim.load_state_dict(full.net.state_dict(), strict=True)
    x = torch.rand(6, 1, 32, 32)
    with torch.no_grad():
        assert torch.allclose(slim(x), full(x), atol=1e-4)


@needs_int8
def test_matcher_applies_the_configured_precision():
    assert Matcher(MatchConfig(descriptor_precision="fp32")).extractor.descriptor.resolved_precision() == "fp32"
    assert Matcher(MatchConfig()).extractor.descriptor.resolved_precision() == "int8"


@needs_int8
def test_calibrate_rejects_empty():
    with pytest.raises(LocalScaleError, match="calibration"):
        calibrate_int8(HardNetDescriptor((8, 16, 32)).net, torch.zeros(0, 1, 32, 32))
