"""The Local-ScaleNet training campaign across sessions: one long run in ``runs/campaign_local``
(started and resumed by ``train/campaign_local.sh``), carried between machines by a small committed
copy of its checkpoint and logs in ``train/campaign/local/``.

    python train/campaign.py unpack   # committed copy -> runs/ (only when it is ahead of runs/)
    python train/campaign.py pack     # runs/ -> committed copy (weights fp32, Adam moments bf16)
    python train/campaign.py status   # steps, training hours, validation curve (table, JSON, PNG)
    python train/campaign.py validate W [W ...]   # the campaign's validation pairs scored by other weights

The packed checkpoint keeps the weights in fp32 and stores Adam's two moments in bf16 (about 15 MB
instead of 23 MB); ``torch.optim.Adam.load_state_dict`` casts them back to fp32 on resume, so a resume
from the packed copy continues the same run with moments rounded to bf16.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import socket
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "runs" / "campaign_local"
PACKED = ROOT / "train" / "campaign" / "local"
LOGS = ("train_log.csv", "val_log.jsonl")


def _step(path: Path) -> int:
    if not path.exists():
        return -1
    return int(torch.load(path, map_location="cpu", weights_only=True)["train_state"]["step"])


def _atomic_copy(src: Path, dst: Path) -> None:
    tmp = dst.with_name(f".{dst.name}.tmp")
    shutil.copyfile(src, tmp)
    tmp.replace(dst)


def _trainer_cpu_seconds() -> dict[str, float]:
    """CPU seconds (user + system) of each running campaign trainer, by pid (Linux ``/proc``)."""
    found = {}
    for stat in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            cmd = stat.read_bytes().split(b"\0")
            if b"runs/campaign_local" not in cmd or not any(b"localscale-train" in c for c in cmd):
                continue
            fields = (stat.parent / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        found[stat.parent.name] = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return found


def _record_session(step: int) -> None:
    """One line per trainer process in ``sessions.jsonl``: its CPU time and the step it reached."""
    ledger = PACKED / "sessions.jsonl"
    rows = [json.loads(ln) for ln in ledger.read_text().splitlines()] if ledger.exists() else []
    for pid, cpu in _trainer_cpu_seconds().items():
        key = f"{socket.gethostname()}:{pid}"
        rows = [r for r in rows if r["process"] != key]
        rows.append(
            {"process": key, "date": time.strftime("%Y-%m-%d"), "cpu_hours": round(cpu / 3600, 3), "step": step}
        )
    ledger.write_text("".join(json.dumps(r) + "\n" for r in rows))


def pack() -> None:
    """Write the committed copy of ``runs/campaign_local``: weights fp32, Adam moments bf16, the logs,
    and the CPU time of the running trainer (``sessions.jsonl``)."""
    ckpt = torch.load(RUN / "last.pt", map_location="cpu", weights_only=True)
    for state in ckpt["train_state"]["optimizer"]["state"].values():
        for key in ("exp_avg", "exp_avg_sq"):
            state[key] = state[key].to(torch.bfloat16)
    PACKED.mkdir(parents=True, exist_ok=True)
    tmp = PACKED / ".last.pt.tmp"
    torch.save(ckpt, tmp)
    tmp.replace(PACKED / "last.pt")
    for name in LOGS:
        if (RUN / name).exists():
            _atomic_copy(RUN / name, PACKED / name)
    _record_session(int(ckpt["train_state"]["step"]))
    print(f"packed step {ckpt['train_state']['step']} -> {PACKED} ({(PACKED / 'last.pt').stat().st_size / 1e6:.1f} MB)")


def unpack() -> None:
    """Copy the committed checkpoint and logs into ``runs/campaign_local`` when they are ahead of it."""
    packed, local = _step(PACKED / "last.pt"), _step(RUN / "last.pt")
    if packed <= local:
        print(f"runs/ is at step {local}, the committed copy at {packed}: nothing to unpack")
        return
    RUN.mkdir(parents=True, exist_ok=True)
    for name in ("last.pt", *LOGS):
        if (PACKED / name).exists():
            _atomic_copy(PACKED / name, RUN / name)
    print(f"unpacked step {packed} into {RUN}")


def _hours(rows: list[dict]) -> float:
    """Training wall time summed over the run's sessions (``time_s`` restarts at each resume)."""
    total, prev = 0.0, 0.0
    for r in rows:
        t = float(r["time_s"])
        total += t - prev if t >= prev else t
        prev = t
    return total / 3600


def status(out: Path | None) -> dict:
    """Steps done, hours, the training loss per 1000 steps and the validation rows."""
    log = RUN if (RUN / "train_log.csv").exists() else PACKED
    with open(log / "train_log.csv") as f:
        rows = list(csv.DictReader(f))
    val = (
        [json.loads(ln) for ln in (log / "val_log.jsonl").read_text().splitlines()] if (log / LOGS[1]).exists() else []
    )
    buckets: dict[int, list[float]] = {}
    for r in rows:
        buckets.setdefault((int(r["step"]) - 1) // 1000, []).append(float(r["loss"]))
    curve = [
        {"steps": f"{k * 1000 + 1}-{k * 1000 + len(v)}", "mean_loss": sum(v) / len(v)}
        for k, v in sorted(buckets.items())
    ]
    ledger = PACKED / "sessions.jsonl"
    sessions = [json.loads(ln) for ln in ledger.read_text().splitlines()] if ledger.exists() else []
    res = {
        "steps": int(rows[-1]["step"]) if rows else 0,
        "wall_hours": _hours(rows),
        "cpu_hours": sum(r["cpu_hours"] for r in sessions),
        "sessions": sessions,
        "loss": curve,
        "validation": val,
    }
    print(
        f"steps {res['steps']}, {res['wall_hours']:.2f} h of training wall time, "
        f"{res['cpu_hours']:.2f} CPU-hours recorded at the packs ({len(sessions)} trainer processes)"
    )
    print("| steps | mean training loss |\n|---|---|")
    for c in curve:
        print(f"| {c['steps']} | {c['mean_loss']:.4f} |")
    if val:
        print("\n| step | held-out mean r | median r | constant-1 mean r |\n|---|---|---|---|")
        for v in val:
            print(f"| {v['step']} | {v['mean_r']:.3f} | {v['median_r']:.3f} | {v['baseline_mean_r']:.3f} |")
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "campaign.json").write_text(json.dumps(res, indent=1))
        _plot(curve, val, out / "campaign.png")
    return res


def _plot(curve: list[dict], val: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
    ax[0].plot([int(c["steps"].split("-")[1]) for c in curve], [c["mean_loss"] for c in curve], "-o", ms=3)
    ax[0].set(xlabel="step", ylabel="training loss (KL, mean per 1000 steps)")
    if val:
        ax[1].plot([v["step"] for v in val], [v["mean_r"] for v in val], "-o", ms=3, label="Local-ScaleNet")
        ax[1].plot([v["step"] for v in val], [v["baseline_mean_r"] for v in val], "--", label="constant 1")
        ax[1].legend()
    ax[1].set(xlabel="step", ylabel="held-out mean error factor r")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def validate_weights(weights: list[str]) -> dict:
    """The campaign's held-out validation pairs (as the trainer scores them) for each weights file:
    an inference checkpoint (e.g. the shipped ``local_scalenet.pt``) or a training ``last.pt``."""
    import contextlib

    from localscale.cli.train import parse_args
    from localscale.data import collate
    from localscale.training.loop import _datasets, build_model
    from localscale.training.steps import validate

    command = (ROOT / "train" / "campaign_local.sh").read_text().split("exec localscale-train", 1)[1]
    cfg = parse_args(command.replace("\\\n", " ").replace('"$@"', "").split())
    torch.set_num_threads(1)
    _, val = _datasets(cfg, 1)
    batches = [collate([val[i] for i in range(j, min(j + 16, len(val)))]) for j in range(0, len(val), 16)]
    out = {}
    for w in weights:
        cfg.init_weights = w
        model = build_model(cfg, verbose=False)
        out[w] = validate(model, batches, "local", torch.device("cpu"), contextlib.nullcontext)
        print(f"{w}: mean r {out[w]['mean_r']:.3f}, median r {out[w]['median_r']:.3f}")
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("command", choices=["pack", "unpack", "status", "validate"])
    p.add_argument("weights", nargs="*", help="validate: weights files")
    p.add_argument("--out", type=Path, default=None, help="status: folder for campaign.json and campaign.png")
    a = p.parse_args(argv)
    if a.command == "pack":
        pack()
    elif a.command == "unpack":
        unpack()
    elif a.command == "validate":
        validate_weights(a.weights)
    else:
        status(a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
