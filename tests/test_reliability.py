"""Untrusted input: checkpoints that would run code or are malformed, image files whose
size is unknown or huge, EXIF orientation, and homographies near the numeric limits."""
import os
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch

from localscale.checkpoint import (FORMAT_VERSION, load_model, read_checkpoint, restore_train_state, save_model,
                                   train_state)
from localscale.errors import CheckpointError
from localscale.features.descriptors import HardNetDescriptor
from localscale.models import LocalScaleNet

TINY = dict(width=0.125, feature_dim=16, image_size=64)
WEIGHTS = Path(__file__).resolve().parent.parent / "localscale" / "weights"


def _one_line(exc_info) -> str:
    msg = str(exc_info.value)
    assert "\n" not in msg
    return msg


class _WritesMarker:
    """Unpickling this object would create a file (stands for arbitrary code)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (Path.touch, (Path(self.marker),))


@pytest.fixture(scope="module")
def ckpt_path(tmp_path_factory):
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("ck") / "m.pt"
    save_model(LocalScaleNet(**TINY).eval(), path)
    return path


def _variant(ckpt_path, tmp_path, name, edit):
    ck = torch.load(ckpt_path, weights_only=True)
    edit(ck)
    out = tmp_path / name
    torch.save(ck, out)
    return out


# ---------------------------------------------------------------- checkpoints
def test_the_pickled_payload_check_itself_works(tmp_path):
    """Without weights_only the crafted file does create the marker (so the next test means something)."""
    marker = tmp_path / "ran"
    torch.save({"x": _WritesMarker(marker)}, tmp_path / "evil.pt")
    torch.load(tmp_path / "evil.pt", weights_only=False)
    assert marker.exists()


@pytest.mark.parametrize("loader", [load_model, read_checkpoint, HardNetDescriptor.from_pretrained])
def test_checkpoint_with_code_in_meta_is_refused_unrun(ckpt_path, tmp_path, loader):
    marker = tmp_path / "ran"
    evil = _variant(ckpt_path, tmp_path, "evil.pt", lambda ck: ck["meta"].update(x=_WritesMarker(marker)))
    with pytest.raises(CheckpointError, match="contains non-tensor objects") as e:
        loader(evil)
    assert str(evil) in _one_line(e)
    assert not marker.exists()


def test_hardnet_checkpoint_with_code_is_refused_unrun(tmp_path):
    marker = tmp_path / "ran"
    HardNetDescriptor().save(tmp_path / "h.pt", meta={"x": 1})
    ck = torch.load(tmp_path / "h.pt", weights_only=True)
    ck["meta"]["x"] = _WritesMarker(marker)
    torch.save(ck, tmp_path / "h.pt")
    with pytest.raises(CheckpointError, match="non-tensor objects"):
        HardNetDescriptor.from_pretrained(tmp_path / "h.pt")
    assert not marker.exists()


@pytest.mark.parametrize("name,edit,match", [
    ("nosd", lambda ck: ck.pop("state_dict"), "has no 'state_dict'"),
    ("sdlist", lambda ck: ck.update(state_dict=[1, 2]), "'state_dict' is a list"),
    ("sdvalue", lambda ck: ck["state_dict"].update(extra=3.0), "'state_dict' entry 'extra' is a float, not a tensor"),
    ("version", lambda ck: ck.update(localscale_format=FORMAT_VERSION + 1), "unsupported checkpoint format version 2"),
    ("version_str", lambda ck: ck.update(localscale_format="1"), "unsupported checkpoint format version '1'"),
    ("noconfig", lambda ck: ck.pop("config"), "no valid 'config'"),
    ("config_key", lambda ck: ck["config"].update(colour=1), "config does not fit LocalScaleNet"),
    ("config_type", lambda ck: ck["config"].update(reduction="abc"), "config does not fit LocalScaleNet"),
    ("config_list", lambda ck: ck.update(config=[1, 2]), "no valid 'config'"),
])
def test_malformed_checkpoints_give_one_line_errors(ckpt_path, tmp_path, name, edit, match):
    bad = _variant(ckpt_path, tmp_path, f"{name}.pt", edit)
    with pytest.raises(CheckpointError, match=match) as e:
        load_model(bad)
    assert str(bad) in _one_line(e)


def test_hardnet_unknown_format_and_non_tensor_values_are_refused(tmp_path):
    net = HardNetDescriptor()
    net.save(tmp_path / "h.pt")
    ck = torch.load(tmp_path / "h.pt", weights_only=True)
    torch.save({**ck, "localscale_format": 7}, tmp_path / "v7.pt")
    with pytest.raises(CheckpointError, match="unsupported checkpoint format version 7"):
        HardNetDescriptor.from_pretrained(tmp_path / "v7.pt")
    torch.save({"state_dict": {**ck["state_dict"], "bad": "x"}}, tmp_path / "str.pt")
    with pytest.raises(CheckpointError, match="'bad' is a str, not a tensor"):
        HardNetDescriptor.from_pretrained(tmp_path / "str.pt")


def test_plain_pickle_and_garbage_are_one_line_errors(tmp_path):
    import pickle

    (tmp_path / "p.pt").write_bytes(pickle.dumps({"localscale_format": 1}, protocol=4))
    (tmp_path / "g.pt").write_bytes(b"hello, not a checkpoint" * 50)
    for f in ("p.pt", "g.pt"):
        with pytest.raises(CheckpointError, match="cannot read checkpoint") as e:
            read_checkpoint(tmp_path / f)
        _one_line(e)


@pytest.mark.parametrize("name", sorted(p.name for p in WEIGHTS.glob("*.pt")))
def test_shipped_weights_load_with_weights_only(name):
    ck = torch.load(WEIGHTS / name, map_location="cpu", weights_only=True)
    assert ck["localscale_format"] == FORMAT_VERSION and isinstance(ck["meta"], dict)
    assert all(isinstance(v, torch.Tensor) for v in ck["state_dict"].values())


def test_train_state_is_plain_data_and_restores_the_schedule(tmp_path):
    model = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(model.parameters(), lr=1.0)
    sched = torch.optim.lr_scheduler.MultiStepLR(opt, [2, 4, 4], 0.5)
    for _ in range(3):
        model(torch.ones(1, 3)).sum().backward()
        opt.step()
        sched.step()
    state = train_state(opt, sched, 3)
    assert type(state["scheduler"]["milestones"]) is dict     # no Counter stored

    def no_counter(obj):
        if isinstance(obj, Counter):
            return False
        if isinstance(obj, dict):
            return all(no_counter(v) for v in obj.values())
        if isinstance(obj, (list, tuple)):
            return all(no_counter(v) for v in obj)
        return True

    assert no_counter(state)
    torch.save({"train_state": state}, tmp_path / "last.pt")
    loaded = torch.load(tmp_path / "last.pt", weights_only=True)["train_state"]

    opt2 = torch.optim.Adam(torch.nn.Linear(3, 2).parameters(), lr=1.0)
    sched2 = torch.optim.lr_scheduler.MultiStepLR(opt2, [9], 0.5)
    assert restore_train_state(opt2, sched2, loaded) == 3
    assert isinstance(sched2.milestones, Counter) and sched2.milestones == Counter([2, 4, 4])
    lrs = []
    for _ in range(3):
        opt2.step()
        sched2.step()
        lrs.append(opt2.param_groups[0]["lr"])
    assert lrs == pytest.approx([0.125, 0.125, 0.125])   # 1 * 0.5 (step 2) * 0.25 (step 4, twice)
