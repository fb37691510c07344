"""Whether a model places its images right (localscale.sfm.placement): a known similarity-transformed
model, misplaced photos and close-ups, the references read from files."""

import numpy as np
import pytest

from localscale.core.errors import LocalScaleError
from localscale.sfm.placement import align_centres, placement, read_reference_centres, spread, umeyama


def _rotation(seed: int) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _ring(n: int = 10) -> dict:
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return {f"p{i:02d}.jpg": np.array([np.cos(t), np.sin(t), 0.1 * np.cos(3 * t)]) for i, t in enumerate(a)}


def _transformed(ref: dict, s=2.5, seed=1, t=(3.0, -1.0, 7.0)) -> dict:
    R = _rotation(seed)
    return {n: (c - np.array(t)) @ R / s for n, c in ref.items()}  # the inverse of s R x + t


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(8, 3))
    R = _rotation(3)
    dst = 0.7 * src @ R.T + np.array([1.0, 2.0, 3.0])
    s, R2, t = umeyama(src, dst)
    assert s == pytest.approx(0.7)
    assert np.allclose(R2, R) and np.allclose(t, [1, 2, 3])


def test_every_photo_right_under_a_similarity():
    ref = _ring()
    model = _transformed(ref)
    p = placement(model, sorted(ref), reference=ref)
    assert (p["placed_right"], p["checked"], p["wrong"]) == (10, 10, [])
    assert max(p["errors"].values()) < 1e-6


def test_misplaced_photos_are_counted_and_do_not_pull_the_alignment():
    ref = _ring()
    model = _transformed(ref)
    names = sorted(ref)
    scale = spread(list(ref.values()))  # the reference's spread, in reference units
    model[names[0]] = model[names[0]] + np.array([0.12, 0, 0]) * scale / 2.5  # 12% of the spread
    model[names[1]] = model[names[1]] + np.array([0, 7500.0, 0]) * scale / 2.5  # 7,500 x the spread
    model[names[2]] = model[names[2]] + np.array([0, 0, 0.03]) * scale / 2.5  # 3%: still right
    p = placement(model, names, reference=ref)
    assert (p["placed_right"], p["checked"]) == (8, 10)
    assert p["wrong"] == [names[0], names[1]]
    assert p["errors"][names[0]] == pytest.approx(0.12, abs=5e-3)
    assert 0.0 < p["errors"][names[2]] < 0.05


def test_closeups_by_their_source_photo_with_and_without_a_reference():
    ref = _ring()
    names = sorted(ref)
    model = _transformed(ref)
    scale = spread(list(ref.values())) / 2.5
    model["c_right.jpg"] = model[names[3]] + np.array([0.3, 0, 0]) * scale  # 30% of the spread: right
    model["c_wrong.jpg"] = model[names[4]] + np.array([0, 3.0, 0]) * scale  # 3 x the spread: wrong
    closeups = {"c_right.jpg": names[3], "c_wrong.jpg": names[4], "c_unreg.jpg": names[5]}
    images = names + sorted(closeups)
    for reference in (ref, None):
        p = placement(model, images, reference=reference, closeups=closeups)
        assert p["closeups"] == {"checked": 3, "right": 1}
        assert "c_right.jpg" not in p["wrong"] and {"c_wrong.jpg", "c_unreg.jpg"} <= set(p["wrong"])
        assert p["errors"]["c_unreg.jpg"] is None
    assert placement(model, images, reference=ref, closeups=closeups)["placed_right"] == 11  # 10 photos + 1
    assert placement(model, images, closeups=closeups)["checked"] == 3  # no reference: the close-ups only


def test_unregistered_photos_are_not_right_and_too_few_cannot_align():
    ref = _ring()
    names = sorted(ref)
    model = {n: c for n, c in _transformed(ref).items() if n in names[:6]}
    assert placement(model, names, reference=ref)["placed_right"] == 6
    few = {n: model[n] for n in names[:2]}
    p = placement(few, names, reference=ref)
    assert (p["placed_right"], p["checked"]) == (0, 10)


def test_align_needs_three_images():
    with pytest.raises(LocalScaleError):
        align_centres(np.zeros((2, 3)), np.zeros((2, 3)), 0.1)


def test_reference_centres_from_colmap_text_and_a_table(tmp_path):
    R = _rotation(5)
    t = np.array([0.5, -1.0, 2.0])
    centre = -R.T @ t
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    model = tmp_path / "model"
    model.mkdir()
    (model / "images.txt").write_text(
        "# header\n"
        f"1 {w} {x} {y} {z} {t[0]} {t[1]} {t[2]} 1 a.jpg\n"
        "10.0 20.0 -1 30.0 40.0 5\n"
        f"2 1 0 0 0 0 0 1 1 b.jpg\n\n"
    )
    got = read_reference_centres(model)
    assert (
        set(got) == {"a.jpg", "b.jpg"} and np.allclose(got["a.jpg"], centre) and np.allclose(got["b.jpg"], [0, 0, -1])
    )
    table = tmp_path / "par.txt"
    table.write_text("1\n" + "a.jpg 1 0 0 0 1 0 0 0 1 " + " ".join(map(str, R.ravel())) + " " + " ".join(map(str, t)))
    assert np.allclose(read_reference_centres(table)["a.jpg"], centre)
    with pytest.raises(LocalScaleError):
        read_reference_centres(tmp_path / "missing")
