"""Learning curves of the real-pair training runs: the training loss (mixed synthetic and real
samples, moving mean) against the step, the final validation errors and each run's hours.

    python eval/real_pair_curves.py runs/real_long runs/real_mild runs/real_control \\
        --out results/real_pairs/learning_curves

Each argument is a folder of runs (``<folder>/<model>_without_<collection>/``, as
``train/train_real_pairs.py`` writes them) or one run; a run is read from its ``train_log.csv``
(``step,loss,lr,time_s``) and ``val_log.jsonl``. Writes ``OUT.json`` (per run: the loss every
``--every`` steps, the final validation, seconds) and ``OUT.png``; prints a table.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

from localscale.core.outputs import write_text
from localscale.evaluation.report import git_commit


def read_run(run: Path, window: int, every: int) -> dict:
    rows = list(csv.DictReader(open(run / "train_log.csv")))
    steps = np.array([int(r["step"]) for r in rows])
    loss = np.array([float(r["loss"]) for r in rows])
    kernel = np.ones(min(window, len(loss))) / min(window, len(loss))
    smooth = np.convolve(loss, kernel, mode="valid")  # mean of the last `window` steps
    smooth_steps = steps[len(steps) - len(smooth) :]
    keep = (smooth_steps % every == 0) | (smooth_steps == smooth_steps[-1])
    val = [json.loads(line) for line in open(run / "val_log.jsonl")] if (run / "val_log.jsonl").is_file() else []
    last = val[-1] if val else {}
    return {
        "run": str(run),
        "steps": int(steps[-1]),
        "hours": round(float(rows[-1]["time_s"]) / 3600, 2),
        "loss_first": round(float(smooth[0]), 4),
        "loss_last": round(float(smooth[-1]), 4),
        "curve": [[int(s), round(float(v), 4)] for s, v in zip(smooth_steps[keep], smooth[keep])],
        "val_synthetic_mean_r": last.get("mean_r"),
        "val_real_mean_r": last.get("real_mean_r"),
        "val_real_constant_mean_r": last.get("real_baseline_mean_r"),
    }


def runs_of(folder: Path) -> list:
    if (folder / "train_log.csv").is_file():
        return [folder]
    return sorted(p for p in folder.iterdir() if (p / "train_log.csv").is_file())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("folders", nargs="+", type=Path)
    p.add_argument("--window", type=int, default=50, help="steps in the moving mean of the loss")
    p.add_argument("--every", type=int, default=50, help="a curve point every N steps")
    p.add_argument("--out", type=Path, default=Path("results/real_pairs/learning_curves"))
    a = p.parse_args(argv)
    runs = [r for f in a.folders for r in (runs_of(f) if f.is_dir() else [])]
    if not runs:
        print("error: no run (a folder with train_log.csv) in " + " ".join(map(str, a.folders)), file=sys.stderr)
        return 2
    out = [read_run(r, a.window, a.every) for r in runs]
    print("| run | steps | hours | loss first -> last | val synthetic r | val real r (constant 1) |")
    print("|---|---|---|---|---|---|")
    for r in out:
        fmt = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
        print(
            f"| {r['run']} | {r['steps']} | {r['hours']} | {r['loss_first']:.3f} -> {r['loss_last']:.3f} | "
            f"{fmt(r['val_synthetic_mean_r'])} | {fmt(r['val_real_mean_r'])} ({fmt(r['val_real_constant_mean_r'])}) |"
        )
    a.out.parent.mkdir(parents=True, exist_ok=True)
    write_text(
        a.out.with_suffix(".json"),
        json.dumps({"window": a.window, "runs": out, "commit": git_commit()}, indent=1) + "\n",
    )
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for r in out:
        c = np.array(r["curve"])
        ax.plot(c[:, 0], c[:, 1], label=Path(r["run"]).parent.name + "/" + Path(r["run"]).name)
    ax.set_xlabel("step")
    ax.set_ylabel(f"training loss (KL, mean of {a.window} steps)")
    ax.legend(fontsize=6)
    fig.tight_layout()
    tmp = a.out.with_name(a.out.name + ".tmp.png")
    fig.savefig(tmp, dpi=90)
    tmp.replace(a.out.with_suffix(".png"))
    print(f"wrote {a.out.with_suffix('.json')} and {a.out.with_suffix('.png')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
