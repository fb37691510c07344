"""Large images: reduced decoding, band-wise full-resolution maps, and memory that grows with the
image by a few bytes per pixel (predict) or not at all (match, show, scale)."""

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest
import torch
from PIL import Image

from localscale.io import image_shape, load_image, load_image_reduced, load_working_image, reduction_factor
from localscale.io.preprocess import make_letterbox
from localscale.maps import GridMaps
from localscale.models import LocalScaleNet
from localscale.models.base import upsample_to_original


@pytest.mark.parametrize("shape", [(301, 457), (457, 301), (40, 5000), (192, 192), (17, 23), (3000, 2000)])
def test_band_readout_equals_the_whole_map_readout(shape):
    lb = make_letterbox(*shape, 192)
    grid = torch.randn(3, 24, 24, generator=torch.Generator().manual_seed(sum(shape)))
    want = upsample_to_original(grid, lb).numpy()
    maps = GridMaps(grid, lb, [np.exp, None, None])
    assert np.allclose(maps.full(0), np.exp(want[0]), rtol=1e-4)  # float32 rounding, amplified by exp
    assert np.allclose(maps.full(1), want[1], atol=1e-5)
    rows = np.concatenate([band for _, band in maps.bands(1, max_elements=997)])  # odd band size
    assert rows.shape == shape and np.allclose(rows, want[1], atol=1e-5)
    for step in (2, 3, 7):
        assert np.allclose(maps.sampled(1, step), want[1][::step, ::step], atol=1e-5)
    k = maps.sample_step(1000)
    assert np.ceil(shape[0] / k) * np.ceil(shape[1] / k) <= 1000
    assert k == 1 or np.ceil(shape[0] / (k - 1)) * np.ceil(shape[1] / (k - 1)) > 1000


def test_prediction_maps_are_read_out_on_use(photos):
    net = LocalScaleNet.from_pretrained()
    a = cv2.resize(photos["astronaut"], (640, 480), interpolation=cv2.INTER_AREA)
    b = cv2.resize(a[60:420, 80:560], (640, 480), interpolation=cv2.INTER_LINEAR)
    pred = net.predict(a, b)
    assert pred._full == {}  # nothing full-size until asked for
    s = pred.sampled("scale", max_pixels=20_000)
    assert pred._full == {} and s.shape == (120, 160)  # every 4th pixel
    assert np.allclose(s, pred.scale[::4, ::4], rtol=1e-5)
    batch = net.predict_batch(a[None].transpose(0, 3, 1, 2), b[None].transpose(0, 3, 1, 2))
    pred = net.predict(a, b, anchor=False)  # the batch is the one-pass map
    assert np.allclose(pred.scale, batch.scale[0], rtol=1e-4)
    assert np.allclose(pred.confidence, batch.confidence[0], atol=1e-4)
    assert np.allclose(pred.visible, batch.visible[0], atol=1e-4)
    assert np.median(pred.scale) > 1.1  # B is a zoom into A: content looks bigger in B


def _jpeg(path, img, **kw):
    Image.fromarray(img).save(path, quality=92, **kw)
    return path


def test_large_jpeg_is_decoded_reduced_and_keeps_its_size(tmp_path, photos):
    big = cv2.resize(photos["coffee"], (2400, 1600), interpolation=cv2.INTER_CUBIC)
    p = _jpeg(tmp_path / "big.jpg", big)
    assert reduction_factor(1600, 2400, 768) == 2 and reduction_factor(1600, 2400, 500) == 4
    assert reduction_factor(1600, 2400, 100) == 8 and reduction_factor(1600, 2400, None) == 1
    small, full = load_image_reduced(p, min_long_side=500)
    assert full == (1600, 2400) == image_shape(p) and small.shape == (400, 600, 3)
    ref = cv2.resize(load_image(p), (600, 400), interpolation=cv2.INTER_AREA)
    assert np.abs(small.astype(int) - ref).mean() < 2.0
    png = tmp_path / "big.png"
    cv2.imwrite(str(png), big[..., ::-1])
    small_png, full_png = load_image_reduced(png, min_long_side=500)
    assert full_png == (1600, 2400) and small_png.shape == (400, 600, 3)
    assert np.abs(small_png.astype(int) - ref).mean() < 2.0
    arr, full_arr = load_image_reduced(big, min_long_side=500)  # arrays are not reduced
    assert arr.shape == big.shape and full_arr == (1600, 2400)


@pytest.mark.parametrize("orientation", [3, 6, 8])
def test_reduced_decoding_keeps_the_exif_orientation(tmp_path, photos, orientation):
    stored = cv2.resize(photos["coffee"], (2400, 1600), interpolation=cv2.INTER_CUBIC)
    exif = Image.Exif()
    exif[0x0112] = orientation
    p = _jpeg(tmp_path / f"o{orientation}.jpg", stored, exif=exif)
    upright = load_image(p)
    small, full = load_image_reduced(p, min_long_side=500)
    assert full == upright.shape[:2]
    assert small.shape[:2] == (upright.shape[0] // 4, upright.shape[1] // 4)
    ref = cv2.resize(upright, small.shape[1::-1], interpolation=cv2.INTER_AREA)
    assert np.abs(small.astype(int) - ref).mean() < 2.0


def test_working_image_maps_full_pixels_to_working_pixels(tmp_path, photos):
    big = cv2.resize(photos["rocket"], (3000, 2000), interpolation=cv2.INTER_CUBIC)
    p = _jpeg(tmp_path / "w.jpg", big)
    work, S = load_working_image(p, 1000)
    assert work.shape == (667, 1000, 3)
    corners = np.array([[-0.5, -0.5, 1], [2999.5, 1999.5, 1]]) @ S.T  # pixel-area edges map onto edges
    assert np.allclose(corners[:, :2], [[-0.5, -0.5], [999.5, 666.5]], atol=0.3)
    same, eye = load_working_image(p, 4000)
    assert same.shape == big.shape and np.array_equal(eye, np.eye(3))


def test_prediction_on_a_large_file_matches_the_full_decode(tmp_path, photos):
    net = LocalScaleNet.from_pretrained()
    a = cv2.resize(photos["astronaut"], (3072, 3072), interpolation=cv2.INTER_CUBIC)
    b = cv2.resize(a[400:2700, 300:2600], (3072, 3072), interpolation=cv2.INTER_CUBIC)
    pa, pb = _jpeg(tmp_path / "a.jpg", a), _jpeg(tmp_path / "b.jpg", b)
    from_files = net.predict(pa, pb)  # decoded at 1/4 (768 px)
    from_arrays = net.predict(load_image(pa), load_image(pb))  # full decode
    assert from_files.scale.shape == (3072, 3072)
    ratio = np.exp(np.abs(np.log(from_files.sampled("scale") / from_arrays.sampled("scale"))))
    assert np.median(ratio) < 1.02 and ratio.max() < 1.1


# VmHWM: the peak of this process's own memory (ru_maxrss would include the parent's at fork)
_PEAK = """
import json, re, sys
from localscale.cli import main
rc = main(sys.argv[1:])
hwm = re.search(r"VmHWM:\\s+(\\d+) kB", open("/proc/self/status").read())
print(json.dumps({"rc": rc, "peak_mb": int(hwm.group(1)) / 1024}))
"""


def _peak_mb(*args) -> float:
    r = subprocess.run(
        [sys.executable, "-c", _PEAK, *map(str, args)],
        capture_output=True,
        text=True,
        timeout=600,
        env={**__import__("os").environ, "OMP_NUM_THREADS": "1"},
    )
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])["peak_mb"]


@pytest.fixture(scope="module")
def pair_sizes(tmp_path_factory, photos):
    """The same pair as a 0.3 MP and a 16 MP JPEG."""
    d = tmp_path_factory.mktemp("large")
    a = photos["astronaut"]
    b = cv2.resize(a[60:460, 40:440], (512, 512), interpolation=cv2.INTER_LINEAR)
    out = {}
    for name, side in (("small", 640), ("large", 4000)):
        out[name] = [
            _jpeg(d / f"{name}_{k}.jpg", cv2.resize(img, (side, side), interpolation=cv2.INTER_CUBIC))
            for k, img in (("a", a), ("b", b))
        ]
    return d, out


def test_predict_memory_grows_by_a_few_bytes_per_pixel(pair_sizes):
    d, imgs = pair_sizes
    small = _peak_mb("predict", *imgs["small"], "-o", d / "p_small")
    large = _peak_mb("predict", *imgs["large"], "-o", d / "p_large")
    extra_pixels = 4000 * 4000 - 640 * 640
    bytes_per_pixel = (large - small) * 2**20 / extra_pixels
    assert bytes_per_pixel < 20, f"predict: {bytes_per_pixel:.1f} bytes per extra pixel ({small:.0f} -> {large:.0f} MB)"
    s = np.load(d / "p_large" / "large_a_large_b_scale.npy", mmap_mode="r")
    v = np.load(d / "p_large" / "large_a_large_b_visible.npy", mmap_mode="r")
    assert s.shape == v.shape == (4000, 4000) and s.dtype == v.dtype == np.float32
    assert np.isfinite(s[::50, ::50]).all() and 0 <= v[::50, ::50].min() and v[::50, ::50].max() <= 1


def test_match_and_show_memory_do_not_grow_with_the_image(pair_sizes):
    d, imgs = pair_sizes
    mid = [d / "mid_a.png", d / "mid_b.png"]
    for src, dst in zip(imgs["large"], mid):  # the working resolution itself, as PNG
        cv2.imwrite(str(dst), cv2.resize(cv2.imread(str(src)), (2048, 2048), interpolation=cv2.INTER_AREA))
    base = _peak_mb("match", *mid, "-o", d / "m_mid", "--num-features", 300)
    large = _peak_mb("match", *imgs["large"], "-o", d / "m_large", "--num-features", 300)
    assert large - base < 120, f"match: {base:.0f} MB at 2048 px, {large:.0f} MB at 4000 px"
    m = np.load(d / "m_large" / "matches.npz")
    assert m["keypoints_a"].max() > 2048 and m["keypoints_a"].max() < 4000  # full-image pixels
    show_large = _peak_mb("show", *imgs["large"], "-o", d / "s_large")
    show_mid = _peak_mb("show", *mid, "-o", d / "s_mid")
    assert show_large - show_mid < 120, f"show: {show_mid:.0f} MB at 2048 px, {show_large:.0f} MB at 4000 px"
