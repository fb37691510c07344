"""Fine-tune the bundled scale models on synthetic + labelled real pairs, leaving one collection out.

For every collection with labels (``LABELS/<collection>/pairs.npz``, from ``train/label_collections.py``)
and each model (``local``, ``global``), one run trains from the bundled weights on the bundled
model's synthetic pair options plus the real pairs of all other collections (``--real-fraction``
of the samples), validating on the collection left out; then, unless ``--no-final``, one run
on every collection. Each run resumes from its ``last.pt``, so the script resumes after an
interruption; finished runs (``model.pt`` present) are skipped.

    OMP_NUM_THREADS=1 python train/train_real_pairs.py --labels runs/real_models --out runs/real --steps 200
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from localscale.training import TrainConfig, train

WEIGHTS = Path(__file__).resolve().parents[1] / "localscale" / "weights"
BUNDLED = {"local": WEIGHTS / "local_scalenet.pt", "global": WEIGHTS / "scalenet.pt"}
CARDS = {"local": WEIGHTS / "local_scalenet.json", "global": WEIGHTS / "scalenet.json"}
#: options of a run that are not the bundled model's own training options
RUN_OPTIONS = ("out", "steps", "lr_milestones", "init_weights", "seed", "val_every", "ckpt_every", "threads")


def run_config(model: str, out: Path, train_files: list, val_file: str, args) -> TrainConfig:
    """The bundled model's training options, from its model card, with this run's data and schedule."""
    bundled = json.loads(CARDS[model].read_text())["training"]["config"]
    cfg = TrainConfig(
        **{k: (tuple(v) if isinstance(v, list) else v) for k, v in bundled.items() if k not in RUN_OPTIONS}
    )
    cfg.out = str(out)
    cfg.steps = args.steps
    cfg.lr = args.lr
    cfg.lr_milestones = (int(args.steps * 0.8),)
    cfg.init_weights = str(BUNDLED[model])
    cfg.seed = args.seed
    cfg.val_every = args.steps
    cfg.ckpt_every = 25
    cfg.threads = args.threads
    cfg.val_pairs = args.val_pairs
    cfg.freeze_extractor = args.freeze_extractor
    cfg.real_pairs = ",".join(str(f) for f in train_files)
    cfg.real_fraction = args.real_fraction
    cfg.real_val_pairs = val_file
    return cfg


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--labels", type=Path, default=Path("runs/real_models"))
    p.add_argument("--out", type=Path, default=Path("runs/real"))
    p.add_argument("--models", nargs="+", default=["local", "global"], choices=["local", "global"])
    p.add_argument("--held-out", nargs="*", default=None, help="collections to leave out (default: each in turn)")
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--lr", type=float, default=5e-5)
    p.add_argument("--real-fraction", type=float, default=0.5)
    p.add_argument("--val-pairs", type=int, default=64)
    p.add_argument("--freeze-extractor", action="store_true")
    p.add_argument("--seed", type=int, default=21)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--no-final", action="store_true", help="skip the run on every collection")
    args = p.parse_args(argv)
    files = {d.name: d / "pairs.npz" for d in sorted(args.labels.iterdir()) if (d / "pairs.npz").exists()}
    if len(files) < 2:
        print(f"error: need labels of >= 2 collections under {args.labels}, found {len(files)}", file=sys.stderr)
        return 2
    splits = [(h, [f for n, f in files.items() if n != h], str(files[h])) for h in (args.held_out or files)]
    if not args.no_final:
        splits.append(("all", list(files.values()), ""))
    for model in args.models:
        for held, train_files, val_file in splits:
            out = args.out / f"{model}_without_{held}" if held != "all" else args.out / f"{model}_all"
            if (out / "model.pt").exists():
                print(f"{out}: done, skipped", flush=True)
                continue
            print(f"{out}: {model}, real pairs of {len(train_files)} collections, held out: {held}", flush=True)
            row = train(run_config(model, out, train_files, val_file, args))
            print(f"{out}: {json.dumps(row)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
