"""The parts of a training run: loss, validation, logs, distributed set-up, data-loader workers, loading weights."""

from __future__ import annotations

import csv
import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

import torch
import torch.distributed as dist
import torch.nn.functional as F

from .. import scales
from ..core.errors import LocalScaleError
from .config import NEW_LAYER_PREFIXES, TrainConfig


def _load_matching(
    model, state_dict: dict, source: str, may_miss: tuple[str, ...] = NEW_LAYER_PREFIXES
) -> tuple[list[str], list[str]]:
    """Load ``state_dict``; only layers starting with ``may_miss`` (default: the optional new
    layers, :data:`NEW_LAYER_PREFIXES`) may be missing."""
    try:
        missing, unexpected = model.load_state_dict(state_dict, strict=False)
    except RuntimeError as e:
        raise LocalScaleError(f"{source}: weights do not fit this model ({str(e).splitlines()[0]})") from None
    bad = [k for k in missing if not k.startswith(may_miss)] + list(unexpected)
    if bad:
        raise LocalScaleError(f"{source}: weights do not fit this model ({len(bad)} mismatched keys, e.g. {bad[0]})")
    return list(missing), list(unexpected)


def compute_loss(model, batch: dict, kind: str, visibility_weight: float = 0.5, per_pair: bool = False) -> torch.Tensor:
    """Local: KL on the co-visible cells (+ BCE of the visibility output over A's image region);
    ``per_pair``: the KL averaged per pair first (:func:`~localscale.scales.kl_loss`).
    Global: KL of both directions on pairs that share content."""
    if kind == "local":
        logits, vis = model(batch["a"], batch["b"], all_outputs=True)
        target = scales.scale_to_distribution(batch["scale"], dim=1)
        loss = scales.kl_loss(logits, target, batch["mask"], per_pair=per_pair)
        if vis is not None:
            valid = batch["valid"].float()
            bce = F.binary_cross_entropy_with_logits(vis[:, 0].float(), batch["mask"].float(), reduction="none")
            loss = loss + visibility_weight * (bce * valid).sum() / valid.sum().clamp_min(1.0)
        return loss
    l_ab, l_ba = model(batch["a"], batch["b"])
    g = batch["global_scale"].float()
    related = batch["related"] if "related" in batch else None
    return 0.5 * (
        scales.kl_loss(l_ab, scales.scale_to_distribution(g, 1), related)
        + scales.kl_loss(l_ba, scales.scale_to_distribution(1.0 / g, 1), related)
    )


@torch.no_grad()
def validate(model, batches: list[dict], kind: str, device, amp_ctx) -> dict:
    """Mean scale-ratio error r on held-out pairs, with the constant-1 baseline."""
    model.eval()
    errs, base, inter, union = [], [], 0.0, 0.0
    for batch in batches:
        batch = {k: v.to(device) for k, v in batch.items()}
        with amp_ctx():
            out = model(batch["a"], batch["b"], all_outputs=True) if kind == "local" else model(batch["a"], batch["b"])
        if kind == "local":
            out, vis = out
            if vis is not None:
                pv, gv, valid = vis[:, 0] > 0, batch["mask"], batch["valid"]
                inter += float((pv & gv & valid).sum())
                union += float(((pv | gv) & valid).sum())
            log_s = scales.soft_log_scale(torch.softmax(out.float(), 1), 1)
            m = batch["mask"]
            gt = torch.log(batch["scale"])
            errs.append((log_s - gt).abs()[m].cpu())
            base.append(gt.abs()[m].cpu())
        else:
            ls_ab = scales.soft_log_scale(torch.softmax(out[0].float(), 1), 1)
            ls_ba = scales.soft_log_scale(torch.softmax(out[1].float(), 1), 1)
            gt = torch.log(batch["global_scale"].float())
            keep = batch["related"] if "related" in batch else torch.ones_like(gt, dtype=torch.bool)
            errs.append((scales.consistent_log_scale(ls_ab, ls_ba) - gt).abs()[keep].cpu())
            base.append(gt.abs()[keep].cpu())
    e, b = torch.cat(errs).double(), torch.cat(base).double()
    row = {
        "mean_r": float(torch.exp(e).mean()),
        "median_r": float(torch.exp(e.median())),
        "baseline_mean_r": float(torch.exp(b).mean()),
    }
    if union:
        row["visibility_iou"] = inter / union
    return row


def _grads_finite(model) -> bool:
    return all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


class _Logger:
    def __init__(self, out: Path, enabled: bool):
        self.enabled = enabled
        self.csv = out / "train_log.csv"
        self.val = out / "val_log.jsonl"

    def train(self, row: dict) -> None:
        if not self.enabled:
            return
        new = not self.csv.exists()
        with open(self.csv, "a", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(row))
            if new:
                w.writeheader()
            w.writerow(row)

    def truncate(self, step: int) -> None:
        """On resume, drop log rows written after the checkpoint (they will be written again)."""
        if not self.enabled:
            return
        if self.csv.exists():
            lines = self.csv.read_text().splitlines(keepends=True)
            self.csv.write_text("".join(lines[:1] + [ln for ln in lines[1:] if int(ln.split(",", 1)[0]) <= step]))
        if self.val.exists():
            rows = [ln for ln in self.val.read_text().splitlines(keepends=True) if json.loads(ln)["step"] <= step]
            self.val.write_text("".join(rows))

    def validation(self, row: dict) -> None:
        if self.enabled:
            with open(self.val, "a") as f:
                f.write(json.dumps(row) + "\n")


def _setup_distributed(cfg: TrainConfig) -> tuple[int, int, torch.device]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1:
        local_rank = int(os.environ.get("LOCAL_RANK", "0"))
        if cfg.device.startswith("cuda"):
            torch.cuda.set_device(local_rank)
            device = torch.device("cuda", local_rank)
        else:
            device = torch.device("cpu")
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        return dist.get_rank(), world, device
    return 0, 1, torch.device(cfg.device)


def die_with_parent() -> None:
    """Make this process exit when its parent dies, even by ``kill -9``.

    On Linux the kernel sends SIGKILL to it when the parent exits (``prctl(PR_SET_PDEATHSIG)``);
    if the parent died before that was set, it exits now. Elsewhere a thread polls the parent.
    """
    import multiprocessing

    parent = multiprocessing.parent_process()
    parent_pid = parent.pid if parent is not None else os.getppid()
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            PR_SET_PDEATHSIG = 1
            libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except (OSError, AttributeError):  # pragma: no cover - no usable libc
            pass
    if os.getppid() != parent_pid:  # the parent is already gone
        os._exit(1)
    if not sys.platform.startswith("linux"):  # pragma: no cover

        def _watch():
            while os.getppid() == parent_pid:
                time.sleep(1.0)
            os._exit(1)

        threading.Thread(target=_watch, daemon=True).start()


def _single_threaded_worker(_: int) -> None:
    # each DataLoader worker renders whole samples; OpenCV's own thread pool would oversubscribe the cores
    die_with_parent()
    import cv2

    cv2.setNumThreads(1)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the main process's: it saves and stops
