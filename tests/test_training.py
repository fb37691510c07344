import csv
import json

import pytest
import torch

from localscale import training
from localscale.checkpoint import load_model, read_checkpoint
from localscale.training import TrainConfig, TrainingDiverged, train


def tiny_cfg(image_dir, out, **kw):
    base = dict(data=str(image_dir), out=str(out), width=0.125, feature_dim=16, image_size=64, steps=6,
                batch_size=4, lr=1e-3, holdout_every=3, val_pairs=8, val_every=3, ckpt_every=3, workers=0,
                threads=1, amp="off")
    base.update(kw)
    return TrainConfig(**base)


def test_short_run_learns_and_exports(image_dir, tmp_path):
    cfg = tiny_cfg(image_dir, tmp_path / "run", steps=40, val_every=40, ckpt_every=20, lr=2e-3)
    res = train(cfg)
    rows = list(csv.DictReader(open(tmp_path / "run" / "train_log.csv")))
    losses = [float(r["loss"]) for r in rows]
    assert len(losses) == 40
    assert sum(losses[-10:]) / 10 < 0.85 * sum(losses[:10]) / 10    # the loss goes down
    assert res["step"] == 40 and res["mean_r"] > 1
    model = load_model(tmp_path / "run" / "model.pt", arch="LocalScaleNet")
    assert model.meta["steps"] == 40
    val = [json.loads(l) for l in open(tmp_path / "run" / "val_log.jsonl")]
    assert val[-1]["step"] == 40


def test_interrupted_run_resumes_to_identical_weights(image_dir, tmp_path):
    train(tiny_cfg(image_dir, tmp_path / "straight"))
    train(tiny_cfg(image_dir, tmp_path / "resumed"), max_steps_this_run=3)   # "killed" after step 3
    assert read_checkpoint(tmp_path / "resumed" / "last.pt")["train_state"]["step"] == 3
    train(tiny_cfg(image_dir, tmp_path / "resumed"))
    a = read_checkpoint(tmp_path / "straight" / "last.pt")["state_dict"]
    b = read_checkpoint(tmp_path / "resumed" / "last.pt")["state_dict"]
    assert a.keys() == b.keys()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_global_model_trains_with_the_same_trainer(image_dir, tmp_path):
    res = train(tiny_cfg(image_dir, tmp_path / "g", model="global", steps=3))
    assert res["step"] == 3
    load_model(tmp_path / "g" / "model.pt", arch="ScaleNet")


def test_nan_loss_stops_and_keeps_last_good_checkpoint(image_dir, tmp_path, monkeypatch):
    real = training.compute_loss
    calls = {"n": 0}

    def flaky(model, batch, kind):
        calls["n"] += 1
        loss = real(model, batch, kind)
        return loss * float("nan") if calls["n"] == 5 else loss

    monkeypatch.setattr(training, "compute_loss", flaky)
    with pytest.raises(TrainingDiverged, match="at step 5"):
        train(tiny_cfg(image_dir, tmp_path / "nan"))
    assert read_checkpoint(tmp_path / "nan" / "last.pt")["train_state"]["step"] == 3
