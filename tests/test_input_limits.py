"""Image files of unusual sample types (integer TIFFs, HDR float TIFFs) and images the scale networks
cannot answer for (thin strips, tiny images, scales beyond the bins' range): refused or flagged,
never a traceback or a silent answer."""

import os

import cv2
import numpy as np
import pytest

os.environ.setdefault("OMP_NUM_THREADS", "1")

from localscale.cli import main  # noqa: E402
from localscale.core.errors import ImageError  # noqa: E402
from localscale.io import load_image  # noqa: E402

PHOTO = os.path.join(os.path.dirname(__file__), "..", "localscale", "assets", "kodim01_a.jpg")


def _smooth(h: int, w: int, seed: int = 0) -> np.ndarray:
    """``h x w x 3`` float64 in [0, 1], smooth (photo-like)."""
    rng = np.random.default_rng(seed)
    small = rng.random((max(2, h // 8), max(2, w // 8), 3))
    return np.clip(cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC), 0, 1)


def _error_lines(err: str) -> list:
    return [line for line in err.splitlines() if line.strip()]


@pytest.mark.parametrize("dtype", [np.int8, np.int16, np.int32])
@pytest.mark.parametrize("channels", [1, 3])
def test_integer_tiffs_of_unknown_range_are_refused(tmp_path, capsys, dtype, channels):
    img = (_smooth(48, 64) * 100).astype(dtype)
    img = img[..., 0] if channels == 1 else img
    path = tmp_path / "int.tif"
    assert cv2.imwrite(str(path), img) and cv2.imread(str(path), cv2.IMREAD_UNCHANGED).dtype == dtype
    with pytest.raises(ImageError, match=f"samples are {np.dtype(dtype).name}"):
        load_image(path)
    out = tmp_path / "out"
    assert main(["predict", str(path), PHOTO, "-o", str(out)]) == 2
    lines = _error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and lines[0].startswith("error: image A") and "int" in lines[0]
    assert not out.exists()


def test_an_hdr_float_tiff_is_scaled_by_its_bright_end_with_a_warning(tmp_path, capsys):
    """Values in [0, 4] (linear HDR): read as a [0, 255] image it would be black (mean 2 / 255)."""
    hdr = (_smooth(48, 64) * 4).astype(np.float32)
    path = tmp_path / "hdr.tif"
    assert cv2.imwrite(str(path), hdr)
    with pytest.warns(UserWarning, match="high dynamic range"):
        got = load_image(path, precise=True)
    scale = np.percentile(hdr, 99.5)
    assert np.allclose(got, np.clip(hdr[..., ::-1] / scale, 0, 1), atol=1e-6)
    assert got.mean() > 0.3  # not nearly black
    assert main(["scale", str(path), PHOTO]) == 0
    err = capsys.readouterr().err
    assert "UserWarning" not in err
    assert sum(line.startswith("warning: image A") and "high dynamic range" in line for line in err.splitlines()) == 1


def test_a_float_tiff_in_0_255_is_still_divided_by_255(tmp_path):
    img = (_smooth(48, 64, seed=1) * 255).astype(np.float32)
    path = tmp_path / "f255.tif"
    assert cv2.imwrite(str(path), img)
    assert np.allclose(load_image(path, precise=True), img[..., ::-1] / 255, atol=1e-6)


@pytest.fixture(scope="module")
def scalenet():
    from localscale import ScaleNet

    return ScaleNet.from_pretrained()


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    folder = tmp_path_factory.mktemp("limits")
    rng = np.random.default_rng(0)
    made = {
        "flat_strip": np.full((16, 5000, 3), 128, np.uint8),
        "noise_strip": rng.integers(0, 255, (16, 8000, 3), dtype=np.uint8),
        "tiny": rng.integers(0, 255, (16, 16, 3), dtype=np.uint8),
    }
    for name, img in made.items():
        cv2.imwrite(str(folder / f"{name}.png"), img)
    return {name: folder / f"{name}.png" for name in made}


@pytest.mark.parametrize(
    "name, words", [("flat_strip", "thinner than one"), ("noise_strip", "thinner than one"), ("tiny", "too small")]
)
def test_images_the_global_network_cannot_answer_for_are_flagged(scalenet, images, capsys, name, words):
    p = scalenet.predict(images[name], PHOTO)
    assert not p.reliable
    assert any(words in r for r in p.limits) and any("outside the network's range" in r for r in p.limits)
    assert main(["scale", str(images[name]), PHOTO]) == 0
    err = capsys.readouterr().err
    assert any(
        line.startswith("warning: the global scale is unreliable") and words in line for line in err.splitlines()
    )


def test_a_photo_pair_has_no_limits(scalenet):
    b = os.path.join(os.path.dirname(PHOTO), "kodim01_b.jpg")
    p = scalenet.predict(PHOTO, b)
    assert p.limits == [] and p.reliable


def test_the_scale_map_check_names_a_thin_strip(images):
    from localscale import LocalScaleNet
    from localscale.reliability import check_pair

    check = check_pair(LocalScaleNet.from_pretrained(), images["flat_strip"], PHOTO)
    assert not check.reliable and any("thinner than one" in r for r in check.reasons)


def test_scales_beyond_the_bins_are_named():
    from localscale.model_limits import range_reasons

    assert range_reasons(1.0) == [] and range_reasons(0.125) == [] and range_reasons(8.0) == []
    assert "x0.05 is outside" in range_reasons(0.05)[0] and range_reasons(12.0) and range_reasons(float("nan"))


def test_rectify_records_and_warns_about_an_unreliable_scale(images, tmp_path, capsys):
    import json

    out = tmp_path / "out"
    assert main(["rectify", str(images["flat_strip"]), PHOTO, "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert any(
        line.startswith("warning: the global scale is unreliable") and "thinner" in line for line in err.splitlines()
    )
    (record,) = [json.loads(p.read_text()) for p in out.glob("*_rectified.json")]
    assert record["reliable"] is False and any("thinner" in r for r in record["unreliable_because"])
