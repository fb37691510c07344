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
    data[ihdr + 4:ihdr + 12] = struct.pack(">II", 20000, 20000)
    crc = zlib.crc32(bytes(data[ihdr:ihdr + 17])) & 0xFFFFFFFF
    data[ihdr + 17:ihdr + 21] = struct.pack(">I", crc)
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

    stored = cv2.resize(photos["astronaut"], (96, 64), interpolation=cv2.INTER_AREA)   # 64 x 96: not square
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
    else:   # two JPEG decoders: small rounding differences only
        assert diff.mean() < 2, diff.mean()


def test_predict_on_a_tagged_tiff_gives_the_upright_map(tmp_path, photos):
    from localscale.cli import main

    stored = cv2.resize(photos["astronaut"], (96, 64), interpolation=cv2.INTER_AREA)
    a = _tagged(tmp_path / "a.tif", stored, 6)
    b = tmp_path / "b.png"
    cv2.imwrite(str(b), stored[..., ::-1])
    assert main(["predict", str(a), str(b), "-o", str(tmp_path / "out")]) == 0
    assert np.load(tmp_path / "out" / "a_b_scale.npy").shape == (96, 64)
