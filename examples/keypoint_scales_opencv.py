"""OpenCV keypoints (one octave of SIFT, or single-level ORB) rescaled by Local-ScaleNet's maps,
described by a patch descriptor and matched; compared with the same keypoints left as detected.

    python examples/keypoint_scales_opencv.py [--detector orb|sift] [--descriptor sift|hardnet]

``sift`` is kornia's training-free SIFTDescriptor on patches, ``hardnet`` the bundled HardNet
(``localscale.features.get_descriptor("hardnet")``). The example pair has a strong perspective
(parts of B are zoomed ~2.6x); its ground-truth homography scores the matches.
"""

import argparse
from pathlib import Path

import cv2
import numpy as np
from kornia.feature import SIFTDescriptor

from localscale import LocalScaleNet
from localscale.features import describe_lafs, get_descriptor, laf_from_opencv, rescale_keypoint_pair
from localscale.io import load_image, read_homography
from localscale.matching import match_descriptors, reprojection_errors

ASSETS = Path(__file__).resolve().parent.parent / "localscale" / "assets"
p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
p.add_argument("--detector", choices=["orb", "sift"], default="orb")
p.add_argument("--descriptor", choices=["sift", "hardnet"], default="sift")
p.add_argument("--num-features", type=int, default=1000)
p.add_argument(
    "--images",
    nargs=3,
    default=[ASSETS / "kodim01_a.jpg", ASSETS / "kodim01_b.jpg", ASSETS / "H_a_b.txt"],
    metavar=("A", "B", "H"),
    help="image A, image B and the homography A->B",
)
args = p.parse_args()

a, b = load_image(args.images[0]), load_image(args.images[1])
H = read_homography(args.images[2])


def detect(rgb):
    """A single-scale detector: the correction supplies the scale change, so it must not adapt itself."""
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    if args.detector == "orb":  # one pyramid level: every size is 31
        return cv2.ORB_create(args.num_features, nlevels=1, edgeThreshold=16).detect(gray, None)
    kps = cv2.SIFT_create(4 * args.num_features).detect(gray, None)
    octave = [(k.octave & 255) - 256 * ((k.octave & 255) >= 128) for k in kps]  # -1 .. n, as in OpenCV
    one = [k for k, o in zip(kps, octave) if o == 0]  # one octave only
    return sorted(one, key=lambda k: -k.response)[: args.num_features]


kps_a, kps_b = detect(a), detect(b)

# 1. the pair's maps: S_{A->B} on A and S_{B->A} on B
net = LocalScaleNet.from_pretrained()
s_ab, s_ba = net.predict(a, b).scale, net.predict(b, a).scale

# 2. rescale the keypoints (new cv2.KeyPoint, size x max(1, 1/S)) so both patches cover the same content.
#    ORB: every size is 31 (its descriptor's patch), kept as the base. SIFT: even within one octave its
#    sizes follow the zoom, so a fixed support (base_radius, pixels) replaces them before the correction.
base_radius, mr_size = (None, 0.5) if args.detector == "orb" else (12.0, 1.0)  # LAF scale = mr_size x size
res_a, res_b = rescale_keypoint_pair(kps_a, kps_b, s_ab, s_ba, base_radius=base_radius, mr_size=mr_size)
same_a, same_b = rescale_keypoint_pair(kps_a, kps_b, None, None, base_radius=base_radius, mr_size=mr_size)

# 3. describe the patches of the keypoints' LAFs and match (mutual nearest neighbours)
descriptor = SIFTDescriptor(32, rootsift=True) if args.descriptor == "sift" else get_descriptor("hardnet")
xy_a = np.array([k.pt for k in kps_a], np.float32)
xy_b = np.array([k.pt for k in kps_b], np.float32)
for name, ka, kb in (("uncorrected", same_a, same_b), ("rescaled", res_a, res_b)):
    da = describe_lafs(a, laf_from_opencv(ka, mr_size), descriptor)
    db = describe_lafs(b, laf_from_opencv(kb, mr_size), descriptor)
    _, matches = match_descriptors(da, db)
    err = reprojection_errors(xy_a, xy_b, matches.numpy(), H)
    print(
        f"{args.detector}+{args.descriptor} {name:>11}: {len(kps_a)}/{len(kps_b)} keypoints, "
        f"{len(matches)} matches, {(err < 5).sum()} correct (< 5 px), accuracy {(err < 5).mean():.1%}"
    )
enlarged = np.array([k.size for k in res_b]) / np.array([k.size for k in same_b])
print(f"B's keypoints enlarged up to x{enlarged.max():.2f} (median x{np.median(enlarged):.2f})")
