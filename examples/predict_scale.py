"""Predict the per-pixel scale between the example pair and compare with the ground truth.

python examples/predict_scale.py
"""

from pathlib import Path

import numpy as np

from localscale import LocalScaleNet, ScaleNet
from localscale.geometry import covisible_mask, homography_scale_map
from localscale.io import load_image, read_homography
from localscale.viz import plot_scale_prediction

ASSETS = Path(__file__).resolve().parent.parent / "localscale" / "assets"  # the bundled example pair
a, b = load_image(ASSETS / "kodim01_a.jpg"), load_image(ASSETS / "kodim01_b.jpg")
H = read_homography(ASSETS / "H_a_b.txt")

pred = LocalScaleNet.from_pretrained().predict(a, b)  # S_{A->B} per pixel of A
gt = homography_scale_map(H, *a.shape[:2])
mask = covisible_mask(H, a.shape[:2], b.shape[:2])
r = np.exp(np.abs(np.log(pred.scale[mask] / gt[mask])))
print(
    f"Local-ScaleNet: mean scale-ratio error {r.mean():.3f} over {mask.mean():.0%} co-visible pixels "
    f"(constant 1: {np.exp(np.abs(np.log(gt[mask]))).mean():.3f})"
)
print(
    f"ScaleNet global scale: {ScaleNet.from_pretrained().predict(a, b).scale:.3f} "
    f"(ground truth, log-mean over the co-visible region: {np.exp(np.log(gt[mask]).mean()):.3f})"
)
plot_scale_prediction(a, b, pred.scale, pred.confidence, gt, mask, path="example_scale.png")
print("wrote example_scale.png")
