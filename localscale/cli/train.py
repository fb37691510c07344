"""``localscale-train`` (or ``python -m localscale.cli.train``): the trainer's command line (options mirror
:class:`~localscale.training.TrainConfig`)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from ..core.errors import LocalScaleError
from ..training import TrainConfig, TrainingDiverged, train


def parse_args(argv: list[str] | None = None, model: str | None = None) -> TrainConfig:
    from .options import OneLineErrorParser

    p = OneLineErrorParser(
        prog="localscale-train", description="Train Local-ScaleNet or ScaleNet on synthetic homography pairs."
    )
    for f in dataclasses.fields(TrainConfig):
        if model is not None and f.name == "model":
            continue
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        if model == "global" and f.name == "out":
            default = "runs/global"
        flag = "--" + f.name.replace("_", "-")
        if isinstance(default, bool):
            p.add_argument(flag, action=argparse.BooleanOptionalAction, default=default)
        elif isinstance(default, tuple):
            p.add_argument(flag, type=int, nargs="*", default=list(default))
        else:
            p.add_argument(flag, type=type(default), default=default)
    p.add_argument(
        "--max-steps-this-run",
        type=int,
        default=None,
        help="stop after this many steps (resume later with the same command)",
    )
    a = vars(p.parse_args(argv))
    max_run = a.pop("max_steps_this_run")
    if model is not None:
        a["model"] = model
    a["lr_milestones"] = tuple(a["lr_milestones"])
    cfg = TrainConfig(**a)
    cfg._max_steps_this_run = max_run  # type: ignore[attr-defined]
    return cfg


def main(argv: list[str] | None = None, model: str | None = None) -> int:
    cfg = parse_args(argv, model)
    try:
        res = train(cfg, getattr(cfg, "_max_steps_this_run", None))
    except (LocalScaleError, TrainingDiverged) as e:
        print(f"error: {' '.join(str(e).split())}", file=sys.stderr)
        return 2
    except OSError as e:  # a file the run reads or writes (full disk, no permission)
        where = f"{e.filename}: " if e.filename else ""
        print(f"error: {where}{e.strerror or e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"interrupted; resume with the same command (checkpoint: {Path(cfg.out) / 'last.pt'})", file=sys.stderr)
        return 130
    if res:
        print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
