"""Figure of one real pair: A, the local map, the refined map, the ground truth and the geometry weight.

python eval/refined_figure.py ../shared/data/sequences/v_churchill 3 -o docs/refined_map.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from localscale import LocalScaleNet
from localscale.geometry import covisible_mask, homography_scale_map
from localscale.io import load_image, read_homography
from localscale.matching.correction import CorrectionGate
from localscale.matching.pipeline import match_refined_pair
from localscale.viz import plot_refined_map


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("sequence", help="HPatches-layout folder (1.*, k.*, H_1_k)")
    p.add_argument("k", type=int, help="second image of the pair (1, k)")
    p.add_argument("-o", "--output", default="docs/refined_map.png")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    seq = Path(args.sequence)
    a = load_image(next(iter(sorted(seq.glob("1.*")))))
    b = load_image(next(iter(sorted(seq.glob(f"{args.k}.*")))))
    H = read_homography(seq / f"H_1_{args.k}")
    model = LocalScaleNet.from_pretrained()
    fwd, bwd = model.predict(a, b), model.predict(b, a)
    res = match_refined_pair(a, b, *CorrectionGate().apply_predictions(fwd, bwd), fwd.scale, bwd.scale)
    gt = homography_scale_map(H, *a.shape[:2])
    gt[~covisible_mask(H, a.shape[:2], b.shape[:2])] = np.nan
    v = res.verification
    title = f"{seq.name} 1-{args.k}: {v.model} {'verified' if v.verified else 'not verified'}, {v.num_inliers} inliers"
    plot_refined_map(a, fwd.scale, res.refined_a.scale, res.refined_a.source, gt, args.output, title)
    from PIL import Image  # a small PNG: 128-colour palette

    Image.open(args.output).convert("RGB").quantize(128).save(args.output, optimize=True)
    print(args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
