import argparse
import json

import cv2
import numpy as np
import pytest
import torch

import localscale.cli as cli
from localscale import LocalScaleNet, ScaleNet, loading
from localscale.checkpoint import save_model
from localscale.cli import main
from localscale.core.errors import LocalScaleError
from localscale.core.outputs import ensure_not_input
from localscale.maps.files import write_scale_map

TINY = dict(width=0.125, feature_dim=16, image_size=64)


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    d = tmp_path_factory.mktemp("models")
    torch.manual_seed(0)
    save_model(LocalScaleNet(**TINY), d / "local.pt")
    save_model(ScaleNet(**TINY), d / "global.pt")
    return d


@pytest.fixture(scope="module")
def pair(tmp_path_factory, photos):
    d = tmp_path_factory.mktemp("pair")
    a = photos["coffee"]
    H = np.array([[1.5, 0.1, -40], [0.0, 1.4, -30], [0.0004, 0.0, 1.0]])
    b = cv2.warpPerspective(a, H, (a.shape[1], a.shape[0]))
    cv2.imwrite(str(d / "a.png"), a[..., ::-1])
    cv2.imwrite(str(d / "b.jpg"), b[..., ::-1])
    np.savetxt(d / "H", H)
    return d


@pytest.fixture(scope="module")
def seqs(tmp_path_factory, photos):
    """Two small sequences in HPatches layout (``<seq>/1.png``, ``2.png``, ``H_1_2``): same stems."""
    root = tmp_path_factory.mktemp("seqs")
    H = np.array([[1.6, 0.0, -30.0], [0.0, 1.6, -20.0], [0.0, 0.0, 1.0]])
    for name in ("v_coffee", "v_chelsea"):
        a = cv2.resize(photos[name[2:]], (160, 120), interpolation=cv2.INTER_AREA)
        b = cv2.warpPerspective(a, H, (160, 120))
        (root / name).mkdir()
        cv2.imwrite(str(root / name / "1.png"), a[..., ::-1])
        cv2.imwrite(str(root / name / "2.png"), b[..., ::-1])
        np.savetxt(root / name / "H_1_2", H)
    return root


def one_line_error(capsys, *words):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:"), err
    for w in words:
        assert w in err[0], err
    return err[0]


# ---------------------------------------------------------------- predict


def test_predict_writes_npy_tiff_png(models, pair, tmp_path):
    rc = main(
        [
            "predict",
            str(pair / "a.png"),
            str(pair / "b.jpg"),
            "-o",
            str(tmp_path),
            "--local-weights",
            str(models / "local.pt"),
        ]
    )
    assert rc == 0
    s = np.load(tmp_path / "a_b_scale.npy")
    assert s.shape == (400, 600) and s.dtype == np.float32
    tif = cv2.imread(str(tmp_path / "a_b_scale.tif"), cv2.IMREAD_UNCHANGED)
    assert tif.dtype == np.float32 and np.allclose(tif, s)
    png = cv2.imread(str(tmp_path / "a_b_scale.png"))
    assert png.shape == (400, 600, 3)


def test_predict_search_writes_the_searched_map_and_says_what_it_kept(pair, tmp_path, capsys):
    rc = main(["predict", str(pair / "a.png"), str(pair / "b.jpg"), "-o", str(tmp_path), "--search"])
    assert rc == 0
    err = capsys.readouterr().err
    assert "window pairs scored; kept" in err
    s = np.load(tmp_path / "a_b_scale.npy")
    assert s.shape == (400, 600) and np.isfinite(s).all()


@pytest.mark.parametrize(
    "extra,words",
    [
        (["--hard"], "--search uses the soft read-out"),
        (["--local-weights", "UNCAL"], "needs a calibrated Local-ScaleNet"),
    ],
)
def test_predict_search_refuses_what_it_cannot_do(models, pair, tmp_path, capsys, extra, words):
    extra = [str(models / "local.pt") if e == "UNCAL" else e for e in extra]
    assert main(["predict", str(pair / "a.png"), str(pair / "b.jpg"), "-o", str(tmp_path), "--search", *extra]) == 2
    one_line_error(capsys, words)


def test_scale_search_runs_scalenet_on_the_kept_windows(pair, capsys):
    assert main(["scale", str(pair / "a.png"), str(pair / "b.jpg"), "--search", "--json"]) == 0
    out = capsys.readouterr()
    assert "window pairs scored; ScaleNet on" in out.err
    assert json.loads(out.out)["scale"] > 0


def test_match_with_the_searched_correction(pair, tmp_path):
    assert (
        main(
            [
                "match",
                str(pair / "a.png"),
                str(pair / "b.jpg"),
                "-o",
                str(tmp_path),
                "--correction",
                "searched",
                "--H",
                str(pair / "H"),
                "--num-features",
                "150",
                "--descriptor",
                "sift",
            ]
        )
        == 0
    )
    assert len(np.load(tmp_path / "matches.npz")["matches"]) > 0


def test_predict_search_is_for_one_pair(models, seqs, tmp_path, capsys):
    (seqs / "p.txt").write_text("v_coffee/1.png v_coffee/2.png\n")
    assert main(["predict", "--pairs", str(seqs / "p.txt"), "-o", str(tmp_path), "--search"]) == 2
    one_line_error(capsys, "--search works on one pair")


def test_deprecated_model_option_still_names_the_checkpoint(models, pair, tmp_path, capsys):
    assert (
        main(
            [
                "predict",
                str(pair / "a.png"),
                str(pair / "b.jpg"),
                "-o",
                str(tmp_path),
                "--model",
                str(models / "global.pt"),
            ]
        )
        == 2
    )
    one_line_error(capsys, "is a ScaleNet, expected a LocalScaleNet")


def test_predict_same_stems_get_the_folder_name(models, seqs, tmp_path):
    a, b = seqs / "v_coffee" / "1.png", seqs / "v_chelsea" / "1.png"
    assert main(["predict", str(a), str(b), "-o", str(tmp_path), "--local-weights", str(models / "local.pt")]) == 0
    assert (tmp_path / "v_coffee-1_v_chelsea-1_scale.npy").is_file()


def test_pairs_file_indices_are_positions_and_index_tsv_maps_outputs(models, seqs, tmp_path, capsys):
    pairs = tmp_path / "pairs.txt"
    pairs.write_text(
        "# header\nv_coffee/1.png v_coffee/2.png\nv_coffee/1.png v_coffee/missing.png\n\n"
        "v_chelsea/1.png v_chelsea/2.png\n"
    )
    (seqs / "pairs.txt").write_text(pairs.read_text())
    out = tmp_path / "out"
    rc = main(
        ["predict", "--pairs", str(seqs / "pairs.txt"), "-o", str(out), "--local-weights", str(models / "local.pt")]
    )
    assert rc == 1
    err = capsys.readouterr().err
    assert "missing.png" in err and "file not found" in err
    names = sorted(p.name for p in out.glob("*_scale.npy"))
    # the failed pair keeps its index 1: the next pair is 00002, and the sequences are told apart
    assert names == ["00000_v_coffee-1_v_coffee-2_scale.npy", "00002_v_chelsea-1_v_chelsea-2_scale.npy"]
    rows = [r.split("\t") for r in (out / "index.tsv").read_text().splitlines()]
    assert rows[0][:5] == ["index", "line", "image_a", "image_b", "status"]
    assert [r[0] for r in rows[1:]] == ["0", "1", "2"] and [r[1] for r in rows[1:]] == ["2", "3", "5"]
    assert rows[1][2].endswith("v_coffee/1.png") and rows[1][3].endswith("v_coffee/2.png")
    assert [r[4].split(":")[0] for r in rows[1:]] == ["ok", "error", "ok"]
    assert rows[3][5] == "00002_v_chelsea-1_v_chelsea-2" and rows[3][2].endswith("v_chelsea/1.png")


def test_pairs_file_honours_hard_planar_and_counts_encodings(models, pair, tmp_path, capsys):
    pairs = tmp_path / "pairs.txt"
    pairs.write_text(f"{pair}/a.png {pair}/b.jpg\n{pair}/b.jpg {pair}/a.png\n")
    w = ["--local-weights", str(models / "local.pt")]
    assert main(["predict", "--pairs", str(pairs), "-o", str(tmp_path / "soft")] + w) == 0
    assert "2 images encoded, 2 reused" in capsys.readouterr().out
    assert main(["predict", "--pairs", str(pairs), "-o", str(tmp_path / "hp"), "--hard", "--planar"] + w) == 0
    assert (
        main(
            ["predict", str(pair / "a.png"), str(pair / "b.jpg"), "-o", str(tmp_path / "single"), "--hard", "--planar"]
            + ["--no-anchor"]
            + w
        )
        == 0
    )
    soft = np.load(tmp_path / "soft" / "00000_a_b_scale.npy")
    hp = np.load(tmp_path / "hp" / "00000_a_b_scale.npy")
    single = np.load(tmp_path / "single" / "a_b_scale.npy")
    assert not np.allclose(soft, hp)
    assert np.allclose(hp, single, rtol=1e-3, atol=1e-4)


def test_pairs_file_cache_size_and_bf16_reach_the_cache(models, pair, tmp_path, monkeypatch):
    import localscale.cache as cache_mod

    made = []

    class Spy(cache_mod.FeatureCache):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            made.append(self)

    monkeypatch.setattr(cache_mod, "FeatureCache", Spy)
    pairs = tmp_path / "pairs.txt"
    pairs.write_text(f"{pair}/a.png {pair}/b.jpg\n")
    assert (
        main(
            [
                "predict",
                "--pairs",
                str(pairs),
                "-o",
                str(tmp_path / "o"),
                "--cache-mb",
                "3",
                "--bf16",
                "--local-weights",
                str(models / "local.pt"),
            ]
        )
        == 0
    )
    assert len(made) == 1 and made[0].max_bytes == 3 * 2**20 and made[0].bf16 and made[0].misses == 2


# ---------------------------------------------------------------- show, demo


def test_show_writes_into_the_output_folder(models, pair, tmp_path, capsys):
    out = tmp_path / "figs"  # does not exist yet
    rc = main(
        [
            "show",
            str(pair / "a.png"),
            str(pair / "b.jpg"),
            "-o",
            str(out) + "/",
            "--H",
            str(pair / "H"),
            "--local-weights",
            str(models / "local.pt"),
        ]
    )
    assert rc == 0
    fig = out / "a_b_figure.png"
    assert cv2.imread(str(fig)) is not None and not (out / ".png").exists()
    assert capsys.readouterr().out.strip() == str(fig)


def test_output_must_not_be_an_input(pair, tmp_path):
    with pytest.raises(LocalScaleError, match="refusing to overwrite"):
        ensure_not_input(tmp_path / ".." / tmp_path.name / "a.png", [tmp_path / "a.png"])
    ensure_not_input(tmp_path / "b.png", [tmp_path / "a.png", None])


# ---------------------------------------------------------------- scale, rectify


def test_scale(models, pair, capsys):
    assert main(["scale", str(pair / "a.png"), str(pair / "b.jpg"), "--global-weights", str(models / "global.pt")]) == 0
    assert "S(A->B)" in capsys.readouterr().out
    assert (
        main(
            ["scale", str(pair / "a.png"), str(pair / "b.jpg"), "--json", "--global-weights", str(models / "global.pt")]
        )
        == 0
    )
    assert json.loads(capsys.readouterr().out)["scale"] > 0


def test_rectify_names_outputs_per_sequence_and_writes_a_record(models, seqs, tmp_path):
    w = ["--global-weights", str(models / "global.pt")]
    for s in ("v_coffee", "v_chelsea"):
        assert main(["rectify", str(seqs / s / "1.png"), str(seqs / s / "2.png"), "-o", str(tmp_path)] + w) == 0
    images = sorted(tmp_path.glob("*_rectified_*.png"))
    assert len(images) == 2 and {p.name.split("_rectified")[0] for p in images} == {
        "v_coffee-1_v_coffee-2",
        "v_chelsea-1_v_chelsea-2",
    }
    rec = json.loads((tmp_path / "v_coffee-1_v_coffee-2_rectified.json").read_text())
    assert rec["resized"] in ("A", "B") and rec["output"].endswith(f"_rectified_{rec['resized']}.png")
    img = cv2.imread(rec["output"])
    assert [img.shape[1], img.shape[0]] == rec["size_after"]
    f = rec["factor"]
    assert rec["size_after"] == [max(1, round(v * f)) for v in rec["size_before"]]
    assert rec["resized_image"].endswith(f"{'1' if rec['resized'] == 'A' else '2'}.png")
    assert np.isclose(f, rec["scale"] if rec["resized"] == "A" else 1 / rec["scale"])


def test_rectify_failed_write_is_an_error(models, seqs, tmp_path, capsys):
    for w in "AB":  # a folder where the image should go: cv2.imwrite fails
        (tmp_path / f"v_coffee-1_v_coffee-2_rectified_{w}.png").mkdir()
    assert (
        main(
            [
                "rectify",
                str(seqs / "v_coffee" / "1.png"),
                str(seqs / "v_coffee" / "2.png"),
                "-o",
                str(tmp_path),
                "--global-weights",
                str(models / "global.pt"),
            ]
        )
        == 2
    )
    one_line_error(capsys, "cannot write", "rectified")


# ---------------------------------------------------------------- match


def test_match_fused_loads_the_given_models(models, pair, tmp_path, monkeypatch):
    calls = []
    real = loading.load_scale_model
    monkeypatch.setattr(
        loading, "load_scale_model", lambda kind, w=None, d="cpu": calls.append((kind, w, d)) or real(kind, w, d)
    )
    L, G = str(models / "local.pt"), str(models / "global.pt")
    assert (
        main(
            [
                "match",
                str(pair / "a.png"),
                str(pair / "b.jpg"),
                "-o",
                str(tmp_path),
                "--correction",
                "fused",
                "--descriptor",
                "sift",
                "--num-features",
                "64",
                "--local-weights",
                L,
                "--global-weights",
                G,
                "--device",
                "cpu:0",
            ]
        )
        == 0
    )
    assert calls == [("local", L, "cpu:0"), ("global", G, "cpu:0")]
    assert (tmp_path / "matches.npz").is_file() and (tmp_path / "matches.png").is_file()


@pytest.mark.parametrize(
    "correction,flag",
    [
        ("fused", "--local-weights"),
        ("fused", "--global-weights"),
        ("global", "--global-weights"),
        ("local", "--local-weights"),
    ],
)
def test_match_missing_weights_is_an_error(correction, flag, pair, tmp_path, capsys):
    assert (
        main(
            [
                "match",
                str(pair / "a.png"),
                str(pair / "b.jpg"),
                "-o",
                str(tmp_path),
                "--correction",
                correction,
                "--descriptor",
                "sift",
                "--num-features",
                "32",
                flag,
                str(tmp_path / "nope.pt"),
            ]
        )
        == 2
    )
    one_line_error(capsys, "checkpoint not found", "nope.pt")
    assert not (tmp_path / "matches.npz").exists()


def test_match_failed_write_is_an_error(pair, tmp_path, capsys):
    (tmp_path / "matches.png").mkdir()  # cv2.imwrite cannot write there
    assert (
        main(
            [
                "match",
                str(pair / "a.png"),
                str(pair / "b.jpg"),
                "-o",
                str(tmp_path),
                "--correction",
                "none",
                "--descriptor",
                "sift",
                "--num-features",
                "32",
            ]
        )
        == 2
    )
    one_line_error(capsys, "cannot write", "matches.png")


# ---------------------------------------------------------------- shared options


def _spy_loader(monkeypatch, models):
    """Replace the CLI's model loader: record (kind, weights, device) and whether each encoder
    pass ran under bfloat16 autocast."""
    calls, autocast = [], []
    real = loading.load_scale_model

    def loader(kind, weights=None, device="cpu"):
        calls.append((kind, weights, device))
        m = real(kind, str(models / f"{kind}.pt"), device)
        enc = m.encode
        m.encode = lambda x: autocast.append(torch.is_autocast_enabled("cpu")) or enc(x)
        return m

    monkeypatch.setattr(loading, "load_scale_model", loader)
    return calls, autocast


def _commands(pair, seqs, tmp_path):
    a, b = str(pair / "a.png"), str(pair / "b.jpg")
    pairs = tmp_path / "pairs.txt"
    pairs.write_text(f"{a} {b}\n")
    m = ["--descriptor", "sift", "--num-features", "32"]
    return {  # argv, models the command needs, whether --bf16 exists
        "predict": ([a, b], ["local"], True),
        "predict --pairs": (["--pairs", str(pairs)], ["local"], True),
        "show": ([a, b], ["local"], True),
        "demo": ([], ["local"], True),
        "scale": ([a, b], ["global"], True),
        "rectify": ([a, b], ["global"], True),
        "match local": ([a, b, "--correction", "local"] + m, ["local"], True),
        "match global": ([a, b, "--correction", "global"] + m, ["global"], True),
        "match fused": ([a, b, "--correction", "fused"] + m, ["local", "global"], True),
        "eval-hpatches": (
            [str(seqs), "--methods", "none", "local", "global", "fused"] + m[2:],
            ["local", "global"],
            False,
        ),
    }


COMMANDS = [
    "predict",
    "predict --pairs",
    "show",
    "demo",
    "scale",
    "rectify",
    "match local",
    "match global",
    "match fused",
    "eval-hpatches",
]


@pytest.mark.parametrize("name", COMMANDS)
def test_weight_device_precision_flags_reach_the_models(name, models, pair, seqs, tmp_path, monkeypatch):
    argv, kinds, has_bf16 = _commands(pair, seqs, tmp_path)[name]
    calls, autocast = _spy_loader(monkeypatch, models)
    weights = {k: str(tmp_path / f"my_{k}.pt") for k in kinds}
    flags = [x for k in kinds for x in (f"--{k}-weights", weights[k])] + ["--device", "cpu:0"]
    flags += ["--bf16"] if has_bf16 else []
    out = [] if name == "scale" else ["-o", str(tmp_path / "out")]
    assert main([name.split()[0]] + argv + out + flags) == 0
    assert sorted(calls) == sorted((k, weights[k], "cpu:0") for k in kinds)
    assert autocast and all(autocast) == has_bf16 and any(autocast) == has_bf16
    if has_bf16:  # and without --bf16 nothing runs under autocast
        calls.clear(), autocast.clear()
        redo = ["--overwrite"] if name == "predict --pairs" else []  # a rerun skips complete pairs
        assert main([name.split()[0]] + argv + out + flags[:-1] + redo) == 0
        assert autocast and not any(autocast)


@pytest.mark.parametrize(
    "device,msg", [("banana", "unknown device 'banana'"), ("cuda", "no CUDA device"), ("cuda:1", "no CUDA device")]
)
@pytest.mark.parametrize("name", ["predict", "show", "scale", "rectify", "match fused", "eval-hpatches"])
def test_bad_device_is_a_one_line_error(name, device, msg, pair, seqs, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    argv, _, _ = _commands(pair, seqs, tmp_path)[name]
    out = [] if name == "scale" else ["-o", str(tmp_path / "out")]
    assert main([name.split()[0]] + argv + out + ["--device", device]) == 2
    one_line_error(capsys, msg)


@pytest.mark.parametrize(
    "name", ["predict", "predict --pairs", "show", "demo", "rectify", "match fused", "eval-hpatches"]
)
def test_output_that_is_a_file_is_an_error_before_any_work(name, pair, seqs, tmp_path, monkeypatch, capsys):
    argv, _, _ = _commands(pair, seqs, tmp_path)[name]
    (tmp_path / "taken").write_text("keep me")

    def no_loading(*a, **k):
        raise AssertionError("a model was loaded although the output is unusable")

    monkeypatch.setattr(loading, "load_scale_model", no_loading)
    assert main([name.split()[0]] + argv + ["-o", str(tmp_path / "taken")]) == 2
    one_line_error(capsys, "taken", "not a folder")
    assert (tmp_path / "taken").read_text() == "keep me"


def _subcommands():
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    return sub.choices


@pytest.mark.parametrize("name", list(_subcommands()))
def test_help_of_every_subcommand_teaches(name, capsys):
    with pytest.raises(SystemExit) as e:
        main([name, "--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    sp = _subcommands()[name]
    assert sp.description and sp.description.split("\n")[0][:30] in text
    assert "example" in text and f"localscale {name}" in text.split("example", 1)[1]
    formatter = sp._get_formatter()
    for action in sp._actions:
        if isinstance(action, argparse._HelpAction) or action.help == argparse.SUPPRESS:
            continue
        assert action.help, f"{name}: {action.dest} has no help"
        if action.option_strings and action.nargs != 0:
            assert "default" in formatter._get_help_string(action).lower(), f"{name}: {action.dest} hides its default"
    assert "--device" in text and (name == "scale" or "-o" in text)


def test_weight_options_are_spelled_the_same_everywhere():
    for name, sp in _subcommands().items():
        opts = {o for a in sp._actions for o in a.option_strings if a.help != argparse.SUPPRESS}
        assert "--device" in opts, name
        assert opts & {"--local-weights", "--global-weights"}, name
        assert not opts & {"--local-model", "--global-model", "--model"}, name


# ---------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "args,msg",
    [
        (["predict", "nope_a.png", "nope_b.png"], "file not found"),
        (["show", "x.png", "y.png", "--local-weights", "missing.pt"], "checkpoint not found"),
        (["predict", "--pairs", "no_pairs.txt"], "pairs file not found"),
    ],
)
def test_errors_are_one_line(args, msg, capsys, models, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    extra = ["--local-weights", str(models / "local.pt")] if "--local-weights" not in args else []
    assert main(args + extra) == 2
    one_line_error(capsys, msg)


def test_wrong_architecture_checkpoint(models, pair, tmp_path, capsys):
    assert (
        main(
            [
                "predict",
                str(pair / "a.png"),
                str(pair / "b.jpg"),
                "-o",
                str(tmp_path),
                "--local-weights",
                str(models / "global.pt"),
            ]
        )
        == 2
    )
    assert "is a ScaleNet, expected a LocalScaleNet" in capsys.readouterr().err


def test_visible_map_is_written_when_the_model_predicts_it(tmp_path):
    class Pred:
        scale = np.full((6, 8), 2.0, np.float32)
        confidence = np.ones((6, 8), np.float32)
        visible = np.full((6, 8), 0.25, np.float32)

    paths = write_scale_map(Pred(), tmp_path, "x_y")
    assert tmp_path / "x_y_visible.npy" in paths and np.allclose(np.load(tmp_path / "x_y_visible.npy"), 0.25)
    del Pred.visible
    assert all("visible" not in p.name for p in write_scale_map(Pred(), tmp_path / "old", "x_y"))


def test_matching_names_still_work_from_features_with_a_deprecation_warning():
    import localscale.features as features
    import localscale.matching as matching
    import localscale.matching.correction as correction

    for name in (
        "CorrectionGate",
        "NO_GATE",
        "CORRECTIONS",
        "fuse_local_global",
        "scale_maps_for_pair",
        "match_pair",
        "MatchConfig",
        "Matcher",
    ):
        with pytest.warns(DeprecationWarning, match=f"localscale.matching.{name}"):
            old = getattr(features, name)
        assert old is getattr(matching, name)
    assert matching.CorrectionGate is correction.CorrectionGate
    with pytest.raises(AttributeError):
        _ = features.no_such_name
