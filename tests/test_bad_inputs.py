"""Bad input and faults, table-driven, across every command and the Python API.

Each CLI case runs ``localscale.cli.main`` (or the trainer's ``main``) in-process on tiny
generated inputs and asserts: exit code 2, exactly one stderr line starting with ``error:``
that names the problem, no traceback, nothing written to the output folder, and every input
file unchanged (hashed before and after). The API cases assert one-line
:class:`~localscale.core.errors.LocalScaleError` messages. The fault tests cover interrupted
writes, NaN gradients and weights, code in checkpoints, decompression bombs and DataLoader
workers orphaned by ``kill -9``.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import struct
import subprocess
import sys
import textwrap
import time
import warnings
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

import localscale.io as lio
from localscale import LocalScaleNet, ScaleNet, training
from localscale.checkpoint import checkpoint_dict, save_model
from localscale.cli import main
from localscale.cli import train as train_cli
from localscale.cli.signals import Terminated
from localscale.core.errors import CheckpointError, LocalScaleError
from localscale.models import load_model
from localscale.reliability import check_pair

TINY = dict(width=0.125, feature_dim=16, image_size=64)


class _WritesMarker:
    """Unpickling this object would create a file (stands for arbitrary code)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (Path.touch, (Path(self.marker),))


# ---------------------------------------------------------------- generated inputs


def _smooth_image(seed: int, h: int = 64, w: int = 80) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.resize(rng.integers(0, 256, (h // 8, w // 8, 3), dtype=np.uint8), (w, h), interpolation=cv2.INTER_CUBIC)
    return cv2.GaussianBlur(img, (0, 0), 1.0)


def _png_claiming(width: int, height: int) -> bytes:
    ok, buf = cv2.imencode(".png", np.zeros((16, 16, 3), np.uint8))
    data = bytearray(buf.tobytes())
    i = data.index(b"IHDR")
    data[i + 4 : i + 12] = struct.pack(">II", width, height)
    data[i + 17 : i + 21] = struct.pack(">I", zlib.crc32(bytes(data[i : i + 17])) & 0xFFFFFFFF)
    return bytes(data)


def _jpeg_claiming(width: int, height: int) -> bytes:
    ok, buf = cv2.imencode(".jpg", np.zeros((16, 16, 3), np.uint8))
    data = bytearray(buf.tobytes())
    i = data.index(b"\xff\xc0")  # baseline SOF: FFC0 len(2) precision(1) height(2) width(2)
    data[i + 5 : i + 9] = struct.pack(">HH", height, width)
    return bytes(data)


def _damaged_jpeg() -> bytes:
    """A JPEG whose header declares 9999 x 9999 pixels but whose data holds a 320 x 214 image."""
    ok, buf = cv2.imencode(".jpg", _smooth_image(6, 214, 320))
    data = bytearray(buf.tobytes())
    i = data.index(b"\xff\xc0")
    data[i + 5 : i + 9] = struct.pack(">HH", 9999, 9999)
    return bytes(data)


BOMBS = {  # headers claiming far more than MAX_PIXELS, a few KB of data
    "bomb.png": lambda: _png_claiming(100_000, 100_000),
    "bomb.jpg": lambda: _jpeg_claiming(60_000, 60_000),
    "bomb.ppm": lambda: b"P6\n30000 30000\n255\n" + bytes(4096),
    "bomb.pfm": lambda: b"PF\n20000 20000\n-1.0\n" + bytes(4096),
    "bomb.pam": lambda: b"P7\nWIDTH 20000\nHEIGHT 20000\nDEPTH 3\nMAXVAL 255\nTUPLTYPE RGB\nENDHDR\n" + bytes(4096),
    "bomb.hdr": lambda: b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 20000 +X 20000\n" + bytes(4096),
}

#: bad image files: name -> words the error must contain
BAD_IMAGES = {
    "missing.png": "file not found",
    "empty.png": "empty file",
    "folder.png": "is a directory",
    "truncated.png": "cannot decode",
    "cut_header.jpg": "size cannot be read",
    "garbage.png": "size cannot be read",
    "text.jpg": "size cannot be read",
    "no_size.hdr": "size cannot be read",
    "tiny.png": "smaller than the minimum",
    "thin.png": "smaller than the minimum",
    "damaged.jpg": ["damaged file", "9999x9999", "--accept-damaged"],
    "loop.png": "symbolic link loop",
    "broken.png": "broken symbolic link",
    "x" * 300 + ".png": "File name too long",
    **{name: "larger than the limit" for name in BOMBS},
}


def _make_checkpoints(d: Path) -> dict:
    """Bad checkpoints: name -> (path, words of the error)."""
    torch.manual_seed(0)
    good = checkpoint_dict(LocalScaleNet(**TINY).eval())

    def variant(name, edit):
        ck = {k: (dict(v) if isinstance(v, dict) else v) for k, v in good.items()}
        replaced = edit(ck)
        ck = replaced if isinstance(replaced, list) else ck  # an edit may return a whole new object
        torch.save(ck, d / name)
        return d / name

    def nan(ck):
        sd = dict(ck["state_dict"])
        k = next(k for k, v in sd.items() if v.is_floating_point())
        sd[k] = torch.full_like(sd[k], float("nan"))
        ck["state_dict"] = sd

    def inf(ck):
        sd = dict(ck["state_dict"])
        k = [k for k, v in sd.items() if v.is_floating_point()][-1]
        sd[k] = torch.full_like(sd[k], float("inf"))
        ck["state_dict"] = sd

    (d / "empty.pt").write_bytes(b"")
    (d / "text.pt").write_text("not a checkpoint\n")
    save_model(LocalScaleNet(**TINY), d / "full.pt")
    (d / "truncated.pt").write_bytes((d / "full.pt").read_bytes()[:3000])
    save_model(ScaleNet(**TINY), d / "global.pt")
    return {
        "missing": (d / "missing.pt", "checkpoint not found"),
        "empty": (d / "empty.pt", "cannot read checkpoint"),
        "text": (d / "text.pt", "cannot read checkpoint"),
        "truncated": (d / "truncated.pt", "cannot read checkpoint"),
        "code_in_meta": (
            variant("evil.pt", lambda ck: ck.update(meta={"x": _WritesMarker(d / "RAN")})),
            "non-tensor objects",
        ),
        "nan_weights": (variant("nan.pt", nan), "NaN or inf"),
        "inf_weights": (variant("inf.pt", inf), "NaN or inf"),
        "format_99": (variant("f99.pt", lambda ck: ck.update(localscale_format=99)), "format version 99"),
        "format_str": (variant("fstr.pt", lambda ck: ck.update(localscale_format="1")), "format version '1'"),
        "no_format": (variant("nofmt.pt", lambda ck: ck.pop("localscale_format")), "not a localscale checkpoint"),
        "no_state_dict": (variant("nosd.pt", lambda ck: ck.pop("state_dict")), "no 'state_dict'"),
        "non_tensor": (variant("nt.pt", lambda ck: ck["state_dict"].update({"head.x": [1, 2]})), "not a tensor"),
        "bad_config": (
            variant("cfg.pt", lambda ck: ck.update(config={"width": "wide", "bogus": 1})),
            "config does not fit",
        ),
        "no_config": (variant("nocfg.pt", lambda ck: ck.update(config=[1])), "no valid 'config'"),
        "wrong_arch": (d / "global.pt", "expected a LocalScaleNet"),
        "unknown_arch": (variant("arch.pt", lambda ck: ck.update(arch="Banana")), "Banana"),
        "missing_keys": (
            variant(
                "keys.pt",
                lambda ck: ck.update(state_dict={k: v for i, (k, v) in enumerate(good["state_dict"].items()) if i % 2}),
            ),
            "do not match",
        ),
        "list": (variant("list.pt", lambda ck: [1, 2, 3]), "not a localscale checkpoint"),
    }


def _hash_tree(root: Path) -> dict:
    """sha1 of every regular file under ``root`` (links are not followed)."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in filenames + dirnames:
            p = Path(dirpath) / name
            if p.is_symlink():
                out[str(p)] = "link:" + os.readlink(p)
            elif p.is_file():
                out[str(p)] = hashlib.sha1(p.read_bytes()).hexdigest()
            elif p.is_dir():
                out[str(p)] = "dir"
    return out


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    root = tmp_path_factory.mktemp("bad_inputs")
    d = root / "in"
    d.mkdir()
    cv2.imwrite(str(d / "a.png"), _smooth_image(1))
    cv2.imwrite(str(d / "b.png"), _smooth_image(2))
    good_png = (d / "a.png").read_bytes()
    ok, jpg = cv2.imencode(".jpg", _smooth_image(3))
    (d / "empty.png").write_bytes(b"")
    (d / "folder.png").mkdir()
    (d / "truncated.png").write_bytes(good_png[:120])
    (d / "cut_header.jpg").write_bytes(jpg.tobytes()[:20])
    (d / "garbage.png").write_bytes(np.random.default_rng(0).integers(0, 256, 2000, dtype=np.uint8).tobytes())
    (d / "text.jpg").write_text("hello, I am not a photo\n")
    (d / "no_size.hdr").write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\nno resolution line\n" + bytes(100))
    cv2.imwrite(str(d / "tiny.png"), _smooth_image(4)[:8, :8])
    cv2.imwrite(str(d / "thin.png"), _smooth_image(5, 64, 80)[:4])
    (d / "damaged.jpg").write_bytes(_damaged_jpeg())
    os.symlink("loop2.png", d / "loop.png")
    os.symlink("loop.png", d / "loop2.png")
    os.symlink("nowhere.png", d / "broken.png")
    for name, make in BOMBS.items():
        (d / name).write_bytes(make())
    # homographies
    (d / "H_ok").write_text("1 0 0\n0 1 0\n0 0 1\n")
    (d / "H_nan").write_text("nan 0 0\n0 1 0\n0 0 1\n")
    (d / "H_singular").write_text("1 2 3\n2 4 6\n0 0 1\n")
    (d / "H_2x2").write_text("1 0\n0 1\n")
    (d / "H_text").write_text("one two three\n")
    (d / "afile").write_text("I am a file, not a folder\n")
    # pairs files
    (d / "pairs_one_field.txt").write_text("a.png b.png\nb.png\n")
    (d / "pairs_three.txt").write_text("a.png b.png a.png\n")
    (d / "pairs_quote.txt").write_text('"a.png b.png\n')
    (d / "pairs_empty.txt").write_text("")
    (d / "pairs_comments.txt").write_text("# nothing\n\n   # still nothing\n")
    (d / "pairs_latin1.txt").write_bytes("a.png b\xe9.png\n".encode("latin-1"))
    (d / "pairs_ok.txt").write_text("a.png b.png\n")
    os.symlink("pairs_loop2.txt", d / "pairs_loop.txt")
    os.symlink("pairs_loop.txt", d / "pairs_loop2.txt")
    os.symlink("no_pairs.txt", d / "pairs_broken.txt")
    ck = d / "ckpt"
    ck.mkdir()
    checkpoints = _make_checkpoints(ck)
    save_model(LocalScaleNet(**TINY), d / "local.pt")
    save_model(ScaleNet(**TINY), d / "global.pt")
    # HPatches-layout roots
    hp = root / "hp"
    (hp / "v_ok").mkdir(parents=True)
    for k in (1, 2):
        cv2.imwrite(str(hp / "v_ok" / f"{k}.png"), _smooth_image(10))
    (hp / "v_ok" / "H_1_2").write_text("1 0 0\n0 1 0\n0 0 1\n")
    bad = root / "hp_bad"
    (bad / "v_nan").mkdir(parents=True)
    cv2.imwrite(str(bad / "v_nan" / "1.png"), _smooth_image(11))
    cv2.imwrite(str(bad / "v_nan" / "2.png"), _smooth_image(11))
    (bad / "v_nan" / "H_1_2").write_text("nan 0 0\n0 1 0\n0 0 1\n")
    (root / "hp_empty").mkdir()
    # training photo folders
    photos = root / "photos"
    photos.mkdir()
    for i in range(6):
        cv2.imwrite(str(photos / f"p{i}.png"), _smooth_image(20 + i, 96, 128))
    one = root / "one_photo"
    one.mkdir()
    cv2.imwrite(str(one / "p.png"), _smooth_image(30, 96, 128))
    corrupt = root / "corrupt_photos"
    corrupt.mkdir()
    for i in range(4):
        (corrupt / f"c{i}.png").write_bytes(good_png[:120])
    return {
        "root": root,
        "in": d,
        "ck": checkpoints,
        "hp": hp,
        "hp_bad": bad,
        "hp_empty": root / "hp_empty",
        "photos": photos,
        "one_photo": one,
        "corrupt_photos": corrupt,
    }


def _run(fn, argv, capsys):
    try:
        rc = fn(argv)
    except SystemExit as e:  # argument errors
        rc = e.code
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def assert_clean_error(rc, err, words, out_dir: Path | None = None):
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert rc == 2, (rc, err)
    assert len(lines) == 1, err
    for w in words if isinstance(words, (list, tuple)) else [words]:
        assert w in lines[0], (w, lines[0])
    if out_dir is not None:
        assert not out_dir.exists() or not any(out_dir.iterdir()), list(out_dir.iterdir())


# ---------------------------------------------------------------- the CLI table


def _image_cases():
    """Every bad image file, as image A or B of each command that reads images."""
    cases = []
    for name, words in BAD_IMAGES.items():
        short = name if len(name) < 40 else "long_name.png"
        cases += [
            (
                f"predict-A-{short}",
                ["predict", "{in}/" + name, "{in}/b.png", "-o", "{out}", "--local-weights", "{in}/local.pt"],
                words,
            ),
            (
                f"predict-B-{short}",
                ["predict", "{in}/a.png", "{in}/" + name, "-o", "{out}", "--local-weights", "{in}/local.pt"],
                words,
            ),
            (f"scale-A-{short}", ["scale", "{in}/" + name, "{in}/b.png", "--global-weights", "{in}/global.pt"], words),
            (
                f"rectify-B-{short}",
                ["rectify", "{in}/a.png", "{in}/" + name, "-o", "{out}", "--global-weights", "{in}/global.pt"],
                words,
            ),
            (
                f"show-A-{short}",
                ["show", "{in}/" + name, "{in}/b.png", "-o", "{out}", "--local-weights", "{in}/local.pt"],
                words,
            ),
            (
                f"match-B-{short}",
                ["match", "{in}/a.png", "{in}/" + name, "-o", "{out}", "--correction", "none", "--descriptor", "sift"],
                words,
            ),
        ]
    return cases


CHECKPOINT_CASES = [
    "missing",
    "empty",
    "text",
    "truncated",
    "code_in_meta",
    "nan_weights",
    "inf_weights",
    "format_99",
    "format_str",
    "no_format",
    "no_state_dict",
    "non_tensor",
    "bad_config",
    "no_config",
    "wrong_arch",
    "unknown_arch",
    "missing_keys",
    "list",
]


def _checkpoint_cases():
    cases = []
    for name in CHECKPOINT_CASES:
        w = "{ck:" + name + "}"
        cases.append(
            (
                f"predict-ckpt-{name}",
                ["predict", "{in}/a.png", "{in}/b.png", "-o", "{out}", "--local-weights", w],
                "{ckw:" + name + "}",
            )
        )
    for name in ("missing", "code_in_meta", "nan_weights", "format_99", "no_state_dict", "truncated"):
        w = "{ck:" + name + "}"
        cases += [
            (
                f"show-ckpt-{name}",
                ["show", "{in}/a.png", "{in}/b.png", "-o", "{out}", "--local-weights", w],
                "{ckw:" + name + "}",
            ),
            (f"demo-ckpt-{name}", ["demo", "-o", "{out}", "--local-weights", w], "{ckw:" + name + "}"),
            (
                f"match-ckpt-{name}",
                [
                    "match",
                    "{in}/a.png",
                    "{in}/b.png",
                    "-o",
                    "{out}",
                    "--correction",
                    "local",
                    "--descriptor",
                    "sift",
                    "--local-weights",
                    w,
                ],
                "{ckw:" + name + "}",
            ),
            (
                f"eval-ckpt-{name}",
                [
                    "eval-hpatches",
                    "{hp}",
                    "-o",
                    "{out}",
                    "--methods",
                    "none",
                    "local",
                    "--descriptor",
                    "sift",
                    "--local-weights",
                    w,
                ],
                "{ckw:" + name + "}",
            ),
        ]
    cases += [
        (
            "scale-ckpt-nan_weights",
            ["scale", "{in}/a.png", "{in}/b.png", "--json", "--global-weights", "{ck:nan_weights}"],
            "NaN or inf",
        ),
        (
            "scale-ckpt-local-for-global",
            ["scale", "{in}/a.png", "{in}/b.png", "--global-weights", "{in}/local.pt"],
            "expected a ScaleNet",
        ),
        (
            "rectify-ckpt-code",
            ["rectify", "{in}/a.png", "{in}/b.png", "-o", "{out}", "--global-weights", "{ck:code_in_meta}"],
            "non-tensor objects",
        ),
        (
            "match-descriptor-code",
            [
                "match",
                "{in}/a.png",
                "{in}/b.png",
                "-o",
                "{out}",
                "--correction",
                "none",
                "--descriptor",
                "{ck:code_in_meta}",
            ],
            "non-tensor objects",
        ),
        (
            "match-descriptor-missing",
            [
                "match",
                "{in}/a.png",
                "{in}/b.png",
                "-o",
                "{out}",
                "--correction",
                "none",
                "--descriptor",
                "{in}/nope.pt",
            ],
            "not found",
        ),
    ]
    return cases


def _option_cases():
    P = ["predict", "--pairs", "{in}/pairs_ok.txt", "-o", "{out}", "--local-weights", "{in}/local.pt"]
    M = ["match", "{in}/a.png", "{in}/b.png", "-o", "{out}", "--descriptor", "sift"]
    E = ["eval-hpatches", "{hp}", "-o", "{out}", "--methods", "none", "--descriptor", "sift"]
    cases = [
        ("predict-batch-size-0", P + ["--batch-size", "0"], "--batch-size"),
        ("predict-batch-size--1", P + ["--batch-size", "-1"], "--batch-size"),
        ("predict-batch-size-text", P + ["--batch-size", "many"], "--batch-size"),
        ("predict-cache-mb-nan", P + ["--cache-mb", "nan"], "--cache-mb"),
        ("predict-cache-mb-inf", P + ["--cache-mb", "inf"], "--cache-mb"),
        ("predict-cache-mb-0", P + ["--cache-mb", "0"], "--cache-mb"),
        ("predict-cache-mb--5", P + ["--cache-mb", "-5"], "--cache-mb"),
        ("predict-unknown-option", P + ["--frobnicate"], "unrecognized arguments"),
        (
            "predict-both-modes",
            ["predict", "{in}/a.png", "{in}/b.png", "--pairs", "{in}/pairs_ok.txt", "-o", "{out}"],
            "not both",
        ),
        ("predict-nothing", ["predict", "-o", "{out}"], "give two images"),
        ("match-num-features-0", M + ["--correction", "none", "--num-features", "0"], "--num-features"),
        ("match-num-features--3", M + ["--correction", "none", "--num-features", "-3"], "--num-features"),
        ("match-ratio-nan", M + ["--correction", "none", "--ratio", "nan"], "ratio"),
        ("match-max-side--5", M + ["--correction", "none", "--max-side", "-5"], "--max-side"),
        ("match-max-side-text", M + ["--correction", "none", "--max-side", "big"], "--max-side"),
        ("match-ratio-2", M + ["--correction", "none", "--ratio", "2"], "ratio"),
        ("match-bad-correction", M + ["--correction", "magic"], "invalid choice"),
        ("match-gt-without-H", M + ["--correction", "gt"], "needs the homography"),
        ("match-H-missing", M + ["--correction", "gt", "--H", "{in}/H_nope"], "not found"),
        ("match-H-nan", M + ["--correction", "gt", "--H", "{in}/H_nan"], "NaN"),
        ("match-H-singular", M + ["--correction", "gt", "--H", "{in}/H_singular"], "singular"),
        ("match-H-2x2", M + ["--correction", "gt", "--H", "{in}/H_2x2"], "3x3"),
        ("match-H-text", M + ["--correction", "gt", "--H", "{in}/H_text"], "not a text matrix"),
        ("match-H-loop", M + ["--correction", "gt", "--H", "{in}/loop.png"], "symbolic link loop"),
        ("match-H-broken-link", M + ["--correction", "gt", "--H", "{in}/broken.png"], "broken symbolic link"),
        ("match-H-folder", M + ["--correction", "gt", "--H", "{in}/folder.png"], "not a regular file"),
        ("match-H-binary", M + ["--correction", "gt", "--H", "{in}/garbage.png"], "not a text matrix"),
        (
            "show-H-nan",
            [
                "show",
                "{in}/a.png",
                "{in}/b.png",
                "-o",
                "{out}",
                "--H",
                "{in}/H_nan",
                "--local-weights",
                "{in}/local.pt",
            ],
            "NaN",
        ),
        (
            "show-H-singular",
            [
                "show",
                "{in}/a.png",
                "{in}/b.png",
                "-o",
                "{out}",
                "--H",
                "{in}/H_singular",
                "--local-weights",
                "{in}/local.pt",
            ],
            "singular",
        ),
        ("eval-max-side--5", E + ["--max-side", "-5"], "--max-side"),
        ("eval-num-features-0", E + ["--num-features", "0"], "--num-features"),
        ("eval-base-radius-nan", E + ["--base-radius", "nan"], "--base-radius"),
        ("eval-bad-method", E + ["--methods", "magic"], "invalid choice"),
        ("eval-root-missing", ["eval-hpatches", "{in}/no_root", "-o", "{out}", "--methods", "none"], "not found"),
        ("eval-root-file", ["eval-hpatches", "{in}/afile", "-o", "{out}", "--methods", "none"], "not found"),
        ("eval-root-empty", ["eval-hpatches", "{hp_empty}", "-o", "{out}", "--methods", "none"], "no sequences"),
        (
            "eval-all-pairs-bad",
            ["eval-hpatches", "{hp_bad}", "-o", "{out}", "--methods", "none", "--descriptor", "sift"],
            ["can be evaluated", "NaN"],
        ),
        ("no-command", [], "required"),
        ("unknown-command", ["frobnicate"], "invalid choice"),
    ]
    for cmd, argv in {
        "predict": ["predict", "{in}/a.png", "{in}/b.png", "-o", "{out}"],
        "show": ["show", "{in}/a.png", "{in}/b.png", "-o", "{out}"],
        "demo": ["demo", "-o", "{out}"],
        "scale": ["scale", "{in}/a.png", "{in}/b.png"],
        "rectify": ["rectify", "{in}/a.png", "{in}/b.png", "-o", "{out}"],
        "match": ["match", "{in}/a.png", "{in}/b.png", "-o", "{out}", "--correction", "fused"],
        "eval-hpatches": ["eval-hpatches", "{hp}", "-o", "{out}", "--methods", "local"],
    }.items():
        cases.append((f"{cmd}-device-banana", argv + ["--device", "banana"], "unknown device 'banana'"))
    return cases


def _pairs_cases():
    P = ["predict", "-o", "{out}", "--local-weights", "{in}/local.pt", "--pairs"]
    return [
        ("pairs-missing", P + ["{in}/no_pairs.txt"], "pairs file not found"),
        ("pairs-folder", P + ["{in}/folder.png"], "pairs file is a folder"),
        ("pairs-loop", P + ["{in}/pairs_loop.txt"], "symbolic link loop"),
        ("pairs-broken-link", P + ["{in}/pairs_broken.txt"], "broken symbolic link"),
        ("pairs-not-utf8", P + ["{in}/pairs_latin1.txt"], ["pairs_latin1.txt:1", "not UTF-8"]),
        ("pairs-one-field", P + ["{in}/pairs_one_field.txt"], ["pairs_one_field.txt:2", "got 1 field"]),
        ("pairs-three-fields", P + ["{in}/pairs_three.txt"], ["pairs_three.txt:1", "got 3 field"]),
        ("pairs-open-quote", P + ["{in}/pairs_quote.txt"], ["pairs_quote.txt:1", "quotation"]),
        ("pairs-empty", P + ["{in}/pairs_empty.txt"], "no pairs"),
        ("pairs-only-comments", P + ["{in}/pairs_comments.txt"], "no pairs"),
        ("pairs-long-name", P + ["{in}/" + "p" * 300 + ".txt"], "name too long"),
    ]


def _output_cases():
    cases = []
    argv = {
        "predict": ["predict", "{in}/a.png", "{in}/b.png", "--local-weights", "{in}/local.pt"],
        "predict-pairs": ["predict", "--pairs", "{in}/pairs_ok.txt", "--local-weights", "{in}/local.pt"],
        "show": ["show", "{in}/a.png", "{in}/b.png", "--local-weights", "{in}/local.pt"],
        "demo": ["demo", "--local-weights", "{in}/local.pt"],
        "rectify": ["rectify", "{in}/a.png", "{in}/b.png", "--global-weights", "{in}/global.pt"],
        "match": ["match", "{in}/a.png", "{in}/b.png", "--correction", "none", "--descriptor", "sift"],
        "eval-hpatches": ["eval-hpatches", "{hp}", "--methods", "none", "--descriptor", "sift"],
    }
    for cmd, a in argv.items():
        cases += [
            (f"{cmd}-out-is-a-file", a + ["-o", "{in}/afile"], "is not a folder"),
            (f"{cmd}-out-under-a-file", a + ["-o", "{in}/afile/sub"], "is a file, not a folder"),
            (f"{cmd}-out-name-too-long", a + ["-o", "{out}/" + "o" * 300], "name too long"),
            (f"{cmd}-out-read-only", a + ["-o", "{out}", "@readonly"], "not writable"),
        ]
    cases.append(
        (
            "predict-pairs-index-is-input",
            ["predict", "--pairs", "{out_in}/index.tsv", "-o", "{out_in}", "--local-weights", "{in}/local.pt"],
            "refusing to overwrite",
        )
    )
    return cases


CLI_CASES = _image_cases() + _checkpoint_cases() + _option_cases() + _pairs_cases() + _output_cases()


def _fill(arg: str, env, out: Path) -> str:
    for key in ("in", "hp", "hp_bad", "hp_empty"):
        arg = arg.replace("{" + key + "}", str(env[key]))
    arg = arg.replace("{out_in}", str(env["in"] / "out_in")).replace("{out}", str(out))
    if arg.startswith("{ck:"):
        return str(env["ck"][arg[4:-1]][0])
    return arg


@pytest.mark.parametrize("case", CLI_CASES, ids=[c[0] for c in CLI_CASES])
def test_cli_bad_input_is_one_clean_error(case, env, tmp_path, capsys, monkeypatch):
    name, argv, words = case
    out = tmp_path / "out"
    if name == "predict-pairs-index-is-input":  # the pairs file is the index the command would write
        (env["in"] / "out_in").mkdir(exist_ok=True)
        (env["in"] / "out_in" / "index.tsv").write_text(f"{env['in']}/a.png\t{env['in']}/b.png\n")
    if "@readonly" in argv:  # root ignores permission bits: make the folder check see a read-only folder
        argv = [a for a in argv if a != "@readonly"]
        out.mkdir()
        real = os.access
        monkeypatch.setattr(os, "access", lambda p, mode, *a, **k: False if Path(p) == out else real(p, mode, *a, **k))
    if isinstance(words, str) and words.startswith("{ckw:"):
        words = env["ck"][words[5:-1]][1]
    argv = [_fill(a, env, out) for a in argv]
    before = _hash_tree(env["root"])
    rc, stdout, err = _run(main, argv, capsys)
    assert_clean_error(rc, err, words, out)
    assert _hash_tree(env["root"]) == before  # no input modified, nothing written beside them
    assert not (env["in"] / "ckpt" / "RAN").exists()  # no code from a checkpoint ran
    assert "NaN" not in stdout


def test_the_table_is_large():
    assert len(CLI_CASES) + len(TRAIN_CASES) + len(API_CASES) >= 100
    assert len({c[0] for c in CLI_CASES}) == len(CLI_CASES)


# ---------------------------------------------------------------- training CLI

TRAIN_BASE = [
    "--width",
    "0.125",
    "--feature-dim",
    "16",
    "--image-size",
    "64",
    "--steps",
    "2",
    "--batch-size",
    "2",
    "--holdout-every",
    "3",
    "--val-pairs",
    "2",
    "--workers",
    "0",
    "--threads",
    "1",
    "--amp",
    "off",
]

TRAIN_CASES = [
    ("data-missing", ["--data", "{root}/no_photos"], "image folder not found"),
    ("data-empty", ["--data", "{hp_empty}"], "no images"),
    ("data-one-photo", ["--data", "{one_photo}"], "need >= 2 training"),
    ("data-all-corrupt", ["--data", "{corrupt_photos}"], "unreadable photos"),
    ("steps-0", ["--steps", "0"], "steps must be >= 1"),
    ("batch-size-0", ["--batch-size", "0"], "batch-size must be >= 1"),
    ("batch-size--1", ["--batch-size", "-1"], "batch-size must be >= 1"),
    ("lr-nan", ["--lr", "nan"], "lr must be in [0, 1]"),
    ("lr-1e39", ["--lr", "1e39"], "lr must be in [0, 1]"),
    ("lr-negative", ["--lr", "-1"], "lr must be in [0, 1]"),
    ("image-size-30", ["--image-size", "30"], "image-size must be a multiple of 8"),
    ("workers--1", ["--workers", "-1"], "workers must be >= 0"),
    ("crop-min-0", ["--crop-min", "0"], "crop_min must be in (0, 1]"),
    ("probability-2", ["--degrade-probability", "2"], "degrade-probability must be in [0, 1]"),
    ("width-nan", ["--width", "nan"], "width must be a finite number"),
    ("steps-text", ["--steps", "many"], "--steps"),
    ("unknown-option", ["--frobnicate"], "unrecognized arguments"),
    ("init-weights-missing", ["--init-weights", "{ck:missing}"], "checkpoint not found"),
    ("init-weights-code", ["--init-weights", "{ck:code_in_meta}"], "non-tensor objects"),
    ("init-weights-nan", ["--init-weights", "{ck:nan_weights}"], "NaN or inf"),
    ("init-weights-global", ["--init-weights", "{ck:wrong_arch}"], "do not fit"),
    ("init-extractor-truncated", ["--init-extractor", "{ck:truncated}"], "cannot read checkpoint"),
    ("out-is-a-file", ["--out", "{in}/afile"], "is not a folder"),
    ("out-name-too-long", ["--out", "{out}/" + "o" * 300], "name too long"),
    ("device-banana", ["--device", "banana"], "unknown device 'banana'"),
    ("device-cuda-99", ["--device", "cuda:99"], "'cuda:99'"),
    ("device-meta", ["--device", "meta"], "'meta' is not supported"),
] + ([] if torch.cuda.is_available() else [("device-cuda", ["--device", "cuda"], "no CUDA device available")])


@pytest.mark.parametrize("case", TRAIN_CASES, ids=[c[0] for c in TRAIN_CASES])
def test_training_cli_bad_input_is_one_clean_error(case, env, tmp_path, capsys):
    name, argv, words = case
    out = tmp_path / "out"
    argv = [
        a.replace("{root}", str(env["root"]))
        .replace("{hp_empty}", str(env["hp_empty"]))
        .replace("{one_photo}", str(env["one_photo"]))
        .replace("{corrupt_photos}", str(env["corrupt_photos"]))
        for a in argv
    ]
    argv = [_fill(a, env, out) for a in argv]
    full = TRAIN_BASE + ["--data", str(env["photos"]), "--out", str(out)] + argv  # later options win
    before = _hash_tree(env["root"])
    with pytest.warns(None) if False else _no_op():
        rc, stdout, err = _run(lambda a: train_cli.main(a, model="local"), full, capsys)
    assert_clean_error(rc, err, words, out)
    assert _hash_tree(env["root"]) == before
    assert not (env["in"] / "ckpt" / "RAN").exists()


class _no_op:
    def __enter__(self):
        import warnings

        self._w = warnings.catch_warnings()
        self._w.__enter__()
        warnings.simplefilter("ignore")  # the skipped-photo warnings of data-all-corrupt

    def __exit__(self, *exc):
        return self._w.__exit__(*exc)


def test_resuming_a_checkpoint_of_another_configuration_is_one_clean_error(env, tmp_path, capsys):
    out = tmp_path / "run"
    argv = TRAIN_BASE + ["--data", str(env["photos"]), "--out", str(out)]
    assert train_cli.main(argv + ["--steps", "1"], model="local") == 0
    capsys.readouterr()
    before = _hash_tree(out)
    rc, _, err = _run(lambda a: train_cli.main(a, model="local"), argv + ["--feature-dim", "32"], capsys)
    assert_clean_error(rc, err, ["cannot resume", "another configuration"])
    assert _hash_tree(out) == before


# ---------------------------------------------------------------- Python API


def _api_model():
    torch.manual_seed(0)
    return LocalScaleNet(**TINY).eval()


API_CASES = [
    (
        "array-5-channels",
        lambda m, e: m.predict(np.zeros((64, 64, 5), np.uint8), np.zeros((64, 64, 3), np.uint8)),
        "got shape (64, 64, 5)",
    ),
    ("array-1d", lambda m, e: m.predict(np.zeros(64, np.uint8), np.zeros((64, 64), np.uint8)), "got shape (64,)"),
    (
        "array-4d",
        lambda m, e: m.predict(np.zeros((1, 64, 64, 3), np.uint8), np.zeros((64, 64), np.uint8)),
        "got shape (1, 64, 64, 3)",
    ),
    (
        "array-int64",
        lambda m, e: m.predict(np.zeros((64, 64), np.int64), np.zeros((64, 64), np.uint8)),
        "unsupported dtype int64",
    ),
    (
        "array-complex",
        lambda m, e: m.predict(np.zeros((64, 64), np.complex64), np.zeros((64, 64), np.uint8)),
        "unsupported dtype complex64",
    ),
    (
        "array-object",
        lambda m, e: m.predict(np.zeros((64, 64), object), np.zeros((64, 64), np.uint8)),
        "unsupported dtype object",
    ),
    (
        "array-nan",
        lambda m, e: m.predict(np.full((64, 64), np.nan, np.float32), np.zeros((64, 64), np.uint8)),
        "NaN or inf",
    ),
    (
        "array-out-of-range",
        lambda m, e: m.predict(np.full((64, 64), 2.0, np.float32), np.zeros((64, 64), np.uint8)),
        "must be in [0, 1]",
    ),
    (
        "array-empty",
        lambda m, e: m.predict(np.zeros((64, 0, 3), np.uint8), np.zeros((64, 64), np.uint8)),
        "smaller than the minimum",
    ),
    (
        "array-tiny",
        lambda m, e: m.predict(np.zeros((8, 8, 3), np.uint8), np.zeros((64, 64), np.uint8)),
        "smaller than the minimum",
    ),
    ("list", lambda m, e: m.predict([[1, 2], [3, 4]], np.zeros((64, 64), np.uint8)), "got list"),
    ("none", lambda m, e: m.predict(None, np.zeros((64, 64), np.uint8)), "got NoneType"),
    ("file-missing", lambda m, e: m.predict(e["in"] / "missing.png", e["in"] / "b.png"), "file not found"),
    ("file-bomb-png", lambda m, e: m.predict(e["in"] / "bomb.png", e["in"] / "b.png"), "larger than the limit"),
    ("file-bomb-hdr", lambda m, e: m.predict(e["in"] / "a.png", e["in"] / "bomb.hdr"), "larger than the limit"),
    ("file-loop", lambda m, e: m.predict(e["in"] / "loop.png", e["in"] / "b.png"), "symbolic link loop"),
    ("H-singular", lambda m, e: lio.read_homography(np.diag([1.0, 1.0, 0.0])), "singular"),
    ("H-nan", lambda m, e: lio.read_homography(np.full((3, 3), np.nan)), "NaN"),
    ("H-shape", lambda m, e: lio.read_homography(np.eye(4)), "3x3"),
    ("H-file-text", lambda m, e: lio.read_homography(e["in"] / "H_text"), "not a text matrix"),
    ("load-nan", lambda m, e: load_model(e["ck"]["nan_weights"][0]), "NaN or inf"),
    ("load-code", lambda m, e: load_model(e["ck"]["code_in_meta"][0]), "non-tensor objects"),
    ("from-pretrained-wrong-arch", lambda m, e: ScaleNet.from_pretrained(e["in"] / "local.pt"), "expected a ScaleNet"),
    (
        "from-pretrained-format",
        lambda m, e: LocalScaleNet.from_pretrained(e["ck"]["format_99"][0]),
        "format version 99",
    ),
    ("save-nan", lambda m, e: save_model(_nan_model(), e["root"] / "saved_nan.pt"), "not saved"),
    ("predict-pairs-bad-pair", lambda m, e: _first_pair_error(m, e), "file not found"),
    ("from-pretrained-cuda-99", lambda m, e: LocalScaleNet.from_pretrained(device="cuda:99"), "'cuda:99'"),
    ("from-pretrained-bogus", lambda m, e: LocalScaleNet.from_pretrained(device="bogus"), "unknown device 'bogus'"),
    ("from-pretrained-meta", lambda m, e: ScaleNet.from_pretrained(device="meta"), "'meta' is not supported"),
    (
        "load-model-device-object",
        lambda m, e: load_model(e["in"] / "local.pt", device=torch.device("meta")),
        "'meta' is not supported",
    ),
    (
        "predict-meta-tensor",
        lambda m, e: m.predict(torch.zeros(3, 64, 64, device="meta"), e["in"] / "b.png"),
        "image A: tensor on the meta device",
    ),
    (
        "predict-batch-meta-tensor",
        lambda m, e: m.predict_batch(torch.zeros(2, 3, 64, 64), torch.zeros(2, 3, 64, 64, device="meta")),
        "images B: tensor on the meta device",
    ),
    (
        "check-pair-scalenet",
        lambda m, e: check_pair(ScaleNet(**TINY), e["in"] / "a.png", e["in"] / "b.png"),
        "check_pair needs a LocalScaleNet",
    ),
    ("check-pair-none", lambda m, e: check_pair(None, e["in"] / "a.png", e["in"] / "b.png"), "got NoneType"),
] + (
    []
    if torch.cuda.is_available()
    else [
        ("from-pretrained-cuda", lambda m, e: LocalScaleNet.from_pretrained(device="cuda"), "no CUDA device available"),
    ]
)


def _nan_model():
    m = _api_model()
    with torch.no_grad():
        next(m.parameters()).fill_(float("nan"))
    return m


def _first_pair_error(m, e):
    from localscale.cache import predict_pairs

    ((_, res),) = list(predict_pairs(m, [(e["in"] / "missing.png", e["in"] / "b.png")]))
    raise res


@pytest.mark.parametrize("case", API_CASES, ids=[c[0] for c in API_CASES])
def test_api_bad_input_is_one_line_error(case, env):
    name, call, words = case
    before = _hash_tree(env["root"])
    with pytest.raises(LocalScaleError) as e:
        call(_api_model(), env)
    msg = str(e.value)
    assert "\n" not in msg and words in msg, msg
    assert _hash_tree(env["root"]) == before
    assert not (env["in"] / "ckpt" / "RAN").exists()


def test_gray_alpha_array_is_gray(env):
    """``H x W x 2`` arrays are gray + alpha."""
    ga = np.dstack([_smooth_image(1)[..., 0], np.full((64, 80), 255, np.uint8)])
    rgb = lio.load_image(ga)
    assert rgb.shape == (64, 80, 3) and (rgb[..., 0] == ga[..., 0]).all()


# ---------------------------------------------------------------- faults: interrupted writes


def test_interrupted_write_leaves_no_partial_file(env, tmp_path, monkeypatch, capsys):
    """A write that dies midway (here: after half the bytes) leaves neither the final name nor a
    temporary file; the command fails with one error line."""
    real_save = np.save

    def half_then_fail(f, arr, *a, **k):
        f.write(b"\x93NUMPY partial")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "save", half_then_fail)
    out = tmp_path / "out"
    rc, _, err = _run(
        main,
        [
            "predict",
            str(env["in"] / "a.png"),
            str(env["in"] / "b.png"),
            "-o",
            str(out),
            "--local-weights",
            str(env["in"] / "local.pt"),
        ],
        capsys,
    )
    assert_clean_error(rc, err, ["No space left on device", "_scale.npy"])
    assert not list(out.glob("*.npy")) and not list(out.glob(".*"))
    monkeypatch.setattr(np, "save", real_save)


@pytest.mark.parametrize("exc", [KeyboardInterrupt, OSError])
def test_atomic_path_keeps_the_old_file_on_failure(tmp_path, exc):
    from localscale.core.outputs import atomic_path

    target = tmp_path / "result.json"
    target.write_text("old, complete")
    with pytest.raises((exc, LocalScaleError)):
        with atomic_path(target) as tmp:
            tmp.write_text("new, half")
            raise exc()
    assert target.read_text() == "old, complete" and sorted(p.name for p in tmp_path.iterdir()) == ["result.json"]


def _pairs_setup(env, tmp_path, n=4):
    d = tmp_path / "imgs"
    d.mkdir()
    for i in range(n + 1):
        cv2.imwrite(str(d / f"im {i}.png"), _smooth_image(40 + i))  # names with spaces: quoted in the file
    lines = [f'"im {i}.png"\t"x"' for i in range(0)] + [f'"im {i}.png" "im {i + 1}.png"' for i in range(n)]
    (d / "pairs.txt").write_text("# pairs\n" + "\n".join(lines) + "\n")
    return d / "pairs.txt"


def test_interrupted_pairs_run_resumes_and_reports_counts(env, tmp_path, monkeypatch, capsys):
    import localscale.maps.files as outputs

    pairs = _pairs_setup(env, tmp_path)
    out = tmp_path / "out"
    argv = [
        "predict",
        "--pairs",
        str(pairs),
        "-o",
        str(out),
        "--local-weights",
        str(env["in"] / "local.pt"),
        "--batch-size",
        "1",
    ]
    real = outputs.write_image
    calls = {"n": 0}

    def terminated_on_the_6th_image(path, img):
        calls["n"] += 1
        if calls["n"] == 6:  # pair 2's colour PNG (two images per pair): SIGTERM arrives during the write
            raise Terminated()
        return real(path, img)

    monkeypatch.setattr(outputs, "write_image", terminated_on_the_6th_image)
    rc, _, err = _run(main, argv, capsys)
    assert rc == 143 and "terminated" in err and "Traceback" not in err
    for f in out.iterdir():  # every file left is complete; no temporary file is left
        assert not f.name.startswith("."), f
        if f.suffix == ".npy":
            np.load(f)
    monkeypatch.setattr(outputs, "write_image", real)
    rc, stdout, _ = _run(main, argv, capsys)
    assert rc == 0 and "4 pairs: 2 written, 2 skipped" in stdout  # pairs 0 and 1 were complete
    rc, stdout, _ = _run(main, argv, capsys)
    assert rc == 0 and "0 written, 4 skipped" in stdout
    (out / "00003_im 3_im 4_confidence.npy").unlink()  # an incomplete pair is redone
    rc, stdout, _ = _run(main, argv, capsys)
    assert "1 written, 3 skipped" in stdout
    rc, stdout, _ = _run(main, argv + ["--overwrite"], capsys)
    assert "4 written, 0 skipped" in stdout
    index = (out / "index.tsv").read_text().splitlines()
    assert len(index) == 5 and all("\tok\t" in ln for ln in index[1:])


def test_pairs_file_carries_any_path(tmp_path):
    from localscale.cli import read_pairs_file

    d = tmp_path
    (d / "p.txt").write_text("a b.png\tc #1.png\n\"q r.png\" 's #2.png'\n# comment\n  \n/abs/x.png y.png\n")
    got = [(a.name, b.name) for a, b in read_pairs_file(d / "p.txt")]
    assert got == [("a b.png", "c #1.png"), ("q r.png", "s #2.png"), ("x.png", "y.png")]


def test_sigterm_during_a_pairs_run_leaves_only_complete_files(env, tmp_path):
    """A real SIGTERM to ``localscale predict --pairs``: exit 143, every file complete, a rerun resumes."""
    pairs = _pairs_setup(env, tmp_path, n=40)
    out = tmp_path / "out"
    cmd = [
        sys.executable,
        "-m",
        "localscale",
        "predict",
        "--pairs",
        str(pairs),
        "-o",
        str(out),
        "--local-weights",
        str(env["in"] / "local.pt"),
        "--batch-size",
        "1",
    ]
    envv = dict(os.environ, OMP_NUM_THREADS="1")
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=envv)
    t0 = time.time()
    while time.time() - t0 < 120 and p.poll() is None and not list(out.glob("*_scale.json")):  # first pair done
        time.sleep(0.01)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=60)
    err = err.decode()
    assert p.returncode == 143 and "Traceback" not in err and "Fatal" not in err, (p.returncode, err[-2000:])
    stopped = [ln for ln in err.splitlines() if ln.startswith("stopped:")]
    assert len(stopped) == 1 and "SIGTERM" in stopped[0] and "a rerun resumes" in stopped[0], err[-2000:]
    done = len(list(out.glob("*_scale.json")))
    assert 1 <= done < 40
    for f in out.iterdir():
        assert not f.name.startswith("."), f
        if f.suffix == ".npy":
            np.load(f)
    index = (out / "index.tsv").read_text().splitlines()[1:]
    assert (
        sum("\tok\t" in r for r in index) == done
        and sum("not run (stopped: terminated by SIGTERM)" in r for r in index) == 40 - done
    )
    rerun = subprocess.run(cmd, capture_output=True, text=True, env=envv, timeout=300)
    assert rerun.returncode == 0, rerun.stderr[-2000:]
    assert f"{40 - done} written, {done} skipped" in rerun.stdout, rerun.stdout
    assert len(list(out.glob("*_scale.json"))) == 40


# ---------------------------------------------------------------- faults: NaN gradients and weights


def test_nan_weights_are_never_saved(env, tmp_path, monkeypatch):
    """Weights that become NaN (here: an optimiser step that writes NaN) stop the run before the
    checkpoint; with no checkpoint yet, the message says so instead of claiming one."""
    real_step = torch.optim.Adam.step

    def nan_step(self, *a, **k):
        r = real_step(self, *a, **k)
        with torch.no_grad():
            self.param_groups[0]["params"][0].fill_(float("nan"))
        return r

    monkeypatch.setattr(torch.optim.Adam, "step", nan_step)
    cfg = training.TrainConfig(
        data=str(env["photos"]),
        out=str(tmp_path / "run"),
        width=0.125,
        feature_dim=16,
        image_size=64,
        steps=2,
        batch_size=2,
        holdout_every=3,
        val_pairs=2,
        workers=0,
        threads=1,
        amp="off",
        ckpt_every=1,
    )
    with pytest.raises(training.TrainingDiverged, match="no checkpoint had been written yet"):
        training.train(cfg)
    assert not (tmp_path / "run" / "last.pt").exists() and not (tmp_path / "run" / "model.pt").exists()


def test_nan_gradients_with_finite_loss_do_not_reach_the_checkpoint(env, tmp_path, monkeypatch):
    real_backward = torch.Tensor.backward

    def nan_backward(self, *a, **k):
        real_backward(self, *a, **k)
        for p in model_params:
            if p.grad is not None:
                p.grad.fill_(float("nan"))

    model_params = []
    real_build = training.TrainConfig.build_model

    def build(self):
        m = real_build(self)
        model_params.extend(m.parameters())
        return m

    monkeypatch.setattr(training.TrainConfig, "build_model", build)
    monkeypatch.setattr(torch.Tensor, "backward", nan_backward)
    cfg = training.TrainConfig(
        data=str(env["photos"]),
        out=str(tmp_path / "run"),
        width=0.125,
        feature_dim=16,
        image_size=64,
        steps=2,
        batch_size=2,
        holdout_every=3,
        val_pairs=2,
        workers=0,
        threads=1,
        amp="off",
        ckpt_every=1,
    )
    training.train(cfg)  # the updates are skipped; what is saved is finite
    for name in ("last.pt", "model.pt"):
        load_model(tmp_path / "run" / name)  # refuses NaN/inf weights


@pytest.mark.parametrize("workers", [0, 1])
def test_unusable_training_photos_are_skipped_and_counted(env, tmp_path, capfd, workers):
    d = tmp_path / "photos"
    d.mkdir()
    for p in env["photos"].iterdir():
        (d / p.name).write_bytes(p.read_bytes())
    (d / "p1.png").write_bytes((env["photos"] / "p1.png").read_bytes()[:150])  # truncated
    cv2.imwrite(str(d / "p4.png"), _smooth_image(50, 24, 24))  # smaller than a crop
    argv = TRAIN_BASE + ["--data", str(d), "--out", str(tmp_path / "run"), "--steps", "4", "--workers", str(workers)]
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = lambda m, c, f, ln, file=None, line=None: print(f"{c.__name__}: {m}", file=sys.stderr)
        assert train_cli.main(argv, model="local") == 0
    err = capfd.readouterr().err  # the worker process warns on the same stderr
    assert "training photo skipped" in err and "p1.png" in err
    assert "training sample(s) were drawn again" in err and "Traceback" not in err
    load_model(tmp_path / "run" / "model.pt")


# ---------------------------------------------------------------- faults: code in checkpoints


@pytest.mark.parametrize("loader", ["load_model", "from_pretrained", "cli", "init_weights", "resume"])
def test_checkpoint_with_code_is_refused_unrun(env, tmp_path, loader, capsys):
    marker = tmp_path / "RAN"
    ck = checkpoint_dict(_api_model(), meta={"note": _WritesMarker(marker)})
    path = tmp_path / ("last.pt" if loader == "resume" else "evil.pt")
    torch.save(ck, path)
    if loader == "load_model":
        with pytest.raises(CheckpointError, match="non-tensor objects"):
            load_model(path)
    elif loader == "from_pretrained":
        with pytest.raises(CheckpointError, match="non-tensor objects"):
            LocalScaleNet.from_pretrained(path)
    elif loader == "cli":
        rc, _, err = _run(
            main,
            [
                "predict",
                str(env["in"] / "a.png"),
                str(env["in"] / "b.png"),
                "-o",
                str(tmp_path / "o"),
                "--local-weights",
                str(path),
            ],
            capsys,
        )
        assert_clean_error(rc, err, "non-tensor objects", tmp_path / "o")
    else:
        extra = ["--init-weights", str(path)] if loader == "init_weights" else []
        rc, _, err = _run(
            lambda a: train_cli.main(a, model="local"),
            TRAIN_BASE + ["--data", str(env["photos"]), "--out", str(tmp_path)] + extra,
            capsys,
        )
        assert_clean_error(rc, err, "non-tensor objects")
    assert not marker.exists()


# ---------------------------------------------------------------- faults: decompression bombs


@pytest.mark.parametrize("name", sorted(BOMBS))
def test_decompression_bomb_is_refused_before_decoding(env, name, monkeypatch):
    """The size is read from the header (PIL, or our parser for .hdr/.pfm/.pam) and refused before
    any byte is decoded, so memory stays bounded whatever the file claims."""
    import resource

    decoded = []
    monkeypatch.setattr(cv2, "imdecode", lambda *a, **k: decoded.append(1))
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(LocalScaleError, match="larger than the limit") as e:
        lio.load_image(env["in"] / name)
    assert "\n" not in str(e.value) and not decoded
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0 < 100 * 1024  # KiB


# ---------------------------------------------------------------- faults: orphaned workers

WORKER_SCRIPT = textwrap.dedent("""
    import os, sys, time
    import torch
    from torch.utils.data import DataLoader, Dataset
    from localscale.training import _single_threaded_worker as init
    if len(sys.argv) > 2:
        init = None   # control: without it the workers outlive a killed parent

    class Slow(Dataset):
        def __len__(self):
            return 10 ** 6
        def __getitem__(self, i):
            with open(os.path.join(sys.argv[1], f"worker-{os.getpid()}"), "w"):
                pass
            time.sleep(60)   # busy in an item: torch's own parent check runs only between items
            return torch.zeros(1)

    if __name__ == "__main__":
        loader = DataLoader(Slow(), batch_size=1, num_workers=2, worker_init_fn=init,
                            multiprocessing_context="spawn")
        for _ in loader:
            pass
""")


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="parent-death signal is Linux-only")
def test_dataloader_workers_die_with_a_killed_parent(tmp_path):
    script = tmp_path / "loader.py"
    script.write_text(WORKER_SCRIPT)
    flags = tmp_path / "pids"
    flags.mkdir()
    p = subprocess.Popen(
        [sys.executable, str(script), str(flags)],
        env=dict(os.environ, OMP_NUM_THREADS="1"),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        t0 = time.time()
        while time.time() - t0 < 120 and len(list(flags.iterdir())) < 2:
            time.sleep(0.1)
        pids = [int(f.name.split("-")[1]) for f in flags.iterdir()]
        assert len(pids) >= 2, "workers did not start"
        p.kill()  # kill -9 the parent
        p.wait()
        t0 = time.time()
        while time.time() - t0 < 5 and any(_alive(pid) for pid in pids):
            time.sleep(0.1)
        assert not any(_alive(pid) for pid in pids), "orphaned DataLoader workers"
    finally:
        if p.poll() is None:
            p.kill()
        for f in flags.iterdir():
            try:
                os.kill(int(f.name.split("-")[1]), signal.SIGKILL)
            except (OSError, ValueError):
                pass


# ---------------------------------------------------------------- eval-hpatches: bad pairs are skipped


def test_eval_hpatches_skips_bad_pairs_and_writes_the_rest(env, tmp_path, capsys):
    root = tmp_path / "seqs"
    good = _smooth_image(60, 96, 128)
    variants = {
        "v_good": None,
        "v_trunc": "trunc",
        "v_tiny": "tiny",
        "v_nan": "nanH",
        "v_garbage": "garbage",
        "v_outside": "outside",
        "v_size": "size",
    }
    for name, kind in variants.items():
        s = root / name
        s.mkdir(parents=True)
        cv2.imwrite(str(s / "1.png"), good)
        cv2.imwrite(str(s / "2.png"), good)
        (s / "H_1_2").write_text("1 0 0\n0 1 0\n0 0 1\n")
        if kind == "trunc":
            (s / "2.png").write_bytes((s / "1.png").read_bytes()[:200])
        elif kind == "tiny":
            cv2.imwrite(str(s / "2.png"), good[:8, :8])
        elif kind == "nanH":
            (s / "H_1_2").write_text("nan 0 0\n0 1 0\n0 0 1\n")
        elif kind == "garbage":
            (s / "H_1_2").write_text("hello\n")
        elif kind == "outside":
            (s / "H_1_2").write_text("1 0 10000\n0 1 0\n0 0 1\n")
        elif kind == "size":  # image 2 at half the size H_1_2 was measured on
            cv2.imwrite(str(s / "2.png"), cv2.resize(good, (64, 48), interpolation=cv2.INTER_AREA))
    out = tmp_path / "out"
    rc, stdout, err = _run(
        main,
        [
            "eval-hpatches",
            str(root),
            "-o",
            str(out),
            "--methods",
            "none",
            "--descriptor",
            "sift",
            "--num-features",
            "100",
        ],
        capsys,
    )
    assert rc == 0 and "Traceback" not in err
    doc = json.loads((out / "results_hardnet-sift.json").read_text())
    skipped = {s["pair"] for s in doc["skipped"]}
    assert skipped == {"v_trunc/1-2", "v_tiny/1-2", "v_nan/1-2", "v_garbage/1-2", "v_outside/1-2"}
    assert {r["pair"] for r in doc["records"]} == {"v_good/1-2", "v_size/1-2"}
    assert "v_size/1-2" in doc["suspicious"]  # warned, not silently scored
    warned = [ln for ln in err.splitlines() if ln.startswith("warning:")]
    assert any("v_size/1-2" in ln and "does not look like" in ln for ln in warned)
    assert sum("skipped:" in ln for ln in warned) == 5


# ---------------------------------------------------------------- no silent wrong output from a broken model


def _nan_global_prediction(monkeypatch):
    from localscale.models.scalenet import ScaleNet as _S

    real = _S.predict

    def nan_predict(self, *a, **k):
        p = real(self, *a, **k)
        p.scale = p.scale_ab = float("nan")
        return p

    monkeypatch.setattr(_S, "predict", nan_predict)


@pytest.mark.parametrize("cmd", ["scale --json", "scale", "rectify"])
def test_non_finite_global_scale_is_an_error_not_output(env, tmp_path, monkeypatch, capsys, cmd):
    _nan_global_prediction(monkeypatch)
    out = tmp_path / "out"
    argv = (
        cmd.split()
        + [str(env["in"] / "a.png"), str(env["in"] / "b.png"), "--global-weights", str(env["in"] / "global.pt")]
        + (["-o", str(out)] if cmd == "rectify" else [])
    )
    rc, stdout, err = _run(main, argv, capsys)
    assert_clean_error(rc, err, "non-finite scale", out)
    assert "NaN" not in stdout and "nan" not in stdout


def test_non_finite_scale_map_is_not_written(env, tmp_path, capsys, monkeypatch):
    from localscale.models.local import LocalScaleNet as _L

    real = _L._readout

    def nan_readout(self, *a, **k):
        p = real(self, *a, **k)
        p.scale[0, 0] = np.nan
        return p

    monkeypatch.setattr(_L, "_readout", nan_readout)
    out = tmp_path / "out"
    rc, _, err = _run(
        main,
        [
            "predict",
            str(env["in"] / "a.png"),
            str(env["in"] / "b.png"),
            "-o",
            str(out),
            "--local-weights",
            str(env["in"] / "local.pt"),
        ],
        capsys,
    )
    assert_clean_error(rc, err, "not finite", out)


def test_long_image_names_give_output_names_within_the_limit(env, tmp_path, capsys):
    d = tmp_path / "imgs"
    d.mkdir()
    names = ["a" * 200 + ".png", "b" * 200 + ".png"]
    for i, n in enumerate(names):
        cv2.imwrite(str(d / n), _smooth_image(70 + i))
    (d / "pairs.txt").write_text(f"{names[0]}\t{names[1]}\n")
    out = tmp_path / "out"
    rc, stdout, err = _run(
        main,
        ["predict", "--pairs", str(d / "pairs.txt"), "-o", str(out), "--local-weights", str(env["in"] / "local.pt")],
        capsys,
    )
    assert rc == 0, err
    files = [f.name for f in out.iterdir()]
    assert len(files) == 6 and all(len(f.encode()) <= 255 for f in files)  # 4 maps, _scale.json, index.tsv
    rc, stdout, err = _run(
        main,
        [
            "predict",
            str(d / names[0]),
            str(d / names[1]),
            "-o",
            str(out),
            "--local-weights",
            str(env["in"] / "local.pt"),
        ],
        capsys,
    )
    assert rc == 0, err


# ---------------------------------------------------------------- predict --pairs: bad pairs, stale outputs


def _stderr_lines(err: str) -> list[str]:
    return [ln for ln in err.splitlines() if ln.strip()]


def test_bad_pairs_are_warnings_and_the_good_pairs_complete(env, tmp_path, capsys):
    d = tmp_path / "imgs"
    d.mkdir()
    for n in ("a.png", "b.png"):
        (d / n).write_bytes((env["in"] / n).read_bytes())
    (d / "truncated.png").write_bytes((env["in"] / "truncated.png").read_bytes())
    long_name = "x" * 100_000 + ".png"
    lines = [
        "a.png b.png",
        "missing.png b.png",
        "truncated.png b.png",
        "..\tb.png",
        f"{long_name}\tb.png",
        "b.png a.png",
    ]
    (d / "pairs.txt").write_bytes(b"\xef\xbb\xbf" + "\n".join(lines).encode() + b"\n")  # with a byte order mark
    out = tmp_path / "out"
    rc, stdout, err = _run(
        main,
        ["predict", "--pairs", str(d / "pairs.txt"), "-o", str(out), "--local-weights", str(env["in"] / "local.pt")],
        capsys,
    )
    assert rc == 1 and "Traceback" not in err
    err_lines = _stderr_lines(err)
    assert not [ln for ln in err_lines if ln.startswith("error:")], err
    assert all(len(ln) < 1000 for ln in err_lines)  # the 100,000-character name is cut in messages
    warnings_ = [ln for ln in err_lines if ln.startswith("warning: pair ")]
    expected = {1: "file not found", 2: "cannot decode", 3: "is a directory", 4: "File name too long"}
    assert len(warnings_) == len(expected)
    for i, words in expected.items():
        mine = [ln for ln in warnings_ if ln.startswith(f"warning: pair {i} (line {i + 1}) ")]
        assert len(mine) == 1 and words in mine[0], (i, warnings_)
    assert err_lines[-1] == f"warning: 4 of 6 pairs failed, see {out / 'index.tsv'}"
    rows = [r.split("\t") for r in (out / "index.tsv").read_text().splitlines()[1:]]
    assert [r[4].split(":")[0] for r in rows] == ["ok", "error", "error", "error", "error", "ok"]
    assert rows[0][2] == str(d / "a.png")  # the byte order mark is not part of the first name
    for r in (rows[0], rows[5]):
        np.load(out / f"{r[5]}_scale.npy")


def test_pairs_file_with_no_usable_pair_is_one_error_before_the_model_loads(env, tmp_path, capsys):
    d = tmp_path / "imgs"
    d.mkdir()
    (d / "pairs.txt").write_text("".join(f"gone_{i}.jpg also_gone_{i}.jpg\n" for i in range(10_000)))
    out = tmp_path / "out"
    # the weights do not exist: a model loaded before the inputs are checked would say so instead
    rc, stdout, err = _run(
        main,
        [
            "predict",
            "--pairs",
            str(d / "pairs.txt"),
            "-o",
            str(out),
            "--local-weights",
            str(tmp_path / "no_such_weights.pt"),
        ],
        capsys,
    )
    assert_clean_error(rc, err, ["no pair can be run", "pair 0 (line 1)", "file not found", "9999 more"], out)
    assert "warning:" not in err


def test_special_files_are_refused_not_read(env, tmp_path):
    """A named pipe as the pairs file or as an image would block a read forever."""
    d = tmp_path / "imgs"
    d.mkdir()
    os.mkfifo(d / "pipe.txt")
    os.mkfifo(d / "pipe.png")
    (d / "pairs.txt").write_text(f"pipe.png {env['in'] / 'b.png'}\n")
    base = [
        sys.executable,
        "-m",
        "localscale",
        "predict",
        "-o",
        str(tmp_path / "out"),
        "--local-weights",
        str(env["in"] / "local.pt"),
    ]
    for argv, words in [
        (["--pairs", str(d / "pipe.txt")], "pairs file is not a regular file (a named pipe)"),
        (["--pairs", str(d / "pairs.txt")], "not a regular file (a named pipe)"),
        ([str(d / "pipe.png"), str(env["in"] / "b.png")], "not a regular file (a named pipe)"),
    ]:
        r = subprocess.run(
            base + argv, capture_output=True, text=True, timeout=120, env=dict(os.environ, OMP_NUM_THREADS="1")
        )
        assert_clean_error(r.returncode, r.stderr, words, tmp_path / "out")


def test_a_rerun_redoes_pairs_whose_image_or_options_changed(env, tmp_path, capsys):
    d = tmp_path / "imgs"
    d.mkdir()
    cv2.imwrite(str(d / "a.png"), _smooth_image(50))
    cv2.imwrite(str(d / "b.png"), _smooth_image(51))
    cv2.imwrite(str(d / "c.png"), _smooth_image(52))
    (d / "pairs.txt").write_text("a.png b.png\nc.png b.png\n")
    out = tmp_path / "out"
    argv = ["predict", "--pairs", str(d / "pairs.txt"), "-o", str(out), "--local-weights", str(env["in"] / "local.pt")]
    assert _run(main, argv, capsys)[0] == 0
    old = np.load(out / "00000_a_b_scale.npy")
    cv2.imwrite(str(d / "a.png"), _smooth_image(53, 72, 96))  # another image (another size) under the same name
    st = (d / "a.png").stat()
    os.utime(d / "a.png", ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    rc, stdout, _ = _run(main, argv, capsys)
    assert rc == 0 and "1 written, 1 skipped" in stdout
    new = np.load(out / "00000_a_b_scale.npy")
    assert old.shape == (64, 80) and new.shape == (72, 96)
    assert (
        main(
            [
                "predict",
                str(d / "a.png"),
                str(d / "b.png"),
                "-o",
                str(tmp_path / "single"),
                "--no-anchor",
                "--local-weights",
                str(env["in"] / "local.pt"),
            ]
        )
        == 0
    )
    assert np.allclose(new, np.load(tmp_path / "single" / "a_b_scale.npy"), rtol=1e-4, atol=1e-5)
    rc, stdout, _ = _run(main, argv + ["--hard"], capsys)  # another read-out: both redone
    assert rc == 0 and "2 written, 0 skipped" in stdout
    rc, stdout, _ = _run(main, argv + ["--hard"], capsys)
    assert rc == 0 and "0 written, 2 skipped" in stdout


def test_a_full_disk_stops_a_pairs_run_that_a_rerun_resumes(env, tmp_path, monkeypatch, capsys):
    pairs = _pairs_setup(env, tmp_path, n=3)
    out = tmp_path / "out"
    argv = [
        "predict",
        "--pairs",
        str(pairs),
        "-o",
        str(out),
        "--local-weights",
        str(env["in"] / "local.pt"),
        "--batch-size",
        "1",
    ]
    real_save = np.save
    calls = {"n": 0}

    def disk_full_after_the_first_pair(f, arr, *a, **k):
        calls["n"] += 1
        if calls["n"] > 1:  # pair 0's scale map was saved; the disk is full from then on
            f.write(b"\x93NUMPY partial")
            raise OSError(28, "No space left on device")
        return real_save(f, arr, *a, **k)

    monkeypatch.setattr(np, "save", disk_full_after_the_first_pair)
    rc, stdout, err = _run(main, argv, capsys)
    assert_clean_error(rc, err, ["No space left on device", "a rerun resumes"])
    assert len([ln for ln in err.splitlines() if ln.startswith("warning: pair ")]) == 1  # it stopped at once
    assert not [f for f in out.iterdir() if f.name.startswith(".")]
    rows = [r.split("\t") for r in (out / "index.tsv").read_text().splitlines()[1:]]
    assert [r[4].split(" ")[0] for r in rows] == ["ok", "error:", "not"]
    monkeypatch.setattr(np, "save", real_save)
    rc, stdout, err = _run(main, argv, capsys)
    assert rc == 0 and "2 written, 1 skipped" in stdout, err


def test_pairs_that_all_fail_while_running_are_one_error_and_nothing_written(env, tmp_path, capsys):
    d = tmp_path / "imgs"
    d.mkdir()
    for n in ("c1.png", "c2.png"):  # they pass the up-front check (regular, not empty) but do not decode
        (d / n).write_bytes((env["in"] / "truncated.png").read_bytes())
    (d / "pairs.txt").write_text("c1.png c2.png\nc2.png c1.png\n")
    out = tmp_path / "out"
    rc, stdout, err = _run(
        main,
        ["predict", "--pairs", str(d / "pairs.txt"), "-o", str(out), "--local-weights", str(env["in"] / "local.pt")],
        capsys,
    )
    assert_clean_error(rc, err, ["all 2 pairs failed", "nothing written"], out)
    assert len([ln for ln in err.splitlines() if ln.startswith("warning: pair ") and "cannot decode" in ln]) == 2


# ---------------------------------------------------------------- images that are valid and must give a map

FLOAT_TIFFS = {
    "float32-rgb": (np.float32, False, 1.0),
    "float16-rgb": (np.float16, False, 1.0),
    "float64-gray": (np.float64, True, 1.0),
    "float32-rgb-0-255": (np.float32, False, 255.0),
}


@pytest.mark.parametrize("kind", sorted(FLOAT_TIFFS))
def test_float_tiff_gives_a_map(env, tmp_path, capsys, kind):
    tifffile = pytest.importorskip("tifffile")
    dtype, gray, top = FLOAT_TIFFS[kind]
    img = _smooth_image(7)[..., ::-1].astype(np.float64) / 255  # 64 x 80 RGB in [0, 1]
    img = img[..., 0] if gray else img
    a = tmp_path / "f.tif"
    tifffile.imwrite(a, (img * top).astype(dtype), photometric="minisblack" if gray else "rgb")
    out = tmp_path / "out"
    rc, stdout, err = _run(
        main,
        ["predict", str(a), str(env["in"] / "a.png"), "-o", str(out), "--local-weights", str(env["in"] / "local.pt")],
        capsys,
    )
    assert rc == 0 and "error:" not in err, err
    assert np.load(out / "f_a_scale.npy").shape == (64, 80)


@pytest.mark.parametrize("shape", [(40, 4000), (4000, 40)])
def test_a_thin_strip_gives_a_map_of_its_size(tmp_path, capsys, shape):
    """A strip (a panorama slice) with the bundled model: its size is checked on the file, not on
    the reduced decode, and the map comes back at the image's size."""
    rng = np.random.default_rng(1)
    big = cv2.resize(
        rng.integers(0, 256, (shape[0] // 4, shape[1] // 4, 3), dtype=np.uint8),
        shape[::-1],
        interpolation=cv2.INTER_CUBIC,
    )
    a, b = tmp_path / "strip_a.png", tmp_path / "strip_b.png"
    cv2.imwrite(str(a), big)
    cv2.imwrite(str(b), np.roll(big, 3, axis=int(np.argmax(shape))))
    out = tmp_path / "out"
    rc, stdout, err = _run(main, ["predict", str(a), str(b), "-o", str(out)], capsys)
    assert rc == 0 and "error:" not in err, err
    for kind in ("scale", "confidence"):
        m = np.load(out / f"strip_a_strip_b_{kind}.npy")
        assert m.shape == shape and np.isfinite(m).all()


ACCEPT_DAMAGED = {
    "predict": ["predict", "{in}/damaged.jpg", "{in}/b.png", "-o", "{out}", "--local-weights", "{in}/local.pt"],
    "show": ["show", "{in}/damaged.jpg", "{in}/b.png", "-o", "{out}", "--local-weights", "{in}/local.pt"],
    "scale": ["scale", "{in}/damaged.jpg", "{in}/b.png", "--global-weights", "{in}/global.pt"],
    "rectify": ["rectify", "{in}/a.png", "{in}/damaged.jpg", "-o", "{out}", "--global-weights", "{in}/global.pt"],
    "match": ["match", "{in}/a.png", "{in}/damaged.jpg", "-o", "{out}", "--correction", "none", "--descriptor", "sift"],
}


@pytest.mark.parametrize("cmd", sorted(ACCEPT_DAMAGED))
def test_damaged_jpeg_is_read_with_accept_damaged(env, tmp_path, capsys, cmd):
    """Without the flag the damaged file is one error (the CLI table above); with it, it is decoded
    with a 'warning:' line naming the damage."""
    out = tmp_path / "out"
    argv = [_fill(a, env, out) for a in ACCEPT_DAMAGED[cmd]] + ["--accept-damaged"]
    rc, stdout, err = _run(main, argv, capsys)
    assert rc == 0 and "error:" not in err, err
    assert any(line.startswith("warning:") and "premature end" in line for line in err.splitlines()), err
    assert "UserWarning" not in err


EMPTY_OUT = {
    "predict": ["predict", "{in}/a.png", "{in}/b.png", "--local-weights", "{in}/local.pt"],
    "predict-pairs": ["predict", "--pairs", "{in}/pairs_ok.txt", "--local-weights", "{in}/local.pt"],
    "show": ["show", "{in}/a.png", "{in}/b.png", "--local-weights", "{in}/local.pt"],
    "demo": ["demo", "--local-weights", "{in}/local.pt"],
    "rectify": ["rectify", "{in}/a.png", "{in}/b.png", "--global-weights", "{in}/global.pt"],
    "match": ["match", "{in}/a.png", "{in}/b.png", "--correction", "none", "--descriptor", "sift"],
    "eval-hpatches": ["eval-hpatches", "{hp}", "--methods", "none", "--descriptor", "sift"],
}


@pytest.mark.parametrize("cmd", sorted(EMPTY_OUT))
def test_empty_output_folder_name_is_an_error(env, tmp_path, capsys, monkeypatch, cmd):
    """``-o ''`` is not the current folder: one error, nothing written there."""
    here = tmp_path / "cwd"
    here.mkdir()
    monkeypatch.chdir(here)
    rc, _, err = _run(main, [_fill(a, env, tmp_path / "unused") for a in EMPTY_OUT[cmd]] + ["-o", ""], capsys)
    assert_clean_error(rc, err, "empty output folder name")
    assert not any(here.iterdir()), list(here.iterdir())
