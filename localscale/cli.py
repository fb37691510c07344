"""``localscale`` command line; every command mirrors a Python API call.

    localscale predict A B -o out/              # LocalScaleNet.predict  -> .npy, float TIFF, colour PNG
    localscale predict --pairs pairs.txt -o out/  # predict_pairs with the feature cache
    localscale show A B -o fig.png [--H H_a_b]  # viz.plot_scale_prediction
    localscale demo [-o out/]                   # show on the bundled example pair
    localscale scale A B                        # ScaleNet.predict (global scale)
    localscale rectify A B -o out/              # resize one image by the global scale
    localscale match A B -o out/ --correction local
    localscale eval-hpatches ROOT
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from .errors import LocalScaleError

ASSETS = Path(__file__).resolve().parent / "assets"   #: the example pair (also in examples/)


def _load_local(path: str | None, device: str):
    from .models import LocalScaleNet

    return LocalScaleNet.from_pretrained(path, device=device)


def _load_global(path: str | None, device: str):
    from .models import ScaleNet

    return ScaleNet.from_pretrained(path, device=device)


def write_scale_map(pred, out_dir: Path, stem: str) -> list[Path]:
    """Write ``<stem>_scale.npy`` (float32), ``_scale.tif`` (float32 TIFF), ``_scale.png`` (colour),
    ``_confidence.npy``."""
    import cv2

    from .viz import colorize_log2_scale

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [out_dir / f"{stem}_scale.npy", out_dir / f"{stem}_scale.tif", out_dir / f"{stem}_scale.png",
             out_dir / f"{stem}_confidence.npy"]
    np.save(paths[0], pred.scale.astype(np.float32))
    if not cv2.imwrite(str(paths[1]), pred.scale.astype(np.float32)):
        raise LocalScaleError(f"cannot write {paths[1]}")
    cv2.imwrite(str(paths[2]), colorize_log2_scale(pred.scale)[..., ::-1])
    np.save(paths[3], pred.confidence.astype(np.float32))
    return paths


def read_pairs_file(path: str | Path) -> list[tuple[Path, Path]]:
    """``A B`` per line (paths relative to the file's folder or absolute); ``#`` starts a comment."""
    path = Path(path)
    if not path.is_file():
        raise LocalScaleError(f"pairs file not found: {path}")
    pairs = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) != 2:
            raise LocalScaleError(f"{path}:{n}: expected two image paths, got {len(parts)} field(s)")
        pairs.append(tuple((path.parent / p) if not Path(p).is_absolute() else Path(p) for p in parts))
    return pairs


def cmd_predict(args) -> int:
    model = _load_local(args.model, args.device)
    out = Path(args.output)
    if args.pairs:
        from tqdm import tqdm

        from .cache import FeatureCache, predict_pairs

        pairs = read_pairs_file(args.pairs)
        cache = FeatureCache(model, max_bytes=int(args.cache_mb * 2**20), bf16=args.bf16)
        failed = 0
        for i, (pair, pred) in enumerate(tqdm(predict_pairs(model, pairs, cache, args.batch_size),
                                              total=len(pairs), desc="pairs", unit="pair")):
            if isinstance(pred, Exception):
                failed += 1
                tqdm.write(f"error: pair {pair[0]} {pair[1]}: {pred}", file=sys.stderr)
                continue
            write_scale_map(pred, out, f"{i:05d}_{Path(pair[0]).stem}_{Path(pair[1]).stem}")
        print(f"{len(pairs) - failed}/{len(pairs)} pairs written to {out} "
              f"(cache: {cache.misses} images encoded, {cache.hits} reused)")
        return 1 if failed else 0
    if not (args.image_a and args.image_b):
        raise LocalScaleError("predict: give two images A B, or --pairs FILE")
    pred = model.predict(args.image_a, args.image_b, hard=args.hard, bf16=args.bf16, planar=args.planar)
    stem = f"{Path(args.image_a).stem}_{Path(args.image_b).stem}"
    for p in write_scale_map(pred, out, stem):
        print(p)
    s = pred.scale
    print(f"S(A->B): median {np.median(s):.3f}, min {s.min():.3f}, max {s.max():.3f}", file=sys.stderr)
    return 0


def show_pair(image_a, image_b, output, H=None, model=None, title=None) -> Path:
    """Predict and write the figure (A, B, log2 scale, confidence, and GT/error when ``H`` is given)."""
    from .geometry import covisible_mask, homography_scale_map
    from .io import load_image, read_homography
    from .viz import plot_scale_prediction

    model = model or _load_local(None, "cpu")
    a, b = load_image(image_a, "image A"), load_image(image_b, "image B")
    pred = model.predict(a, b)
    gt = mask = None
    if H is not None:
        Hm = read_homography(H)
        gt = homography_scale_map(Hm, *a.shape[:2])
        mask = covisible_mask(Hm, a.shape[:2], b.shape[:2])
    plot_scale_prediction(a, b, pred.scale, pred.confidence, gt, mask, output, title)
    return Path(output)


def cmd_show(args) -> int:
    print(show_pair(args.image_a, args.image_b, args.output, args.H, _load_local(args.model, args.device)))
    return 0


def cmd_demo(args) -> int:
    a, b, H = ASSETS / "kodim01_a.jpg", ASSETS / "kodim01_b.jpg", ASSETS / "H_a_b.txt"
    out = Path(args.output) / "demo.png"
    show_pair(a, b, out, H, _load_local(args.model, args.device), title="localscale demo: Local-ScaleNet")
    print(out)
    return 0


def cmd_scale(args) -> int:
    p = _load_global(args.model, args.device).predict(args.image_a, args.image_b)
    if args.json:
        print(json.dumps({"scale": p.scale, "scale_ab": p.scale_ab, "scale_ba": p.scale_ba,
                          "hard_scale": p.hard_scale, "probs_ab": p.probs_ab.round(4).tolist()}))
    else:
        print(f"S(A->B) = {p.scale:.4f}  (A->B {p.scale_ab:.4f}, 1/(B->A) {1 / p.scale_ba:.4f}, "
              f"D-ScaleNet {p.hard_scale:.4f})")
    return 0


def rectify_pair(image_a, image_b, output, model=None) -> dict:
    """Downscale the image whose content is bigger by the global scale so the pair has scale ~1."""
    import cv2

    from .io import load_image

    model = model or _load_global(None, "cpu")
    a, b = load_image(image_a, "image A"), load_image(image_b, "image B")
    s = model.predict(a, b).scale
    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    which, factor = ("B", 1 / s) if s > 1 else ("A", s)
    img = b if which == "B" else a
    resized = cv2.resize(img, (max(1, round(img.shape[1] * factor)), max(1, round(img.shape[0] * factor))),
                         interpolation=cv2.INTER_AREA)
    src = Path(image_b if which == "B" else image_a) if not hasattr(image_a, "shape") else Path(which)
    dst = out / f"{src.stem}_rectified.png"
    cv2.imwrite(str(dst), resized[..., ::-1])
    return {"scale": s, "resized": which, "factor": factor, "output": str(dst)}


def cmd_rectify(args) -> int:
    r = rectify_pair(args.image_a, args.image_b, args.output, _load_global(args.model, args.device))
    print(f"S(A->B) = {r['scale']:.4f}: image {r['resized']} resized by {r['factor']:.4f} -> {r['output']}")
    return 0


def cmd_match(args) -> int:
    from .features.pipeline import run_match_cli

    return run_match_cli(args) or 0


def cmd_eval_hpatches(args, rest) -> int:
    from .evaluation.hpatches import main as hp_main

    return hp_main(([args.root] if args.root else []) + rest) or 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="localscale", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)

    def common(sp, model_help="checkpoint (default: the bundled model)"):
        sp.add_argument("--model", default=None, help=model_help)
        sp.add_argument("--device", default="cpu")

    sp = sub.add_parser("predict", help="per-pixel scale map S(A->B) -> .npy/.tif/.png")
    sp.add_argument("image_a", nargs="?")
    sp.add_argument("image_b", nargs="?")
    sp.add_argument("-o", "--output", default="out")
    sp.add_argument("--pairs", help="text file with one 'A B' pair per line")
    sp.add_argument("--hard", action="store_true", help="D-ScaleNet (arg-max bin) read-out")
    sp.add_argument("--planar", action="store_true", help="fit a homography's scale field (planar scenes only)")
    sp.add_argument("--bf16", action="store_true", help="bfloat16 autocast (fast on CPUs with AMX)")
    sp.add_argument("--batch-size", type=int, default=8)
    sp.add_argument("--cache-mb", type=float, default=256, help="feature cache bound for --pairs")
    common(sp)
    sp.set_defaults(func=cmd_predict)

    sp = sub.add_parser("show", help="figure: A, B, predicted map, confidence (+ GT and error with --H)")
    sp.add_argument("image_a")
    sp.add_argument("image_b")
    sp.add_argument("-o", "--output", default="out/scale.png")
    sp.add_argument("--H", help="ground-truth homography A->B (3x3 text file)")
    common(sp)
    sp.set_defaults(func=cmd_show)

    sp = sub.add_parser("demo", help="run on the bundled example pair and write out/demo.png")
    sp.add_argument("-o", "--output", default="out")
    common(sp)
    sp.set_defaults(func=cmd_demo)

    sp = sub.add_parser("scale", help="global scale S(A->B) with ScaleNet")
    sp.add_argument("image_a")
    sp.add_argument("image_b")
    sp.add_argument("--json", action="store_true")
    common(sp)
    sp.set_defaults(func=cmd_scale)

    sp = sub.add_parser("rectify", help="resize one image by the global scale so the pair has scale ~1")
    sp.add_argument("image_a")
    sp.add_argument("image_b")
    sp.add_argument("-o", "--output", default="out")
    common(sp)
    sp.set_defaults(func=cmd_rectify)

    sp = sub.add_parser("match", help="keypoints + scale-corrected patches + descriptors + mutual NN")
    sp.add_argument("image_a")
    sp.add_argument("image_b")
    sp.add_argument("-o", "--output", default="out")
    sp.add_argument("--correction", choices=["none", "global", "local", "fused", "gt"], default="local",
                    help="patch-size correction: fused = local map shape + global ScaleNet level")
    sp.add_argument("--H", help="ground-truth homography A->B (needed for --correction gt; colours inliers)")
    sp.add_argument("--descriptor", choices=["hardnet", "sift"], default="hardnet")
    sp.add_argument("--num-features", type=int, default=1000)
    sp.add_argument("--ratio", type=float, default=None, help="ratio test threshold (default: mutual NN only)")
    sp.add_argument("--orientation", choices=["upright", "gradient"], default="upright",
                    help="patch orientation: upright, or the dominant gradient (for strong in-plane rotation)")
    sp.add_argument("--local-model", default=None)
    sp.add_argument("--global-model", default=None)
    sp.add_argument("--device", default="cpu")
    sp.set_defaults(func=cmd_match)

    sp = sub.add_parser("eval-hpatches", add_help=False,
                        help="HPatches-style MMA evaluation (localscale eval-hpatches --help for its options)")
    sp.add_argument("root", nargs="?")
    sp.set_defaults(func=None)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser()
    args, rest = parser.parse_known_args(argv)
    try:
        if args.command == "eval-hpatches":
            return cmd_eval_hpatches(args, rest)
        if rest:
            parser.error(f"unrecognized arguments: {' '.join(rest)}")
        return args.func(args)
    except LocalScaleError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
