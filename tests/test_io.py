"""Bad-input suite: every case gives a one-line LocalScaleError (or documented handling)."""

import struct
import zlib

import cv2
import numpy as np
import pytest

from localscale import HomographyError, ImageError
from localscale.io import MAX_PIXELS, load_image, read_homography


@pytest.fixture
def png(tmp_path, photos):
    p = tmp_path / "ok.png"
    cv2.imwrite(str(p), photos["coffee"][..., ::-1])
    return p


def one_line(excinfo):
    msg = str(excinfo.value)
    assert "\n" not in msg
    return msg


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(ImageError) as e:
        load_image(tmp_path / "none.jpg")
    assert "file not found" in one_line(e)
    with pytest.raises(ImageError) as e:
        load_image(tmp_path)
    assert "is a directory" in one_line(e)


def test_zero_byte_and_truncated_files(tmp_path, png, photos):
    z = tmp_path / "zero.png"
    z.write_bytes(b"")
    with pytest.raises(ImageError) as e:
        load_image(z)
    assert "empty file" in one_line(e)
    t = tmp_path / "trunc.png"
    t.write_bytes(png.read_bytes()[:300])
    with pytest.raises(ImageError) as e:
        load_image(t)
    assert "cannot decode" in one_line(e)
    jpg = tmp_path / "ok.jpg"
    cv2.imwrite(str(jpg), photos["coffee"])
    tj = tmp_path / "trunc.jpg"
    tj.write_bytes(jpg.read_bytes()[:200])
    with pytest.raises(ImageError) as e:
        load_image(tj)
    assert "cannot decode" in one_line(e)
    garbage = tmp_path / "garbage.jpg"
    garbage.write_bytes(b"not an image at all" * 10)
    with pytest.raises(ImageError):
        load_image(garbage)


def test_gray_rgba_and_16bit_are_converted(tmp_path, photos):
    rgb = photos["coffee"]
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    cv2.imwrite(str(tmp_path / "g.png"), gray)
    g = load_image(tmp_path / "g.png")
    assert g.shape == rgb.shape and g.dtype == np.uint8 and (g[..., 0] == g[..., 2]).all()
    rgba = np.dstack([rgb[..., ::-1], np.full(rgb.shape[:2], 128, np.uint8)])
    cv2.imwrite(str(tmp_path / "a.png"), rgba)
    with pytest.warns(UserWarning, match="alpha channel dropped"):
        a = load_image(tmp_path / "a.png")
    assert np.array_equal(a, rgb)
    cv2.imwrite(str(tmp_path / "16.png"), (rgb[..., ::-1].astype(np.uint16) * 257))
    with pytest.warns(UserWarning, match="16-bit"):
        s = load_image(tmp_path / "16.png")
    assert np.array_equal(s, rgb)


def test_tiny_images_are_refused(tmp_path):
    for side in (1, 10):
        p = tmp_path / f"{side}.png"
        cv2.imwrite(str(p), np.zeros((side, side, 3), np.uint8))
        with pytest.raises(ImageError) as e:
            load_image(p)
        assert "smaller than the minimum" in one_line(e)


def test_huge_header_is_refused_before_decoding(tmp_path, png):
    data = bytearray(png.read_bytes())
    ihdr = data.index(b"IHDR")
    data[ihdr + 4 : ihdr + 12] = struct.pack(">II", 20000, 20000)
    crc = zlib.crc32(bytes(data[ihdr : ihdr + 17])) & 0xFFFFFFFF
    data[ihdr + 17 : ihdr + 21] = struct.pack(">I", crc)
    p = tmp_path / "huge.png"
    p.write_bytes(bytes(data))
    with pytest.raises(ImageError) as e:
        load_image(p)
    assert "20000x20000" in one_line(e) and f"{MAX_PIXELS / 1e6:.0f} MP" in str(e.value)


def test_arrays_nan_dtype_shape():
    with pytest.raises(ImageError, match="NaN or inf"):
        load_image(np.full((32, 32, 3), np.nan, np.float32))
    with pytest.raises(ImageError, match=r"must be in \[0, 1\]"):
        load_image(np.full((32, 32, 3), 3.0, np.float32))
    with pytest.raises(ImageError, match="unsupported dtype"):
        load_image(np.zeros((32, 32, 3), np.int64))
    with pytest.raises(ImageError, match="expected H x W"):
        load_image(np.zeros((32, 32, 5), np.uint8))
    f = load_image(np.full((32, 32), 0.5, np.float32))
    assert f.shape == (32, 32, 3) and f[0, 0, 0] == 128


def test_homography_files(tmp_path):
    good = tmp_path / "H"
    np.savetxt(good, np.eye(3) * 2)
    assert np.allclose(read_homography(good), np.eye(3) * 2)
    bad = tmp_path / "H_shape"
    np.savetxt(bad, np.eye(2))
    with pytest.raises(HomographyError, match="expected a 3x3 matrix"):
        read_homography(bad)
    sing = tmp_path / "H_sing"
    np.savetxt(sing, np.ones((3, 3)))
    with pytest.raises(HomographyError, match="singular"):
        read_homography(sing)
    txt = tmp_path / "H_txt"
    txt.write_text("a b c\n1 2 3\n4 5 6\n")
    with pytest.raises(HomographyError, match="not a text matrix"):
        read_homography(txt)
    with pytest.raises(HomographyError, match="not found"):
        read_homography(tmp_path / "nope")
    nan = tmp_path / "H_nan"
    nan.write_text("1 0 0\n0 nan 0\n0 0 1\n")
    with pytest.raises(HomographyError, match="NaN"):
        read_homography(nan)


def _tagged(path, stored: np.ndarray, orientation: int):
    """Write ``stored`` (RGB) to ``path`` (TIFF or JPEG, by suffix) with orientation tag ``orientation``."""
    from PIL import Image

    im = Image.fromarray(stored)
    if path.suffix == ".tif":
        im.save(path, "TIFF", tiffinfo={0x0112: orientation})
    else:
        exif = Image.Exif()
        exif[0x0112] = orientation
        im.save(path, "JPEG", quality=95, exif=exif.tobytes())
    return path


@pytest.mark.parametrize("suffix", [".tif", ".jpg"])
@pytest.mark.parametrize("orientation", range(1, 9))
def test_orientation_tag_is_applied_exactly_once(tmp_path, photos, suffix, orientation):
    """TIFF (OpenCV's decoder turns it) and JPEG EXIF (decoded as stored, turned by us) come out
    as PIL's ``exif_transpose`` shows them: turned once, not twice or not at all."""
    from PIL import Image, ImageOps

    from localscale.io import image_shape

    stored = cv2.resize(photos["astronaut"], (96, 64), interpolation=cv2.INTER_AREA)  # 64 x 96: not square
    p = _tagged(tmp_path / f"o{orientation}{suffix}", stored, orientation)
    with Image.open(p) as im:
        assert im.getexif().get(0x0112) == orientation
        expected = np.asarray(ImageOps.exif_transpose(im).convert("RGB"))
    assert expected.shape[:2] == ((96, 64) if orientation >= 5 else (64, 96))
    got = load_image(p)
    assert got.shape == expected.shape and image_shape(p) == got.shape[:2]
    diff = np.abs(got.astype(int) - expected.astype(int))
    if suffix == ".tif":
        assert diff.max() == 0
    else:  # two JPEG decoders: small rounding differences only
        assert diff.mean() < 2, diff.mean()


def test_predict_on_a_tagged_tiff_gives_the_upright_map(tmp_path, photos):
    from localscale.cli import main

    stored = cv2.resize(photos["astronaut"], (96, 64), interpolation=cv2.INTER_AREA)
    a = _tagged(tmp_path / "a.tif", stored, 6)
    b = tmp_path / "b.png"
    cv2.imwrite(str(b), stored[..., ::-1])
    assert main(["predict", str(a), str(b), "-o", str(tmp_path / "out")]) == 0
    assert np.load(tmp_path / "out" / "a_b_scale.npy").shape == (96, 64)


# ---------------------------------------------------------------- float TIFF, 16 bit, thin strips, damaged files


def _smooth(h: int, w: int, seed: int = 0) -> np.ndarray:
    """``h x w x 3`` float64 in [0, 1], smooth (a photo-like test image)."""
    rng = np.random.default_rng(seed)
    small = rng.random((max(2, h // 8), max(2, w // 8), 3))
    return np.clip(cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC), 0, 1)


@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64])
@pytest.mark.parametrize("gray", [False, True])
@pytest.mark.parametrize("top", [1.0, 255.0])
def test_float_tiffs_are_decoded(tmp_path, dtype, gray, top):
    tifffile = pytest.importorskip("tifffile")
    img = _smooth(48, 64)
    img = img[..., 0] if gray else img
    p = tmp_path / "f.tif"
    tifffile.imwrite(p, (img * top).astype(dtype), photometric="minisblack" if gray else "rgb")
    stored = (img * top).astype(dtype).astype(np.float64) / top  # what the file holds, in [0, 1]
    want = np.repeat(stored[..., None], 3, 2) if gray else stored
    got = load_image(p)
    assert got.dtype == np.uint8 and got.shape == (48, 64, 3)
    assert np.abs(got.astype(float) - want * 255).max() <= 0.5 + 1e-6
    precise = load_image(p, precise=True)
    assert precise.dtype == np.float32 and np.abs(precise - want).max() < 1e-6


@pytest.mark.parametrize(
    "bad, words",
    [
        (np.nan, "NaN or inf"),
        (np.inf, "NaN or inf"),
        (-5.0, "expected [0, 1] or [0, 255]"),
        (300.0, "expected [0, 1] or [0, 255]"),
    ],
)
def test_float_tiff_with_bad_values_is_refused(tmp_path, bad, words):
    tifffile = pytest.importorskip("tifffile")
    img = _smooth(32, 32).astype(np.float32)
    img[5, 7, 1] = bad
    p = tmp_path / "bad.tif"
    tifffile.imwrite(p, img, photometric="rgb")
    with pytest.raises(ImageError) as e:
        load_image(p)
    assert words in one_line(e)


def test_16bit_images_reach_the_network_at_full_precision(tmp_path):
    """16-bit PNG/TIFF: uint8 for the detectors (x / 257), float32 x / 65535 for the networks; the
    network's input tensor holds the 16-bit values, not their 8-bit rounding."""
    from localscale import LocalScaleNet

    rng = np.random.default_rng(3)
    img16 = rng.integers(0, 65536, (64, 64, 3), dtype=np.uint16)
    model = LocalScaleNet(width=0.125, feature_dim=16, image_size=64)  # 64 x 64: no resize in the letterbox
    for suffix in (".png", ".tif"):
        p = tmp_path / f"x{suffix}"
        cv2.imwrite(str(p), img16[..., ::-1])
        with pytest.warns(UserWarning, match="16-bit"):
            assert np.array_equal(load_image(p), (img16 / 257.0).round().astype(np.uint8))
        precise = load_image(p, precise=True)
        assert precise.dtype == np.float32 and np.array_equal(precise, img16.astype(np.float32) / 65535)
        x, _ = model.prepare(p)
        assert torch_allclose(x[0].permute(1, 2, 0).numpy(), img16 / 65535.0, 1e-6)
        rounded = np.abs(x[0].numpy() * 255 - np.round(x[0].numpy() * 255))
        assert rounded.max() > 0.4  # values between the 8-bit levels are kept
    eight = tmp_path / "8.png"
    cv2.imwrite(str(eight), (img16 // 257).astype(np.uint8)[..., ::-1])
    x8, _ = model.prepare(eight)  # 8-bit input: as before, x / 255
    assert torch_allclose(x8[0].permute(1, 2, 0).numpy(), (img16 // 257) / 255.0, 1e-6)


def torch_allclose(a, b, tol) -> bool:
    return bool(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)).max() <= tol)


@pytest.mark.parametrize("shape", [(16, 4000), (4000, 16), (40, 4000), (4000, 40)])
def test_thin_strips_are_images(tmp_path, shape):
    from localscale.io import image_shape, load_image_reduced

    p = tmp_path / "strip.png"
    cv2.imwrite(str(p), (_smooth(*shape) * 255).astype(np.uint8))
    assert load_image(p).shape == (*shape, 3) and image_shape(p) == shape
    small, full = load_image_reduced(p, "strip", 256)  # decoded at 1/8: the size check is the file's
    assert full == shape and max(small.shape[:2]) == 500
    thinner = tmp_path / "thinner.png"
    cv2.imwrite(str(thinner), (_smooth(15, 4000) * 255).astype(np.uint8))
    with pytest.raises(ImageError, match="smaller than the minimum"):
        load_image(thinner)


def _damaged_jpeg(path, claimed=(9999, 9999)):
    """A JPEG whose header declares ``claimed`` (width, height) but whose data holds a 320 x 214 image."""
    _, buf = cv2.imencode(".jpg", (_smooth(214, 320) * 255).astype(np.uint8))
    data = bytearray(buf.tobytes())
    i = data.index(b"\xff\xc0")
    data[i + 5 : i + 9] = struct.pack(">HH", claimed[1], claimed[0])
    path.write_bytes(bytes(data))
    return path


def test_damaged_jpeg_is_refused_unless_accepted(tmp_path):
    from localscale.io import accepting_damaged, load_image_reduced

    p = _damaged_jpeg(tmp_path / "damaged.jpg")
    with pytest.raises(ImageError) as e:
        load_image_reduced(p, "image A", 1000)
    msg = one_line(e)
    assert "damaged file" in msg and "9999x9999" in msg and "premature end" in msg
    with pytest.warns(UserWarning, match="premature end"):
        _, full = load_image_reduced(p, "image A", 1000, accept_damaged=True)
    assert full == (9999, 9999)
    with accepting_damaged(), pytest.warns(UserWarning, match="premature end"):
        assert load_image_reduced(p, "image A", 1000)[1] == (9999, 9999)
    with pytest.raises(ImageError, match="damaged file"):  # the setting ends with the block
        load_image_reduced(p, "image A", 1000)
