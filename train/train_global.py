"""Train the global ScaleNet: ``python train/train_global.py --data DIR --out runs/global``.

Same trainer and options as ``train_local.py`` (shared code in :mod:`localscale.training`).
"""

import sys

from localscale.cli.train import main

if __name__ == "__main__":
    sys.exit(main(model="global"))
