"""Make HPatches-layout sequences from photos (random strong-perspective homographies).

    python eval/make_sequences.py PHOTO_DIR OUT_DIR [--num 20] [--size 480] [--images 6] [--seed 0] [--held-out] [--crop 0.7]

``--held-out`` uses only the held-out part of ``localscale.data.split_images`` (use it for
the training photo pool, so evaluation never sees training photos).
"""

import argparse
import sys

from localscale.data import list_images, split_images
from localscale.evaluation.synthetic import make_sequences


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("photos")
    p.add_argument("out")
    p.add_argument("--num", type=int, default=None, help="number of sequences (default: all photos)")
    p.add_argument("--size", type=int, default=480, help="longer side of image 1")
    p.add_argument("--images", type=int, default=6, help="images per sequence")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--held-out", action="store_true")
    p.add_argument(
        "--crop",
        type=float,
        default=1.0,
        help="< 1: image 1 is this central part of the photo, the others show its real surroundings",
    )
    a = p.parse_args(argv)
    if not 0 < a.crop <= 1:
        p.error(f"--crop must be in (0, 1], got {a.crop}")
    files = list_images(a.photos)
    if a.held_out:
        files = split_images(files)[1]
    files = files[: a.num] if a.num else files
    folders = make_sequences(files, a.out, a.images, a.size, a.seed, crop=a.crop)
    print(f"wrote {len(folders)} sequences to {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
