"""HPatches-style evaluation: ``python eval/hpatches.py ROOT -o OUT [options]`` (see ``--help``).

Thin wrapper of :func:`localscale.evaluation.hpatches.main` (also ``localscale eval-hpatches``).
"""
import sys

import torch

from localscale.evaluation.hpatches import main

if __name__ == "__main__":
    torch.set_num_threads(1)
    sys.exit(main())
