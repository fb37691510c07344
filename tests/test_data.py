import cv2
import numpy as np
import torch
from torch.utils.data import DataLoader

from localscale.data import PairConfig, SyntheticPairs, collate, list_images, split_images
from localscale.geometry import homography_scale_map


def small_cfg(**kw):
    return PairConfig(image_size=64, **kw)


def test_items_have_expected_layout(image_dir):
    ds = SyntheticPairs(image_dir, length=10, seed=1, config=small_cfg())
    it = ds[3]
    assert it["a"].shape == (3, 64, 64) and it["b"].shape == (3, 64, 64)
    assert it["a"].dtype == torch.float32 and 0 <= it["a"].min() and it["a"].max() <= 1
    assert it["scale"].shape == (8, 8) and it["mask"].shape == (8, 8) and it["mask"].dtype == torch.bool
    s = homography_scale_map(it["H"].numpy(), 64, 64, 8)
    m = it["mask"].numpy()
    assert np.allclose(it["scale"].numpy()[m], s[m], rtol=1e-5)  # ground truth is the analytic map


def test_deterministic_given_seed_and_index(image_dir):
    a = SyntheticPairs(image_dir, seed=5, config=small_cfg())[7]
    b = SyntheticPairs(image_dir, seed=5, config=small_cfg())[7]
    c = SyntheticPairs(image_dir, seed=6, config=small_cfg())[7]
    assert torch.equal(a["b"], b["b"]) and torch.equal(a["H"], b["H"])
    assert not torch.equal(a["H"], c["H"])


def test_dataloader_workers_give_the_same_batches(image_dir):
    ds = SyntheticPairs(image_dir, length=8, seed=2, config=small_cfg())
    b0 = [b["b"] for b in DataLoader(ds, batch_size=4, collate_fn=collate, num_workers=0)]
    b2 = [b["b"] for b in DataLoader(ds, batch_size=4, collate_fn=collate, num_workers=2)]
    assert all(torch.equal(x, y) for x, y in zip(b0, b2))


def test_target_empty_region_is_filled_not_zero(image_dir):
    cfg = small_cfg(photometric=0.0, gray_probability=0.0)
    ds = SyntheticPairs(image_dir, seed=0, config=cfg)
    for i in range(40):  # find a strong zoom-out: most of B is outside A's footprint
        it = ds[i]
        if it["global_scale"] < 0.4:
            break
    b = it["b"]
    box = b.sum(0) > 0
    # the image region of B (its letterbox) is almost entirely non-black: the fill covers it
    rows, cols = box.any(1).nonzero(), box.any(0).nonzero()
    region = b[:, rows.min() : rows.max() + 1, cols.min() : cols.max() + 1]
    assert (region.sum(0) == 0).float().mean() < 0.02
    nofill = SyntheticPairs(image_dir, seed=0, config=small_cfg(photometric=0.0, gray_probability=0.0, fill=False))[i][
        "b"
    ]
    assert (nofill[:, rows.min() : rows.max() + 1, cols.min() : cols.max() + 1].sum(0) == 0).float().mean() > 0.3


def test_split_is_deterministic_and_disjoint(image_dir):
    files = list_images(image_dir)
    tr, ho = split_images(files, holdout_every=3)
    assert set(tr).isdisjoint(ho) and len(tr) + len(ho) == len(files)
    assert split_images(list(reversed(files)), 3) == (tr, ho)


def test_context_shows_the_photos_surroundings_around_a(tmp_path):
    """With ``context`` B is rendered from the whole photo: inside A's footprint it is the same
    warp of A as without context; around it, B shows the photo instead of the fill photo."""
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (160, 200, 3)).astype(np.uint8), (0, 0), 1.5)
    cv2.imwrite(str(tmp_path / "texture.png"), texture)
    cv2.imwrite(str(tmp_path / "gray.png"), np.full((160, 200, 3), 128, np.uint8))  # the fill photo
    kw = dict(photometric=0.0, gray_probability=0.0, crop_fraction=(0.5, 0.5))
    plain = SyntheticPairs(tmp_path, seed=3, config=small_cfg(**kw))
    ctx = SyntheticPairs(tmp_path, seed=3, config=small_cfg(context=True, **kw))
    shares = []
    for i in range(40):
        p, c = plain[i], ctx[i]
        assert torch.equal(p["H"], c["H"]) and torch.equal(p["a"], c["a"]) and torch.equal(p["scale"], c["scale"])
        region = (p["a"].sum(0) > 0).numpy().astype(np.uint8)  # B's image region (B has A's size)
        if p["a"][:, region > 0].std() < 0.01 or p["global_scale"] > 0.8:  # A from the gray photo / no room
            continue
        footprint = cv2.warpPerspective(region, p["H"].numpy(), (64, 64), flags=cv2.INTER_NEAREST) > 0
        inside = cv2.erode(footprint.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        grow = lambda k: cv2.dilate(footprint.astype(np.uint8), np.ones((k, k), np.uint8)) > 0  # noqa: E731
        around = grow(9) & ~grow(3) & (region > 0)  # a ring just outside A's footprint
        if inside.sum() < 20 or around.sum() < 20:
            continue
        diff = (p["b"] - c["b"]).abs().sum(0).numpy() * 255
        assert np.median(diff[inside]) < 2  # same content where A lands
        is_fill = lambda b: (b.permute(1, 2, 0).numpy() * 255).round().astype(int) == 128  # noqa: E731
        assert is_fill(p["b"])[around].all(1).mean() > 0.95  # no context: the fill photo around A
        shares.append(is_fill(c["b"])[around].all(1).mean())  # context: the photo shows through
    assert len(shares) >= 3 and max(shares) < 0.9 and np.mean(shares) < 0.5, shares


def _rotation_deg(H):
    return abs(np.degrees(np.arctan2(H[1, 0] - H[0, 1], H[0, 0] + H[1, 1])))


def test_identity_pairs_have_scale_one_everywhere(image_dir):
    from localscale.data import PAIR_KINDS

    ds = SyntheticPairs(image_dir, seed=0, config=small_cfg(identity_probability=1.0))
    kinds = set()
    for i in range(12):
        it = ds[i]
        kinds.add(PAIR_KINDS[it["kind"]])
        m = it["mask"]
        assert m.sum() >= 0.8 * it["valid"].sum()  # nearly all of A is visible
        assert torch.all((it["scale"][m] - 1).abs() < 0.1)  # within +-5% scale and a little perspective
        assert _rotation_deg(it["H"].numpy()) <= 3.5
    assert kinds == {"identity", "near-identity"}


def test_exact_identity_pair_without_photometric_change_is_the_same_image(image_dir):
    from localscale.data import PAIR_KINDS

    ds = SyntheticPairs(
        image_dir, seed=0, config=small_cfg(identity_probability=1.0, photometric=0.0, gray_probability=0.0)
    )
    items = [ds[i] for i in range(12)]
    exact = [it for it in items if PAIR_KINDS[it["kind"]] == "identity"]
    assert exact and all(torch.allclose(it["a"], it["b"], atol=1 / 255) for it in exact)


def test_unrelated_pairs_have_nothing_visible(image_dir):
    ds = SyntheticPairs(image_dir, seed=0, config=small_cfg(unrelated_probability=1.0))
    for i in range(5):
        it = ds[i]
        assert not it["related"] and not it["mask"].any() and it["valid"].any()
        assert not torch.allclose(it["a"], it["b"], atol=0.1)


def test_full_rotation_and_low_overlap_options(image_dir):
    plain = SyntheticPairs(image_dir, seed=0, config=small_cfg())
    rot = SyntheticPairs(image_dir, seed=0, config=small_cfg(full_rotation_probability=1.0))
    far = SyntheticPairs(image_dir, seed=0, config=small_cfg(low_overlap_probability=1.0, low_overlap_shift=0.6))
    # (the angle read off H includes skew and perspective: ordinary pairs reach a little beyond 30 deg)
    assert max(_rotation_deg(plain[i]["H"].numpy()) for i in range(30)) < 70
    assert max(_rotation_deg(rot[i]["H"].numpy()) for i in range(30)) > 120
    visible = lambda ds: np.mean([float(ds[i]["mask"].sum() / ds[i]["valid"].sum()) for i in range(30)])  # noqa: E731
    assert visible(far) < visible(plain) - 0.1


def test_gray_on_one_side_and_degradations(image_dir):
    ds = SyntheticPairs(
        image_dir,
        seed=0,
        config=small_cfg(
            gray_one_side_probability=1.0, gray_probability=0.0, degrade_probability=1.0, strong_light_probability=1.0
        ),
    )
    is_gray = lambda t: bool(torch.allclose(t[0], t[1], atol=1 / 255) and torch.allclose(t[1], t[2], atol=1 / 255))  # noqa: E731
    sides = []
    for i in range(10):
        it = ds[i]
        sides.append((is_gray(it["a"]), is_gray(it["b"])))
        near_image = cv2.dilate(it["valid"].numpy().astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        pad = ~torch.from_numpy(np.kron(near_image, np.ones((8, 8), bool)))
        assert it["a"][:, pad].abs().sum() == 0 and it["b"][:, pad].abs().sum() == 0  # padding stays black
    assert all(a != b for a, b in sides if not (a and b))  # exactly one side gray (a colourless photo may be both)
    assert any(a for a, _ in sides) and any(b for _, b in sides)


def test_pair_options_are_range_checked():
    import pytest

    from localscale.core.errors import LocalScaleError
    from localscale.training import TrainConfig

    with pytest.raises(LocalScaleError, match="identity-probability"):
        TrainConfig(identity_probability=1.5).pair_config()


def test_swapped_pairs_are_the_inverse_pair(image_dir):
    plain = SyntheticPairs(image_dir, seed=0, config=small_cfg(photometric=0.0))
    swapped = SyntheticPairs(image_dir, seed=0, config=small_cfg(photometric=0.0, swap_probability=1.0))
    for i in range(6):
        p, s = plain[i], swapped[i]
        # the same rendering, roles exchanged; the target comes from the inverse homography
        assert torch.equal(p["a"], s["b"]) and torch.equal(p["b"], s["a"])
        assert np.allclose(s["H"].numpy(), np.linalg.inv(p["H"].numpy()), atol=1e-8)
        m = s["mask"].numpy()
        if m.any():
            assert np.allclose(s["scale"].numpy()[m], homography_scale_map(s["H"].numpy(), 64, 64, 8)[m], rtol=1e-5)
        if p["mask"].any() and m.any():  # zoom in one way is zoom out the other way
            assert np.log(p["global_scale"]) * np.log(s["global_scale"]) <= 1e-6
