"""Untrusted input: checkpoints that would run code or are malformed, image files whose
size is unknown or huge, EXIF orientation, and homographies near the numeric limits."""

import os
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch

from localscale.checkpoint import FORMAT_VERSION, read_checkpoint, restore_train_state, save_model, train_state
from localscale.core.errors import CheckpointError
from localscale.features.descriptors import HardNetDescriptor
from localscale.models import LocalScaleNet, load_model

TINY = dict(width=0.125, feature_dim=16, image_size=64)
WEIGHTS = Path(__file__).resolve().parent.parent / "localscale" / "weights"


def _one_line(exc_info) -> str:
    msg = str(exc_info.value)
    assert "\n" not in msg
    return msg


class _WritesMarker:
    """Unpickling this object would create a file (stands for arbitrary code)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (Path.touch, (Path(self.marker),))


@pytest.fixture(scope="module")
def ckpt_path(tmp_path_factory):
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("ck") / "m.pt"
    save_model(LocalScaleNet(**TINY).eval(), path)
    return path


def _variant(ckpt_path, tmp_path, name, edit):
    ck = torch.load(ckpt_path, weights_only=True)
    edit(ck)
    out = tmp_path / name
    torch.save(ck, out)
    return out


# ---------------------------------------------------------------- checkpoints
def test_the_pickled_payload_check_itself_works(tmp_path):
    """Without weights_only the crafted file does create the marker (so the next test means something)."""
    marker = tmp_path / "ran"
    torch.save({"x": _WritesMarker(marker)}, tmp_path / "evil.pt")
    torch.load(tmp_path / "evil.pt", weights_only=False)
    assert marker.exists()


@pytest.mark.parametrize("loader", [load_model, read_checkpoint, HardNetDescriptor.from_pretrained])
def test_checkpoint_with_code_in_meta_is_refused_unrun(ckpt_path, tmp_path, loader):
    marker = tmp_path / "ran"
    evil = _variant(ckpt_path, tmp_path, "evil.pt", lambda ck: ck["meta"].update(x=_WritesMarker(marker)))
    with pytest.raises(CheckpointError, match="contains non-tensor objects") as e:
        loader(evil)
    assert str(evil) in _one_line(e)
    assert not marker.exists()


def test_hardnet_checkpoint_with_code_is_refused_unrun(tmp_path):
    marker = tmp_path / "ran"
    HardNetDescriptor().save(tmp_path / "h.pt", meta={"x": 1})
    ck = torch.load(tmp_path / "h.pt", weights_only=True)
    ck["meta"]["x"] = _WritesMarker(marker)
    torch.save(ck, tmp_path / "h.pt")
    with pytest.raises(CheckpointError, match="non-tensor objects"):
        HardNetDescriptor.from_pretrained(tmp_path / "h.pt")
    assert not marker.exists()


@pytest.mark.parametrize(
    "name,edit,match",
    [
        ("nosd", lambda ck: ck.pop("state_dict"), "has no 'state_dict'"),
        ("sdlist", lambda ck: ck.update(state_dict=[1, 2]), "'state_dict' is a list"),
        (
            "sdvalue",
            lambda ck: ck["state_dict"].update(extra=3.0),
            "'state_dict' entry 'extra' is a float, not a tensor",
        ),
        (
            "version",
            lambda ck: ck.update(localscale_format=FORMAT_VERSION + 1),
            "unsupported checkpoint format version 2",
        ),
        ("version_str", lambda ck: ck.update(localscale_format="1"), "unsupported checkpoint format version '1'"),
        ("noconfig", lambda ck: ck.pop("config"), "no valid 'config'"),
        ("config_key", lambda ck: ck["config"].update(colour=1), "config does not fit LocalScaleNet"),
        ("config_type", lambda ck: ck["config"].update(reduction="abc"), "config does not fit LocalScaleNet"),
        ("config_list", lambda ck: ck.update(config=[1, 2]), "no valid 'config'"),
    ],
)
def test_malformed_checkpoints_give_one_line_errors(ckpt_path, tmp_path, name, edit, match):
    bad = _variant(ckpt_path, tmp_path, f"{name}.pt", edit)
    with pytest.raises(CheckpointError, match=match) as e:
        load_model(bad)
    assert str(bad) in _one_line(e)


def test_hardnet_unknown_format_and_non_tensor_values_are_refused(tmp_path):
    net = HardNetDescriptor()
    net.save(tmp_path / "h.pt")
    ck = torch.load(tmp_path / "h.pt", weights_only=True)
    torch.save({**ck, "localscale_format": 7}, tmp_path / "v7.pt")
    with pytest.raises(CheckpointError, match="unsupported checkpoint format version 7"):
        HardNetDescriptor.from_pretrained(tmp_path / "v7.pt")
    torch.save({"state_dict": {**ck["state_dict"], "bad": "x"}}, tmp_path / "str.pt")
    with pytest.raises(CheckpointError, match="'bad' is a str, not a tensor"):
        HardNetDescriptor.from_pretrained(tmp_path / "str.pt")


def test_plain_pickle_and_garbage_are_one_line_errors(tmp_path):
    import pickle

    (tmp_path / "p.pt").write_bytes(pickle.dumps({"localscale_format": 1}, protocol=4))
    (tmp_path / "g.pt").write_bytes(b"hello, not a checkpoint" * 50)
    for f in ("p.pt", "g.pt"):
        with pytest.raises(CheckpointError, match="cannot read checkpoint") as e:
            read_checkpoint(tmp_path / f)
        _one_line(e)


@pytest.mark.parametrize("name", sorted(p.name for p in WEIGHTS.glob("*.pt")))
def test_shipped_weights_load_with_weights_only(name):
    ck = torch.load(WEIGHTS / name, map_location="cpu", weights_only=True)
    assert ck["localscale_format"] == FORMAT_VERSION and isinstance(ck["meta"], dict)
    assert all(isinstance(v, torch.Tensor) for v in ck["state_dict"].values())


def test_train_state_is_plain_data_and_restores_the_schedule(tmp_path):
    model = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(model.parameters(), lr=1.0)
    sched = torch.optim.lr_scheduler.MultiStepLR(opt, [2, 4, 4], 0.5)
    for _ in range(3):
        model(torch.ones(1, 3)).sum().backward()
        opt.step()
        sched.step()
    state = train_state(opt, sched, 3)
    assert type(state["scheduler"]["milestones"]) is dict  # no Counter stored

    def no_counter(obj):
        if isinstance(obj, Counter):
            return False
        if isinstance(obj, dict):
            return all(no_counter(v) for v in obj.values())
        if isinstance(obj, (list, tuple)):
            return all(no_counter(v) for v in obj)
        return True

    assert no_counter(state)
    torch.save({"train_state": state}, tmp_path / "last.pt")
    loaded = torch.load(tmp_path / "last.pt", weights_only=True)["train_state"]

    opt2 = torch.optim.Adam(torch.nn.Linear(3, 2).parameters(), lr=1.0)
    sched2 = torch.optim.lr_scheduler.MultiStepLR(opt2, [9], 0.5)
    assert restore_train_state(opt2, sched2, loaded) == 3
    assert isinstance(sched2.milestones, Counter) and sched2.milestones == Counter([2, 4, 4])
    lrs = []
    for _ in range(3):
        opt2.step()
        sched2.step()
        lrs.append(opt2.param_groups[0]["lr"])
    assert lrs == pytest.approx([0.125, 0.125, 0.125])  # 1 * 0.5 (step 2) * 0.25 (step 4, twice)


# ---------------------------------------------------------------- image files
import resource  # noqa: E402
import warnings  # noqa: E402

import cv2  # noqa: E402
from PIL import Image, ImageOps  # noqa: E402

from localscale.core.errors import HomographyError, ImageError  # noqa: E402
from localscale.io import load_image, read_homography  # noqa: E402

HUGE_HEADERS = {
    "pfm": b"PF\n20000 20000\n-1.0\n",
    "pam": b"P7\nWIDTH 20000\nHEIGHT 20000\nDEPTH 3\nMAXVAL 255\nTUPLTYPE RGB\nENDHDR\n",
    "hdr": b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\nEXPOSURE=1.0\n\n-Y 20000 +X 20000\n",
}


@pytest.fixture
def no_decode(monkeypatch):
    """Fail the test if load_image hands the file to the decoder."""
    calls = []
    monkeypatch.setattr(cv2, "imdecode", lambda *a, **k: calls.append(a) or None)
    return calls


@pytest.mark.parametrize("fmt", sorted(HUGE_HEADERS))
def test_huge_size_in_a_header_pil_cannot_read_is_refused_undecoded(tmp_path, fmt, no_decode):
    p = tmp_path / f"huge.{fmt}"
    p.write_bytes(HUGE_HEADERS[fmt] + bytes(4096))
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(ImageError, match="20000x20000") as e:
        load_image(p)
    assert "larger than the limit" in _one_line(e) and str(p) in str(e.value)
    assert not no_decode
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0 < 200 * 1024  # KiB: < 200 MB


def test_file_whose_size_is_unreadable_is_refused_undecoded(tmp_path, no_decode):
    p = tmp_path / "mystery.img"
    p.write_bytes(b"\x00\x01 no known image header " * 40)
    no_size = {
        "pfm": b"PF\n-1.0\n",
        "pam": b"P7\nDEPTH 3\nMAXVAL 255\nENDHDR\n",  # right signature, no size
        "hdr": b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\nno resolution line\n",
    }
    for fmt, header in no_size.items():
        (tmp_path / f"bad.{fmt}").write_bytes(header + bytes(100))
    for f in [p] + [tmp_path / f"bad.{fmt}" for fmt in no_size]:
        with pytest.raises(ImageError, match="size cannot be read from the header") as e:
            load_image(f)
        _one_line(e)
    assert not no_decode


@pytest.mark.parametrize("ext", [".pfm", ".pam", ".hdr"])
def test_small_pfm_pam_hdr_files_still_load(tmp_path, ext):
    rng = np.random.default_rng(0)
    img = rng.uniform(0.05, 0.9, (20, 30, 3)).astype(np.float32)
    data = img if ext != ".pam" else (img * 255).astype(np.uint8)
    ok, buf = cv2.imencode(ext, data)
    assert ok
    p = tmp_path / f"small{ext}"
    p.write_bytes(buf.tobytes())
    out = load_image(p)
    assert out.shape == (20, 30, 3) and out.dtype == np.uint8
    want = (img[..., ::-1] * 255).round()
    assert np.abs(out.astype(np.float32) - want).mean() < 3  # RGBE keeps ~8 bits of mantissa


def _exif(orientation: int) -> Image.Exif:
    exif = Image.Exif()
    exif[0x0112] = orientation
    return exif


@pytest.mark.parametrize("orientation", [6, 8])
def test_portrait_jpeg_with_exif_orientation_loads_portrait(tmp_path, photos, orientation):
    stored = cv2.resize(photos["coffee"], (64, 48), interpolation=cv2.INTER_AREA)  # landscape pixels
    p = tmp_path / f"o{orientation}.jpg"
    Image.fromarray(stored).save(p, quality=95, exif=_exif(orientation))
    out = load_image(p)
    assert out.shape == (64, 48, 3)  # portrait, as a viewer shows it
    with Image.open(p) as im:
        upright = np.asarray(ImageOps.exif_transpose(im).convert("RGB"))
    assert upright.shape == out.shape
    assert np.abs(out.astype(int) - upright).mean() < 3
    assert np.abs(out.astype(int) - np.rot90(upright, 2)).mean() > 10  # a rotation is not mistaken


@pytest.mark.parametrize("orientation", range(1, 9))
def test_every_exif_orientation_matches_pil(tmp_path, orientation):
    rng = np.random.default_rng(orientation)
    stored = rng.integers(0, 256, (20, 36, 3), dtype=np.uint8)
    p = tmp_path / f"o{orientation}.png"
    Image.fromarray(stored).save(p, exif=_exif(orientation))
    with Image.open(p) as im:
        im.load()
        want = np.asarray(ImageOps.exif_transpose(im).convert("RGB"))
    assert np.array_equal(load_image(p), want)


def test_decoder_messages_stay_off_the_terminal(tmp_path, photos, capfd):
    img = photos["coffee"][:120, :160, ::-1]
    ok, png = cv2.imencode(".png", img)
    (tmp_path / "t.png").write_bytes(png.tobytes()[: len(png) // 2])
    with pytest.raises(ImageError, match="cannot decode") as e:
        load_image(tmp_path / "t.png")
    _one_line(e)
    ok, jpg = cv2.imencode(".jpg", img)
    bad = jpg.copy()
    bad[len(bad) // 2 : len(bad) // 2 + 40] = 0  # corrupt the entropy-coded data: libjpeg warns, still decodes
    (tmp_path / "c.jpg").write_bytes(bad.tobytes())
    with pytest.warns(UserWarning, match="decoder reported a problem: Corrupt JPEG data"):
        assert load_image(tmp_path / "c.jpg").shape == (120, 160, 3)
    err = capfd.readouterr().err
    assert "WARN" not in err and "Corrupt JPEG" not in err and "libpng" not in err
    import sys

    print("stderr still works", file=sys.stderr)
    os.write(2, b"fd 2 still works\n")
    err = capfd.readouterr().err
    assert "stderr still works" in err and "fd 2 still works" in err


def test_symlink_loop_and_broken_link_are_named(tmp_path):
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    a.symlink_to(b)
    b.symlink_to(a)
    with pytest.raises(ImageError, match="symbolic link loop") as e:
        load_image(a)
    _one_line(e)
    (tmp_path / "dangling.png").symlink_to(tmp_path / "gone.png")
    with pytest.raises(ImageError, match="broken symbolic link"):
        load_image(tmp_path / "dangling.png")


def test_opaque_alpha_is_dropped_silently(tmp_path, photos):
    rgb = photos["coffee"][:64, :80]
    Image.fromarray(rgb).save(tmp_path / "o.gif")  # GIF without transparency
    Image.fromarray(np.dstack([rgb, np.full(rgb.shape[:2], 255, np.uint8)])).save(tmp_path / "o.png")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        gif = load_image(tmp_path / "o.gif")
        png = load_image(tmp_path / "o.png")
        load_image(np.dstack([rgb, np.full(rgb.shape[:2], 255, np.uint8)]))
    assert gif.shape == png.shape == rgb.shape and np.array_equal(png, rgb)
    half = np.dstack([rgb, np.full(rgb.shape[:2], 255, np.uint8)])
    half[0, 0, 3] = 0
    with pytest.warns(UserWarning, match="alpha channel dropped"):
        load_image(half)


# ---------------------------------------------------------------- homographies
@pytest.mark.parametrize(
    "H",
    [
        [[1, 0, 1e4], [0, 1, -1.2e4], [0, 0, 1]],  # translation by ~1e4 px
        [[1e-7, 0, 0], [0, 1e-7, 0], [0, 0, 1]],  # zoom out by 1e7
        [[1e7, 0, 0], [0, 1e7, 0], [0, 0, 1]],  # zoom in by 1e7
        [[0.9, 0.1, 2e4], [-0.1, 0.9, 3e4], [1e-6, 2e-6, 1]],  # far-away projective view
    ],
)
def test_valid_homographies_with_extreme_entries_are_accepted(tmp_path, H):
    H = np.array(H, dtype=np.float64)
    assert np.array_equal(read_homography(H), H)
    np.savetxt(tmp_path / "H", H)
    assert np.allclose(read_homography(tmp_path / "H"), H, rtol=1e-15, atol=0)
    pts = np.array([[10.0, 20.0, 1.0], [300.0, -40.0, 1.0]]).T
    back = np.linalg.solve(H, H @ pts)  # invertible in float64
    assert np.allclose(back / back[2], pts, rtol=1e-6)


@pytest.mark.parametrize(
    "H",
    [
        [[1, 2, 3], [2, 4, 6], [0, 0, 1]],  # two proportional rows
        [[1, 2, 3], [4, 5, 6], [7, 8, 9]],  # rank 2 (row 3 = 2 row 2 - row 1)
        [[1e4, 0, 5e3], [0, 0, 0], [0, 0, 1]],  # a zero row, large entries
        [[1e-9, 0, 0], [0, 1e-9, 0], [0, 0, 0]],  # projects everything to infinity
        np.zeros((3, 3)),
    ],
)
def test_rank_deficient_homographies_are_refused(H):
    with pytest.raises(HomographyError, match="singular homography") as e:
        read_homography(np.array(H, dtype=np.float64))
    _one_line(e)


def test_non_finite_homography_is_refused():
    with pytest.raises(HomographyError, match="NaN or inf"):
        read_homography(np.array([[1, 0, np.inf], [0, 1, 0], [0, 0, 1]]))
