"""Batched tensor API: ``predict_batch`` equals per-pair ``predict``, on every available device."""

import cv2
import numpy as np
import pytest
import torch

from localscale import ImageError, LocalScaleNet, ScaleNet

TINY = dict(width=0.125, feature_dim=16, image_size=64)
DEVICES = [
    "cpu",
    pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")),
]


def _batch(photos, names, size):
    """``B x 3 x H x W`` float tensor in [0, 1] (size = (W, H)) from scikit-image photos."""
    imgs = [
        cv2.resize(
            photos[n] if photos[n].ndim == 3 else np.repeat(photos[n][..., None], 3, 2),
            size,
            interpolation=cv2.INTER_AREA,
        )
        for n in names
    ]
    return torch.from_numpy(np.stack(imgs)).permute(0, 3, 1, 2).float() / 255


@pytest.fixture(scope="module")
def local_full():
    """A tiny Local-ScaleNet with every output: cues, visibility and a reliability calibration."""
    torch.manual_seed(0)
    return LocalScaleNet(**TINY, topk=4, warp_features=True, visibility=True, calibration=(0.1, 2.0, 1.5, -0.5)).eval()


@pytest.mark.parametrize("device", DEVICES)
def test_local_predict_batch_equals_predict(local_full, photos, device):
    model = local_full.to(device)
    a = _batch(photos, ["astronaut", "coffee", "chelsea"], (150, 100)).to(device)  # landscape A
    b = _batch(photos, ["coffee", "rocket", "camera"], (90, 120)).to(device)  # portrait B
    out = model.predict_batch(a, b)
    assert out.scale.shape == out.confidence.shape == out.visible.shape == out.reliability.shape == (3, 100, 150)
    assert out.scale.device.type == device and out.probs.shape == (3, 13, 8, 8)
    for i in range(3):
        ref = model.predict(a[i], b[i], anchor=False)
        for key in ("scale", "confidence", "visible", "reliability"):
            np.testing.assert_allclose(getattr(out, key)[i].cpu().numpy(), getattr(ref, key), atol=1e-4, err_msg=key)
    model.to("cpu")


def test_local_predict_batch_numpy_in_numpy_out_and_chunks(local_full, photos):
    a = _batch(photos, ["astronaut", "coffee"], (80, 70))
    b = _batch(photos, ["chelsea", "rocket"], (96, 64))
    out = local_full.predict_batch(a.numpy(), b.numpy(), batch_size=1)
    assert isinstance(out.scale, np.ndarray) and out.scale.shape == (2, 70, 80) and len(out) == 2
    ref = local_full.predict_batch(a, b)
    np.testing.assert_allclose(out.scale, ref.scale.numpy(), atol=1e-4)
    # uint8 input is the same images
    u8 = local_full.predict_batch((a * 255).round().byte(), (b * 255).round().byte())
    np.testing.assert_allclose(u8.scale.numpy(), ref.scale.numpy(), atol=1e-4)
    # one unbatched pair: no batch axis
    single = local_full.predict_batch(a[0], b[0])
    assert single.scale.shape == (70, 80)
    np.testing.assert_allclose(single.scale.numpy(), ref.scale[0].numpy(), atol=1e-4)


def test_local_predict_batch_letterbox_follows_the_convention(local_full, photos):
    """B enlarged 2x must give a 2x larger scale, as with ``predict``."""
    a = _batch(photos, ["coffee"], (120, 80))
    b = _batch(photos, ["chelsea"], (90, 60))
    b2 = torch.nn.functional.interpolate(b, scale_factor=2, mode="bilinear", align_corners=False)
    s1 = local_full.predict_batch(a, b).scale
    s2 = local_full.predict_batch(a, b2).scale
    assert float((s2 / s1).median()) == pytest.approx(2.0, rel=0.05)


def test_hard_readout_and_a_model_without_extra_outputs(photos):
    torch.manual_seed(1)
    model = LocalScaleNet(**TINY).eval()
    a = _batch(photos, ["astronaut", "coffee"], (64, 64))
    b = _batch(photos, ["rocket", "chelsea"], (100, 64))
    out = model.predict_batch(a, b, hard=True)
    assert out.visible is None and out.reliability is None
    for i in range(2):
        np.testing.assert_allclose(
            out.scale[i].numpy(), model.predict(a[i], b[i], hard=True, anchor=False).scale, atol=1e-4
        )


def test_predict_batch_refuses_bad_batches(local_full, photos):
    a = _batch(photos, ["astronaut", "coffee"], (64, 64))
    with pytest.raises(ValueError, match="2 images A but 1 images B"):
        local_full.predict_batch(a, a[:1])
    with pytest.raises(ImageError, match="B x 3 x H x W"):
        local_full.predict_batch(a[:, :2], a[:, :2])
    with pytest.raises(ImageError, match=r"\[0\].*\[0, 1\]"):
        local_full.predict_batch(a * 3, a)
    with pytest.raises(ImageError, match="tensor or a numpy array"):
        local_full.predict_batch([a[0]], [a[0]])


@pytest.mark.parametrize("device", DEVICES)
def test_global_predict_batch_equals_predict(photos, device):
    torch.manual_seed(0)
    model = ScaleNet(**TINY, topk=4, warp_features=True).eval().to(device)
    a = _batch(photos, ["astronaut", "coffee", "chelsea"], (120, 90)).to(device)
    b = _batch(photos, ["coffee", "rocket", "camera"], (70, 100)).to(device)
    s = model.predict_batch(a, b)
    assert s.shape == (3,) and s.device.type == device
    ref = [model.predict(a[i], b[i], turns=False).scale for i in range(3)]
    np.testing.assert_allclose(s.cpu().numpy(), ref, rtol=1e-4)
    assert isinstance(model.predict_batch(a.cpu().numpy(), b.cpu().numpy()), np.ndarray)
