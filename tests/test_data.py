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
    assert np.allclose(it["scale"].numpy()[m], s[m], rtol=1e-5)   # ground truth is the analytic map


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
    for i in range(40):       # find a strong zoom-out: most of B is outside A's footprint
        it = ds[i]
        if it["global_scale"] < 0.4:
            break
    b = it["b"]
    box = b.sum(0) > 0
    # the image region of B (its letterbox) is almost entirely non-black: the fill covers it
    rows, cols = box.any(1).nonzero(), box.any(0).nonzero()
    region = b[:, rows.min():rows.max() + 1, cols.min():cols.max() + 1]
    assert (region.sum(0) == 0).float().mean() < 0.02
    nofill = SyntheticPairs(image_dir, seed=0, config=small_cfg(photometric=0.0, gray_probability=0.0, fill=False))[i]["b"]
    assert (nofill[:, rows.min():rows.max() + 1, cols.min():cols.max() + 1].sum(0) == 0).float().mean() > 0.3


def test_split_is_deterministic_and_disjoint(image_dir):
    files = list_images(image_dir)
    tr, ho = split_images(files, holdout_every=3)
    assert set(tr).isdisjoint(ho) and len(tr) + len(ho) == len(files)
    assert split_images(list(reversed(files)), 3) == (tr, ho)
