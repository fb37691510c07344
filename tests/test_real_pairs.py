"""Real-pair labels from 3D models: the labels, the samples drawn from them, and training on them."""

import math

import cv2
import numpy as np
import pytest
import torch

from localscale.core.errors import LocalScaleError
from localscale.training import real_pairs as rp


def _similarity(xy, scale, angle_deg, shift):
    a = math.radians(angle_deg)
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    return (scale * xy @ R.T + shift).astype(np.float32)


@pytest.mark.parametrize("scale", [2.5, 1 / 3])
def test_labels_of_a_similarity_are_its_scale(scale):
    rng = np.random.default_rng(0)
    xy_a = rng.uniform([0, 0], [800, 600], (300, 2)).astype(np.float32)
    xy_b = _similarity(xy_a, scale, 30, [40, -20])
    per_point = rp.point_log_scales(xy_a, xy_b)
    assert np.isfinite(per_point).all()
    np.testing.assert_allclose(per_point, math.log(scale), atol=1e-4)
    assert rp.global_log_scale(xy_a, xy_b, rng) == pytest.approx(math.log(scale), abs=1e-4)


def test_per_point_labels_follow_a_zoom_that_changes_across_the_image():
    # B magnifies the left half 2x and the right half 0.5x: each point takes its own side's scale
    rng = np.random.default_rng(1)
    xy_a = rng.uniform([0, 0], [1000, 400], (600, 2)).astype(np.float32)
    left = xy_a[:, 0] < 500
    xy_b = np.where(left[:, None], 2.0 * xy_a, 0.5 * xy_a + [3000, 0]).astype(np.float32)
    per_point = rp.point_log_scales(xy_a, xy_b, k=6)
    far = np.abs(xy_a[:, 0] - 500) > 80
    np.testing.assert_allclose(per_point[left & far], math.log(2), atol=1e-3)
    np.testing.assert_allclose(per_point[~left & far], math.log(0.5), atol=1e-3)


@pytest.mark.parametrize("k", [0, 1, 2, 3, 5])
def test_the_turn_matrix_of_the_training_pairs_is_that_of_rot90(k):
    from localscale.geometry import turn_matrix

    img = np.arange(5 * 7).reshape(5, 7)
    T = turn_matrix(k, (5, 7))
    turned = np.rot90(img, k)
    for y in range(5):
        for x in range(7):
            u, v = (T @ [x, y, 1])[:2]
            assert turned[int(round(v)), int(round(u))] == img[y, x]


def _textured(h, w, seed):
    """A smooth colour texture: every point's colour identifies its neighbourhood."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (h // 16, w // 16, 3)).astype(np.uint8)
    return cv2.GaussianBlur(cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC), (0, 0), 3)


@pytest.fixture(scope="module")
def zoomed_pair(tmp_path_factory):
    """Photo A and B = A enlarged 1.6x (content bigger in B), with 500 shared points."""
    d = tmp_path_factory.mktemp("real")
    a = _textured(480, 640, 0)
    b = cv2.resize(a, (1024, 768), interpolation=cv2.INTER_LINEAR)
    cv2.imwrite(str(d / "a.png"), a[..., ::-1])
    cv2.imwrite(str(d / "b.png"), b[..., ::-1])
    rng = np.random.default_rng(2)
    xy_a = rng.uniform([8, 8], [632, 472], (500, 2)).astype(np.float32)  # COLMAP pixel coordinates
    return rp.CovisiblePair(d / "a.png", d / "b.png", xy_a, (1.6 * xy_a).astype(np.float32), "test")


def _colour_at(img: torch.Tensor, pts: np.ndarray) -> np.ndarray:
    x = np.clip(np.round(pts[:, 0]).astype(int), 0, img.shape[2] - 1)
    y = np.clip(np.round(pts[:, 1]).astype(int), 0, img.shape[1] - 1)
    return img[:, y, x].numpy().T


def test_samples_map_the_points_onto_the_same_content_and_span_the_scales(zoomed_pair):
    ds = rp.RealPairs([zoomed_pair], length=24, seed=0, config=rp.RealPairConfig(image_size=96))
    labels = []
    for i in range(len(ds)):
        item, pa, pb = ds.draw(i)
        ca, cb = _colour_at(item["a"], pa), _colour_at(item["b"], pb)
        same = np.abs(ca - cb).mean()
        shuffled = np.abs(ca - cb[np.random.default_rng(i).permutation(len(cb))]).mean()
        assert same < 0.5 * shuffled, (i, same, shuffled)  # crop, turn and letterbox follow the pixels
        m = item["mask"]
        assert m.any() and not item["valid"].any()
        cells = torch.log(item["scale"][m])
        assert float(cells.std()) < 0.05  # one zoom over the whole image
        assert math.log(item["global_scale"]) == pytest.approx(float(cells.median()), abs=0.05)
        labels.append(math.log(item["global_scale"]))
    assert min(labels) < math.log(1 / 2.5) and max(labels) > math.log(2.5)  # zoom in and out are both drawn


def test_covisible_pairs_of_a_colmap_model(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    rng = np.random.default_rng(3)
    n = 60
    xy_a = rng.uniform(10, 500, (n, 2))
    xy_b = 0.5 * xy_a + 7
    model = tmp_path / "model"
    model.mkdir()
    (model / "cameras.txt").write_text("1 SIMPLE_PINHOLE 640 480 500 320 240\n")
    pts_a = " ".join(f"{x} {y} {i + 1}" for i, (x, y) in enumerate(xy_a))
    pts_b = " ".join(f"{x} {y} {i + 1}" for i, (x, y) in enumerate(xy_b)) + " 5 5 -1"
    (model / "images.txt").write_text(f"1 1 0 0 0 0 0 0 1 a.jpg\n{pts_a}\n2 1 0 0 0 1 0 0 1 b.jpg\n{pts_b}\n")
    (model / "points3D.txt").write_text("".join(f"{i + 1} {i} {i} 5 128 128 128 0.5 1 {i} 2 {i}\n" for i in range(n)))
    rec = pycolmap.Reconstruction(model)
    pairs = rp.covisible_pairs(rec, tmp_path, min_points=50, collection="c")
    assert len(pairs) == 1 and pairs[0].image_a == tmp_path / "a.jpg"
    np.testing.assert_allclose(pairs[0].xy_b, 0.5 * pairs[0].xy_a + 7, atol=1e-3)
    assert rp.covisible_pairs(rec, tmp_path, min_points=61) == []
    rp.save_covisible_pairs(tmp_path / "p.npz", pairs)
    back = rp.load_covisible_pairs(tmp_path / "p.npz")
    np.testing.assert_array_equal(back[0].xy_a, pairs[0].xy_a)
    assert back[0].collection == "c" and back[0].image_b == tmp_path / "b.jpg"


def test_a_file_that_is_not_labels_is_a_clear_error(tmp_path):
    bad = tmp_path / "x.npz"
    bad.write_bytes(b"not an npz")
    with pytest.raises(LocalScaleError, match="not a file of labelled real pairs"):
        rp.load_covisible_pairs(bad)


def test_training_mixes_real_pairs_and_validates_on_them(image_dir, zoomed_pair, tmp_path):
    from test_training import tiny_cfg

    from localscale.training import TrainConfig, train

    labels = tmp_path / "pairs.npz"
    rp.save_covisible_pairs(labels, [zoomed_pair])
    cfg = tiny_cfg(image_dir, tmp_path / "run", steps=2, val_every=2, ckpt_every=2)
    cfg.real_pairs, cfg.real_fraction, cfg.real_val_pairs = str(labels), 0.5, str(labels)
    row = train(cfg)
    assert row["real_mean_r"] > 1 and row["real_baseline_mean_r"] > 1.2
    from localscale.training.loop import _datasets

    kinds = [_datasets(cfg, 1)[0][i]["kind"] for i in range(8)]
    assert rp.REAL_KIND in kinds and any(k != rp.REAL_KIND for k in kinds)
    with pytest.raises(LocalScaleError, match="real-fraction"):
        TrainConfig(real_fraction=1.5).check()


def test_model_card_names_real_pair_collections_licences_and_the_one_left_out(repo_script):
    card = repo_script("train/make_model_card.py")
    cfg = {
        "real_pairs": "runs/real_models/skull_alansartlog/pairs.npz,runs/real_models/new_scene/pairs.npz",
        "real_val_pairs": "runs/real_models/kitchen_vggsfm/pairs.npz",
        "real_fraction": 0.3,
    }
    rec = card.real_pairs_card(cfg)
    assert rec["collections"]["skull_alansartlog"] == "CC BY 4.0"
    assert "SOURCES.md" in rec["collections"]["new_scene"]  # unknown licence: points to the source file
    assert rec["held_out"] == "kitchen_vggsfm"
    assert card.real_pairs_card({"real_pairs": ""}) is None


def test_shipped_local_card_records_its_real_pair_data():
    import json
    from pathlib import Path

    import localscale

    card = json.loads((Path(localscale.__file__).parent / "weights" / "local_scalenet.json").read_text())
    used = [Path(f).parent.name for f in card["training"]["config"]["real_pairs"].split(",") if f]
    rec = card["real_pairs"]
    assert sorted(rec["collections"]) == sorted(used) and all(rec["collections"].values())
    assert rec["held_out"] not in used
