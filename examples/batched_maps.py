"""Batched tensor API: scale maps of several pairs in one network pass, on any device.

    python examples/batched_maps.py [--device cuda]

The batch here is the example pair in both directions, (A, B) and (B, A): one call gives the two
maps that the keypoint rescaling needs (S_{A->B} on A, S_{B->A} on B).
"""

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from localscale import LocalScaleNet, ScaleNet
from localscale.geometry import covisible_mask, homography_scale_map
from localscale.io import load_image, read_homography

ASSETS = Path(__file__).resolve().parent.parent / "localscale" / "assets"
p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
args = p.parse_args()

a, b = load_image(ASSETS / "kodim01_a.jpg"), load_image(ASSETS / "kodim01_b.jpg")
H = read_homography(ASSETS / "H_a_b.txt")
to_tensor = lambda rgb: torch.from_numpy(rgb).permute(2, 0, 1).float() / 255  # 3 x H x W in [0, 1]
images_a = torch.stack([to_tensor(a), to_tensor(b)]).to(args.device)  # B x 3 x H x W
images_b = torch.stack([to_tensor(b), to_tensor(a)]).to(args.device)

net = LocalScaleNet.from_pretrained(device=args.device)
t = time.perf_counter()
out = net.predict_batch(images_a, images_b)  # B x H x W tensors on args.device
elapsed = time.perf_counter() - t
print(
    f"predict_batch: {tuple(out.scale.shape)} scale maps on {out.scale.device} in {elapsed:.2f} s "
    f"(confidence {tuple(out.confidence.shape)}, visible: {out.visible is not None})"
)

# the per-pair one-pass map (anchor=False) is the same for the same input (here the same float
# images; a uint8 array is resized before its conversion to float, which moves the map by ~1e-3)
single = net.predict(
    images_a[0].permute(1, 2, 0).cpu().numpy(), images_b[0].permute(1, 2, 0).cpu().numpy(), anchor=False
).scale
print(f"max |predict_batch - predict| on (A, B): {np.abs(out.scale[0].cpu().numpy() - single).max():.2e}")

for i, (Hi, shape_this, shape_other) in enumerate(
    [(H, a.shape[:2], b.shape[:2]), (np.linalg.inv(H), b.shape[:2], a.shape[:2])]
):
    gt = homography_scale_map(Hi, *shape_this)
    mask = covisible_mask(Hi, shape_this, shape_other)
    err = np.exp(np.abs(np.log(out.scale[i].cpu().numpy()[mask] / gt[mask]))).mean()
    print(
        f"pair {i} ({'A->B' if i == 0 else 'B->A'}): mean scale-ratio error {err:.3f} "
        f"(ground-truth scales {gt[mask].min():.2f} .. {gt[mask].max():.2f})"
    )

g = ScaleNet.from_pretrained(device=args.device)
print("ScaleNet.predict_batch (global S per pair):", [round(float(s), 3) for s in g.predict_batch(images_a, images_b)])
