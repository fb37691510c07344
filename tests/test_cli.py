import cv2
import numpy as np
import pytest
import torch

from localscale import LocalScaleNet, ScaleNet
from localscale.checkpoint import save_model
from localscale.cli import main

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


def test_predict_writes_npy_tiff_png(models, pair, tmp_path):
    rc = main(["predict", str(pair / "a.png"), str(pair / "b.jpg"), "-o", str(tmp_path), "--model", str(models / "local.pt")])
    assert rc == 0
    s = np.load(tmp_path / "a_b_scale.npy")
    assert s.shape == (400, 600) and s.dtype == np.float32
    tif = cv2.imread(str(tmp_path / "a_b_scale.tif"), cv2.IMREAD_UNCHANGED)
    assert tif.dtype == np.float32 and np.allclose(tif, s)
    png = cv2.imread(str(tmp_path / "a_b_scale.png"))
    assert png.shape == (400, 600, 3)


def test_pairs_file_reports_bad_pair_and_processes_the_rest(models, pair, tmp_path, capsys):
    pairs = tmp_path / "pairs.txt"
    pairs.write_text(f"{pair}/a.png {pair}/b.jpg\n# comment\n{pair}/a.png {pair}/missing.png\n{pair}/b.jpg {pair}/a.png\n")
    rc = main(["predict", "--pairs", str(pairs), "-o", str(tmp_path / "out"), "--model", str(models / "local.pt")])
    assert rc == 1
    err = capsys.readouterr().err
    assert "missing.png" in err and "file not found" in err
    assert len(list((tmp_path / "out").glob("*_scale.npy"))) == 2


def test_show_with_ground_truth(models, pair, tmp_path):
    out = tmp_path / "fig.png"
    rc = main(["show", str(pair / "a.png"), str(pair / "b.jpg"), "-o", str(out), "--H", str(pair / "H"),
               "--model", str(models / "local.pt")])
    assert rc == 0 and cv2.imread(str(out)) is not None


def test_scale_and_rectify(models, pair, tmp_path, capsys):
    assert main(["scale", str(pair / "a.png"), str(pair / "b.jpg"), "--model", str(models / "global.pt")]) == 0
    assert "S(A->B)" in capsys.readouterr().out
    assert main(["rectify", str(pair / "a.png"), str(pair / "b.jpg"), "-o", str(tmp_path),
                 "--model", str(models / "global.pt")]) == 0
    assert len(list(tmp_path.glob("*_rectified.png"))) == 1


@pytest.mark.parametrize("args,msg", [
    (["predict", "nope_a.png", "nope_b.png"], "file not found"),
    (["show", "x.png", "y.png", "--model", "missing.pt"], "checkpoint not found"),
])
def test_errors_are_one_line(args, msg, capsys, models):
    assert main(args + (["--model", str(models / "local.pt")] if "--model" not in args else [])) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and msg in err[0]


def test_wrong_architecture_checkpoint(models, pair, capsys):
    assert main(["predict", str(pair / "a.png"), str(pair / "b.jpg"), "--model", str(models / "global.pt")]) == 2
    assert "is a ScaleNet, expected a LocalScaleNet" in capsys.readouterr().err
