"""How localscale/assets/kodim01_{a,b}.jpg (the bundled example pair) were made (needs the shared photo pool; users don't need to run it).

A = Kodak kodim01 (held out from training), B = A seen under a strong perspective
(left side zoomed in ~2.6x, right side ~0.9x), B's empty region filled from kodim14.
The ground-truth homography A->B is written to ``localscale/assets/H_a_b.txt`` (HPatches convention).
"""

import sys
from pathlib import Path

import cv2
import numpy as np

from localscale.geometry import homography_scale_map, warp_image
from localscale.io import load_image

root = Path(sys.argv[1] if len(sys.argv) > 1 else "../shared/data/train_images")
assets = Path(__file__).resolve().parent.parent / "localscale" / "assets"
a = load_image(root / "kodak_kodim01.jpg")
fill = load_image(root / "kodak_kodim14.jpg")
h, w = a.shape[:2]
c = np.array([[1, 0, -(w - 1) / 2], [0, 1, -(h - 1) / 2], [0, 0, 1.0]])
persp = np.array([[1, 0, 0], [0, 1, 0], [-0.45 / (w / 2), 0.08 / (h / 2), 1]])
rot = np.deg2rad(8)
sr = 1.4 * np.array([[np.cos(rot), -np.sin(rot), 0], [np.sin(rot), np.cos(rot), 0], [0, 0, 1 / 1.4]])
back = np.array([[1, 0, (w - 1) / 2 + 20], [0, 1, (h - 1) / 2], [0, 0, 1.0]])
H = back @ sr @ persp @ c
H /= H[2, 2]
b, _ = warp_image(a, H, (h, w), fill=fill)
cv2.imwrite(str(assets / "kodim01_a.jpg"), a[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])
cv2.imwrite(str(assets / "kodim01_b.jpg"), b[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])
np.savetxt(assets / "H_a_b.txt", H, fmt="%.10g")
s = homography_scale_map(H, h, w)
print(f"scale A->B over A: min {np.nanmin(s):.2f}, max {np.nanmax(s):.2f}")
