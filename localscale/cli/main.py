"""The ``localscale`` parser and entry point."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import warnings

from ..core.errors import LocalScaleError
from .figures import cmd_demo, cmd_rectify, cmd_scale, cmd_show
from .match import cmd_eval_hpatches, cmd_match
from .options import (
    HelpFormatter,
    OneLineErrorParser,
    _LazyArgumentParser,
    add_engine_options,
    add_hpatches_options,
    add_match_options,
    add_model_options,
    add_refine_matcher_options,
    add_refine_options,
    positive_float,
    positive_int,
)
from .predict import cmd_predict
from .signals import SIGTERM_STATE, Terminated, _on_sigterm

EXAMPLES = {
    "predict": """examples:
  localscale predict localscale/assets/kodim01_a.jpg localscale/assets/kodim01_b.jpg -o out/
      -> out/kodim01_a_kodim01_b_scale.{npy,tif,png}, _confidence.npy
  localscale predict --pairs pairs.txt -o out/ --batch-size 8
  localscale predict wide.jpg closeup.jpg -o out/ --search     (strong zoom or low overlap)
  localscale predict localscale/assets/kodim01_a.jpg localscale/assets/kodim01_b.jpg -o out/ --refine
      -> also out/<A>_<B>_refined_scale.npy, _refined_source.{npy,png} (0 network, 1 homography, 2 matches), _geometry.json
  localscale predict A.jpg B.jpg -o out/ --refine --matcher aliked-lightglue   (geometry from auto)
      pairs.txt: one pair per line, 'A<TAB>B' (names as written) or 'A B' with shell-like
      quoting ("my photo.jpg" b.jpg); relative to the file's folder; lines starting with '#'
      are comments. A rerun skips pairs whose outputs are complete and whose images, weights
      and options are unchanged (--overwrite redoes them).
      -> out/<index>_<A>_<B>_scale.* (index = the pair's position in the file; <A> is
         <folder>-<stem> when stems collide; _scale.json records the inputs) and out/index.tsv
         (index, line, A, B, status, output). A bad pair is a 'warning:' line and exit code 1,
         the other pairs still run; a pairs file with no usable pair is an 'error:', exit 2.""",
    "show": """example:
  localscale show seq/1.ppm seq/2.ppm --H seq/H_1_2 -o figures/
      -> figures/1_2_figure.png
  localscale show scene/a.jpg scene/b.jpg --refine --colmap-model scene/sparse/0 -o figures/
      (3D scene: refined map, its source layer, truth at the model's shared 3D points)""",
    "demo": """example:
  localscale demo -o out/      -> out/demo.png""",
    "scale": """example:
  localscale scale localscale/assets/kodim01_a.jpg localscale/assets/kodim01_b.jpg --json
  localscale scale wide.jpg closeup.jpg --search     (strong zoom or low overlap)""",
    "rectify": """example:
  localscale rectify v_churchill/1.ppm v_churchill/2.ppm -o out/
      -> out/v_churchill-1_v_churchill-2_rectified_B.png (the resized image) and
         out/v_churchill-1_v_churchill-2_rectified.json (scale, resized image, factor, sizes)""",
    "match": """example:
  localscale match localscale/assets/kodim01_a.jpg localscale/assets/kodim01_b.jpg -o out/ --correction fused \\
      --H localscale/assets/H_a_b.txt --num-features 500
      -> out/matches.npz, out/matches.png""",
    "eval-hpatches": """example:
  localscale eval-hpatches hpatches-sequences-release/ -o results/hpatches --methods none local gt
      ROOT/<seq>/1.ppm .. 6.ppm and H_1_2 .. H_1_6; writes results_<descriptor>.{json,md},
      splits.csv and mma_*.png into -o
  localscale eval-hpatches ROOT -o out/ --methods none local --detector orb
      -> out/results_orb_<descriptor>.{json,md}: the same with one-level ORB keypoints""",
}


def build_parser() -> argparse.ArgumentParser:

    p = OneLineErrorParser(
        prog="localscale", description=sys.modules[__package__].__doc__, formatter_class=HelpFormatter
    )
    from .. import __version__

    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_LazyArgumentParser)

    def command(name, summary, description, add_options=None):
        return sub.add_parser(
            name,
            help=summary,
            description=description,
            epilog=EXAMPLES[name],
            formatter_class=HelpFormatter,
            add_options=add_options,
        )

    _add_map_commands(command)
    _add_scale_and_match_commands(command)
    from .reconstruct import add_reconstruct_parser

    add_reconstruct_parser(sub)
    return p


def _add_map_commands(command) -> None:
    from .options import add_image_options

    sp = command(
        "predict",
        "per-pixel scale map S(A->B) -> .npy/.tif/.png",
        "Per-pixel scale map S(A->B) of Local-ScaleNet for one pair (A B) or for every pair of a\n"
        "pairs file (--pairs, with a feature cache: each image is encoded once).",
    )
    sp.add_argument("image_a", nargs="?", help="image A (omit with --pairs)")
    sp.add_argument("image_b", nargs="?", help="image B (omit with --pairs)")
    sp.add_argument("-o", "--output", default="out", help="output folder")
    sp.add_argument(
        "--pairs",
        help="text file with one pair per line: 'A<TAB>B', or 'A B' with shell-like "
        "quoting for names with spaces (default: none, predict A B)",
    )
    sp.add_argument("--hard", action="store_true", help="D-ScaleNet (arg-max bin) read-out")
    sp.add_argument("--planar", action="store_true", help="fit a homography's scale field (planar scenes only)")
    sp.add_argument(
        "--no-anchor",
        action="store_true",
        help="the plain one-pass map (default: the pass anchored on ScaleNet's scale and quarter turn, "
        "with windows under strong zoom, blended toward ScaleNet's scale where the map is unreliable; "
        "--pairs always gives the one-pass maps)",
    )
    sp.add_argument(
        "--search",
        action="store_true",
        help="window search: re-estimate on the windows of A or B (1/2, 1/4 of the sides) that share "
        "the most content with the other image; for strong zooms and low overlap, ~30x slower",
    )
    sp.add_argument("--batch-size", type=positive_int, default=8, help="pairs per network batch with --pairs")
    add_engine_options(sp, "--pairs")
    sp.add_argument("--cache-mb", type=positive_float, default=256, help="feature cache bound (MiB) with --pairs")
    sp.add_argument(
        "--overwrite",
        action="store_true",
        help="with --pairs: redo pairs whose outputs already exist (default: skip them)",
    )
    add_refine_matcher_options(add_refine_options(sp))
    add_model_options(sp, local=True, global_=False, model_alias="local")
    add_image_options(sp)
    sp.set_defaults(func=cmd_predict)

    sp = command(
        "show",
        "figure: A, B, predicted map, confidence (+ GT and error with --H)",
        "Figure of a pair: A, B, the predicted scale map S(A->B) (colours = factors), the\n"
        "confidence, and with --H the ground-truth map and the error.",
    )
    sp.add_argument("image_a", help="image A")
    sp.add_argument("image_b", help="image B")
    sp.add_argument("-o", "--output", default="out", help="output folder (figure <A>_<B>_figure.png)")
    sp.add_argument("--H", help="ground-truth homography A->B (3x3 text file; default: none)")
    sp.add_argument(
        "--refine",
        action="store_true",
        help="show the map refined by the verified geometry of SIFT matches, and its source layer "
        "(network / homography / matches)",
    )
    sp.add_argument(
        "--colmap-model",
        dest="colmap_model",
        metavar="DIR",
        help="COLMAP sparse model with both images: adds the per-point truth at their shared 3D points (default: none)",
    )
    add_model_options(sp, local=True, global_=False, model_alias="local")
    add_image_options(sp)
    sp.set_defaults(func=cmd_show)

    sp = command(
        "demo",
        "run show on the bundled example pair and write out/demo.png",
        "The figure of 'show' on the bundled example pair (with its ground-truth homography).",
    )
    sp.add_argument("-o", "--output", default="out", help="output folder (demo.png)")
    add_model_options(sp, local=True, global_=False, model_alias="local")
    sp.set_defaults(func=cmd_demo)


def _add_scale_and_match_commands(command) -> None:
    from .options import add_image_options

    sp = command(
        "scale",
        "global scale S(A->B) with ScaleNet",
        "Global scale S(A->B) of ScaleNet: consistency-checked, both directions, D-ScaleNet.",
    )
    sp.add_argument("image_a", help="image A")
    sp.add_argument("image_b", help="image B")
    sp.add_argument("--json", action="store_true", help="print one JSON object")
    sp.add_argument(
        "--search",
        action="store_true",
        help="run ScaleNet on the window pair Local-ScaleNet's window search keeps (see predict --search): "
        "strong zoom, low overlap; ~30x slower",
    )
    add_model_options(sp, local=True, global_=True, model_alias="global")
    add_image_options(sp)
    sp.set_defaults(func=cmd_scale)

    sp = command(
        "rectify",
        "resize one image by the global scale so the pair has scale ~1",
        "Downscale the image whose content is bigger by ScaleNet's global scale, so that the\n"
        "pair has scale ~1; writes the resized image and a JSON record of what was done.",
    )
    sp.add_argument("image_a", help="image A")
    sp.add_argument("image_b", help="image B")
    sp.add_argument("-o", "--output", default="out", help="output folder")
    add_model_options(sp, local=False, global_=True, model_alias="global")
    add_image_options(sp)
    sp.set_defaults(func=cmd_rectify)

    sp = command(
        "match",
        "match two images: our scale-corrected patches, SIFT, ALIKED/DISK/XFeat + LightGlue",
        "Match two images with a matcher (--matcher) and a scale correction (--correction): our\n"
        "scale-corrected patches (hardnet: the patch size of each keypoint follows the scale map),\n"
        "or SIFT / learned features on a pair rectified to scale 1 (the image whose content is\n"
        "bigger is shrunk by the correction's level).",
        add_options=add_match_options,
    )
    sp.set_defaults(func=cmd_match)

    sp = command(
        "eval-hpatches",
        "HPatches-style MMA evaluation",
        "HPatches-style mean matching accuracy of the correction methods on a folder of sequences.",
        add_options=add_hpatches_options,
    )
    sp.set_defaults(func=cmd_eval_hpatches)


def _warning_lines():
    """A ``warnings.showwarning`` that prints each Python warning as the CLI shows warnings: one
    ``warning: ...`` line on stderr, once per message."""
    seen: set = set()

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        text = " ".join(str(message).split())
        if text not in seen:
            seen.add(text)
            print(f"warning: {text}", file=sys.stderr, flush=True)

    return show


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    try:
        args = build_parser().parse_args(argv)
    except KeyboardInterrupt:
        print("interrupted; no partial output file was left", file=sys.stderr)
        return 130
    with warnings.catch_warnings():
        warnings.showwarning = _warning_lines()
        return _run(args)


def _run(args) -> int:
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        if getattr(args, "accept_damaged", False):
            from ..io import accepting_damaged

            with accepting_damaged():
                return args.func(args)
        return args.func(args)
    except Terminated:
        print("terminated; no partial output file was left (a rerun of predict --pairs resumes)", file=sys.stderr)
        return 143
    except LocalScaleError as e:
        print(f"error: {' '.join(str(e).split())}", file=sys.stderr)
        return 2
    except OSError as e:  # a file the command reads or writes (e.g. a full disk, no permission)
        where = f"{e.filename}: " if e.filename else ""
        print(f"error: {where}{e.strerror or e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted; no partial output file was left", file=sys.stderr)
        return 130
    finally:
        SIGTERM_STATE.reset()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
