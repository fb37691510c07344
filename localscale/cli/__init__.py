"""``localscale`` command line; every command mirrors a Python API call.

    localscale predict A B -o out/                # LocalScaleNet.predict  -> .npy, float TIFF, colour PNG
    localscale predict --pairs pairs.txt -o out/  # predict_pairs with the feature cache (+ out/index.tsv)
    localscale show A B -o out/ [--H H_a_b]       # viz.plot_scale_prediction -> out/<A>_<B>_figure.png
    localscale demo [-o out/]                     # show on the bundled example pair
    localscale scale A B                          # ScaleNet.predict (global scale)
    localscale rectify A B -o out/                # resize one image by the global scale (+ JSON sidecar)
    localscale match A B -o out/ --correction local
    localscale eval-hpatches ROOT -o out/

Every command takes the same model options: ``--local-weights`` / ``--global-weights``
(checkpoints; default: the bundled weights), ``--device`` and, where a network runs, ``--bf16``.
``-o`` is always an output folder. Bad input is a one-line ``error: ...`` and exit code 2.
"""

from ..io.pairs_file import read_pairs_file
from .common import ASSETS, check_output_dir, pair_name
from .main import build_parser, main

__all__ = ["main", "build_parser", "ASSETS", "check_output_dir", "pair_name", "read_pairs_file"]
