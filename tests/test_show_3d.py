"""``show --refine`` and ``show --colmap-model DIR``: the source layer and the per-point truth of a COLMAP model."""

import cv2
import numpy as np
import pytest

from localscale.cli import main
from localscale.point_truth import shared_point_truth

ZOOM = 2.0


def _write_text_model(d, names, size, xy_a, xy_b):
    """A COLMAP text model: two images (``names``), one pinhole camera, 3D points seen at ``xy_a``, ``xy_b``."""
    d.mkdir(parents=True, exist_ok=True)
    w, h = size
    (d / "cameras.txt").write_text(f"1 PINHOLE {w} {h} 500 500 {w / 2} {h / 2}\n")
    lines = []
    for i, (name, xy) in enumerate(zip(names, (xy_a, xy_b)), start=1):
        lines.append(f"{i} 1 0 0 0 0 0 {i - 1} 1 {name}")
        lines.append(" ".join(f"{x + 0.5:.3f} {y + 0.5:.3f} {k + 1}" for k, (x, y) in enumerate(xy)))
    (d / "images.txt").write_text("\n".join(lines) + "\n")
    pts = [f"{k + 1} {k * 0.01:.2f} 0 5 128 128 128 0.5 1 {k} 2 {k}" for k in range(len(xy_a))]
    (d / "points3D.txt").write_text("\n".join(pts) + "\n")


@pytest.fixture(scope="module")
def zoom_scene(tmp_path_factory, photos):
    """A photo, its centre enlarged 2x, and a COLMAP model whose shared points follow that zoom."""
    d = tmp_path_factory.mktemp("scene")
    a = photos["coffee"]
    h, w = a.shape[:2]
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    M = np.array([[ZOOM, 0, c[0] * (1 - ZOOM)], [0, ZOOM, c[1] * (1 - ZOOM)]])
    b = cv2.warpAffine(a, M, (w, h), flags=cv2.INTER_LINEAR)
    cv2.imwrite(str(d / "a.png"), a[..., ::-1])
    cv2.imwrite(str(d / "b.png"), b[..., ::-1])
    rng = np.random.default_rng(0)
    xy_a = c + rng.uniform(-0.4, 0.4, (60, 2)) * [w / ZOOM, h / ZOOM]
    _write_text_model(d / "sparse", ["a.png", "b.png"], (w, h), xy_a, (xy_a - c) * ZOOM + c)
    return d


def test_shared_point_truth_reads_the_model(zoom_scene):
    xy, truth = shared_point_truth(zoom_scene / "sparse", zoom_scene / "a.png", zoom_scene / "b.png")
    assert xy.shape == (60, 2) and np.allclose(truth, ZOOM, rtol=1e-3)


def test_show_draws_the_source_layer_and_the_point_truth(zoom_scene, tmp_path, capsys):
    out = tmp_path / "figs"
    args = ["show", str(zoom_scene / "a.png"), str(zoom_scene / "b.png"), "-o", str(out)]
    assert main(args + ["--refine", "--colmap-model", str(zoom_scene / "sparse")]) == 0
    fig = cv2.imread(str(out / "a_b_figure.png"))
    assert fig is not None
    plain = tmp_path / "plain"
    assert main(["show", str(zoom_scene / "a.png"), str(zoom_scene / "b.png"), "-o", str(plain)]) == 0
    assert fig.shape[1] > cv2.imread(str(plain / "a_b_figure.png")).shape[1]  # two panels more


@pytest.mark.parametrize("problem", ["missing", "not a model", "image not in it", "too few points"])
def test_show_refuses_a_bad_model(zoom_scene, tmp_path, capsys, problem):
    model = zoom_scene / "sparse"
    image_b = zoom_scene / "b.png"
    if problem == "missing":
        model = tmp_path / "nothing"
    elif problem == "not a model":
        model = tmp_path / "empty"
        model.mkdir()
    elif problem == "image not in it":
        image_b = tmp_path / "c.png"
        cv2.imwrite(str(image_b), np.zeros((40, 40, 3), np.uint8))
    else:
        xy = np.array([[10.0, 10.0], [20.0, 10.0], [10.0, 20.0]])
        model = tmp_path / "few"
        _write_text_model(model, ["a.png", "b.png"], (400, 300), xy, xy)
    out = tmp_path / "out"
    rc = main(["show", str(zoom_scene / "a.png"), str(image_b), "-o", str(out), "--colmap-model", str(model)])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("error: ") and "--colmap-model" in err and len(err.strip().splitlines()) == 1
    assert not out.exists() or not any(out.iterdir())
