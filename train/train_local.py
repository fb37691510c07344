"""Train Local-ScaleNet: ``python train/train_local.py --data DIR --out runs/local [--device cuda]``.

Multi-GPU: ``torchrun --nproc_per_node 4 train/train_local.py --device cuda ...``.
All options: ``--help`` (they mirror :class:`localscale.training.TrainConfig`).
"""

import sys

from localscale.cli.train import main

if __name__ == "__main__":
    sys.exit(main(model="local"))
