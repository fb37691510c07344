"""argparse pieces of the ``localscale`` command line: option groups, value types, parsers.

Only :mod:`localscale.cli` imports this module; the library never does.
"""

from __future__ import annotations

import argparse
import math
import sys


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Keeps the description/epilog layout and appends ``(default: ...)`` to options whose help
    does not already state the default (flags, which default to off, are left alone)."""

    def _get_help_string(self, action):
        text = action.help or ""
        if "default" in text.lower() or action.default in (None, argparse.SUPPRESS) or action.nargs == 0:
            return text
        if action.option_strings or action.nargs in ("?", "*"):
            return text + " (default: %(default)s)"
        return text


def add_image_options(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """``--accept-damaged``, for the commands that read image files."""
    p.add_argument(
        "--accept-damaged",
        action="store_true",
        help="decode an image file whose data ends before the image its header declares (the rest is "
        "filler), with a warning, instead of refusing it",
    )
    return p


def add_model_options(
    p: argparse.ArgumentParser,
    local: bool = True,
    global_: bool = True,
    bf16: bool = True,
    model_alias: str | None = None,
) -> argparse.ArgumentParser:
    """Model options, spelled the same for every command: ``--local-weights``, ``--global-weights``,
    ``--device`` and ``--bf16``. ``model_alias`` (``"local"``/``"global"``) adds the deprecated,
    hidden ``--model`` for that checkpoint."""
    g = p.add_argument_group("model options")
    if local:
        g.add_argument(
            "--local-weights",
            metavar="CKPT",
            default=None,
            help="Local-ScaleNet checkpoint (default: the bundled weights)",
        )
    if global_:
        g.add_argument(
            "--global-weights",
            metavar="CKPT",
            default=None,
            help="global ScaleNet checkpoint (default: the bundled weights)",
        )
    if model_alias:
        g.add_argument("--model", dest=f"{model_alias}_weights", metavar="CKPT", help=argparse.SUPPRESS)
    g.add_argument("--device", default="cpu", help="torch device: cpu, cuda, cuda:N or mps")
    if bf16:
        g.add_argument(
            "--bf16",
            action="store_true",
            help="run the networks under bfloat16 autocast (fast on CPUs with AMX and on recent GPUs)",
        )
    return p


def add_refine_options(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """``--refine`` and ``--refine-passes`` (``match`` and ``predict``)."""
    g = p.add_argument_group("verification and refinement")
    g.add_argument(
        "--refine",
        action="store_true",
        help="verify the matches (MAGSAC homography), refine the scale maps by the verified geometry "
        "and match again with the refined maps; also writes refined maps and geometry.json",
    )
    g.add_argument(
        "--refine-passes",
        type=int,
        default=2,
        metavar="N",
        help="with --refine: matching passes at most (stops when the inlier count stops growing)",
    )
    g.add_argument(
        "--refine-seed",
        choices=("sift", "none"),
        default="sift",
        help="with --refine: when the first pass is not verified, verify OpenCV SIFT matches instead "
        "and refine the maps with their geometry (none: only the first pass's matches)",
    )
    return p


def add_refine_matcher_options(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """``--matcher`` and ``--matcher-weights`` of ``predict --refine`` (names checked when it runs,
    so that building the parser imports no model code)."""
    g = p.add_argument_group("refinement by a matcher")
    g.add_argument(
        "--matcher",
        default=None,
        metavar="NAME",
        help="with --refine: a matcher of 'localscale match --help'; a learned one (e.g. "
        "aliked-lightglue) takes the geometry from correction auto with that matcher (the images as "
        "they are, then the networks' hypotheses, verified), hardnet refines with the patch "
        "matcher's passes (default: aliked-lightglue when its weights are installed, else hardnet; "
        "hardnet with --search)",
    )
    g.add_argument(
        "--matcher-weights",
        metavar="DIR",
        default=None,
        help="folder of the learned matchers' weight files (default: the installed weight packages)",
    )
    return p


def _matcher_help() -> str:
    from ..matching.config import MATCHERS

    rows = []
    for n, c in MATCHERS.items():
        size = f"{c.extractor_conf['num_features']} features, " if "num_features" in c.extractor_conf else ""
        needs = c.extractor_class.needs(c.extractor_conf, c.matching == "lightglue")
        rows.append(f"{n} ({size}{c.max_side or 'full'} px; {needs})")
    return "; ".join(rows)


def add_matcher_options(p: argparse.ArgumentParser, several: bool = False) -> argparse.ArgumentParser:
    """``--matcher`` (one, or several with ``several``), ``--matcher-weights``, ``--num-features``,
    ``--max-side`` and the patch options of the hardnet matcher."""
    from ..features.pretrained import INSTALL_HINT
    from ..matching.config import MATCHERS

    g = p.add_argument_group("matcher")
    if several:
        g.add_argument(
            "--matcher",
            nargs="+",
            default=["hardnet"],
            choices=list(MATCHERS),
            metavar="NAME",
            help="matchers to compare: " + _matcher_help(),
        )
    else:
        g.add_argument(
            "--matcher", default="hardnet", choices=list(MATCHERS), metavar="NAME", help="matcher: " + _matcher_help()
        )
    g.add_argument(
        "--matcher-weights",
        metavar="DIR",
        default=None,
        help=f"folder of the learned matchers' weight files (default: the installed weight packages: {INSTALL_HINT})",
    )
    g.add_argument(
        "--num-features", type=positive_int, default=None, help="keypoints per image (default: the matcher's)"
    )
    g.add_argument(
        "--max-side",
        type=nonnegative_int,
        default=None,
        metavar="PX",
        help="working resolution, longer side (0: full resolution; default: the matcher's, hardnet 2048, "
        "learned matchers 1024, as LightGlue); keypoints are written in full-image pixels",
    )
    g.add_argument(
        "--pyramid",
        type=nonnegative_int,
        default=None,
        metavar="N",
        help="learned matchers with scale maps (correction local, ...): N half-octave levels, each "
        "keypoint from the level its local scale selects (default 0: one rectification)",
    )
    g.add_argument(
        "--descriptor",
        default=None,
        help="hardnet matcher: hardnet | hardnet-full | sift | path to HardNet weights (default: hardnet)",
    )
    g.add_argument(
        "--descriptor-precision",
        choices=("auto", "fp32", "bf16", "int8"),
        default=None,
        help="hardnet matcher: HardNet precision (default auto: int8 on CPU when the weights carry int8 "
        "ranges, else fp32)",
    )
    g.add_argument(
        "--detector",
        default=None,
        metavar="NAME",
        help="hardnet matcher: single-scale keypoint detector: hessian | harris | gftt | dog | sift | orb "
        "| akaze (default: hessian)",
    )
    g.add_argument(
        "--ratio",
        type=positive_float,
        default=None,
        help="hardnet matcher: Lowe ratio test threshold on top of mutual NN (default: mutual NN only)",
    )
    g.add_argument(
        "--orientation",
        choices=("upright", "gradient"),
        default=None,
        help="hardnet matcher: patch orientation, upright or the dominant gradient (default: upright)",
    )
    return p


def add_match_options(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Options of ``localscale match``."""
    from ..matching.correction import CORRECTION_METHODS

    p.add_argument("image_a", help="image A (path)")
    p.add_argument("image_b", help="image B (path)")
    p.add_argument("-o", "--output", default="out", help="output folder (matches.npz, matches.png)")
    p.add_argument(
        "--correction",
        choices=list(CORRECTION_METHODS),
        default="local",
        metavar="NAME",
        help="scale correction: " + "; ".join(f"{c.name}: {c.help}" for c in CORRECTION_METHODS.values()),
    )
    p.add_argument(
        "--H",
        default=None,
        help="ground-truth homography A->B, 3x3 text file (needed for --correction gt; colours inliers; default: none)",
    )
    p.add_argument(
        "--camera",
        default=None,
        help="camera of both images: a COLMAP cameras.txt line ('SIMPLE_RADIAL W H f cx cy k'), or a "
        "file holding one (or JSON); with cameras the pair's two-view geometry and relative pose "
        "go to geometry.json (default: none)",
    )
    p.add_argument("--camera-a", default=None, help="camera of image A (as --camera; default: none)")
    p.add_argument("--camera-b", default=None, help="camera of image B (as --camera; default: none)")
    p.add_argument(
        "--geometry",
        choices=["homography", "fundamental", "auto", "two_view"],
        default=None,
        help="verification model: homography (planes), fundamental, auto (either), two_view "
        "(chosen per pair as COLMAP does; the default with cameras, else homography)",
    )
    add_matcher_options(p)
    add_refine_options(p)
    add_model_options(p, local=True, global_=True, bf16=True)
    add_image_options(p)
    return p


def add_hpatches_options(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``localscale eval-hpatches``."""
    from ..evaluation.hpatches import HIGH_RES, METHODS
    from ..matching.correction import GATE_WEIGHTINGS

    p.add_argument("root", help="folder of sequences (HPatches layout)")
    p.add_argument(
        "-o",
        "--output",
        "--out",
        dest="out",
        default="hpatches_eval",
        help="output folder (results*.json, results*.md, splits.csv, mma_*.png)",
    )
    p.add_argument(
        "--methods",
        nargs="+",
        default=["none", "global", "local", "fused", "gt"],
        choices=METHODS,
        metavar="METHOD",
        help=f"correction methods to compare: {', '.join(METHODS)}",
    )
    add_matcher_options(p, several=True)
    g = p.add_argument_group("hardnet matcher, more")
    g.add_argument(
        "--base-radius", type=positive_float, default=None, help="patch radius (px) at scale 1 (default: 16)"
    )
    add_model_options(p, local=True, global_=True, bf16=False)
    g = p.add_argument_group("pairs")
    g.add_argument("--include-illumination", action="store_true", help="also evaluate i_* sequences")
    g.add_argument("--exclude-hires", action="store_true", help=f"skip {', '.join(HIGH_RES)}")
    g.add_argument("--exclude", nargs="*", default=[], help="sequence names to skip")
    g.add_argument("--sequences", nargs="*", default=None, help="only these sequences (default: all)")
    g.add_argument(
        "--pairs",
        nargs="*",
        type=positive_int,
        default=None,
        metavar="K",
        help="only the pairs 1-K of each sequence (default: 2 3 4 5 6)",
    )
    g = p.add_argument_group("gate of predicted maps")
    g.add_argument(
        "--gate-pair",
        type=float,
        default=None,
        help="pair-level gate: correct only if the 90th pct of |log2 S| reaches this (default: CorrectionGate's)",
    )
    g.add_argument(
        "--gate-deadzone",
        type=float,
        default=None,
        help="per pixel: |log2 S| below this -> 1 (default: CorrectionGate's)",
    )
    g.add_argument("--no-consistency", action="store_true", help="gate: skip the A<->B median consistency shift")
    g.add_argument(
        "--gate-min-confidence",
        type=float,
        default=None,
        help="per pixel: S -> 1 where the confidence is below this (default: CorrectionGate's)",
    )
    g.add_argument(
        "--gate-weighting",
        choices=GATE_WEIGHTINGS,
        default=None,
        help="gate: weight the maps' medians by the predicted visibility or reliability (default: CorrectionGate's)",
    )
    add_engine_options(p, "the pairs' evaluation")
    return p


def add_engine_options(p: argparse.ArgumentParser, what: str) -> argparse.ArgumentParser:
    """``--engine local|ray``, ``--workers``, ``--threads-per-worker``, ``--ray-address``: where ``what`` runs."""
    p.add_argument(
        "--engine",
        choices=["local", "ray"],
        default="local",
        help=f"where {what} runs: this process (local) or a Ray cluster (ray; pip install 'localscale[ray]')",
    )
    p.add_argument(
        "--workers", type=positive_int, default=None, help="Ray workers (default: one per threads-per-worker CPUs)"
    )
    p.add_argument(
        "--threads-per-worker", type=positive_int, default=None, help="torch threads of each Ray worker (default: 1)"
    )
    p.add_argument(
        "--ray-address",
        default=None,
        help="a running Ray cluster (e.g. auto, or HOST:PORT); default: a local one, started and stopped",
    )
    return p


def executor_from_args(args):
    """The Ray executor of ``--engine ray`` (options checked, nothing started), or None for this process."""
    from ..core.errors import LocalScaleError
    from ..engine import get_executor

    if args.engine == "local":
        if any(getattr(args, k) is not None for k in ("workers", "threads_per_worker", "ray_address")):
            raise LocalScaleError("--workers, --threads-per-worker and --ray-address need --engine ray")
        return None
    if args.device != "cpu":
        raise LocalScaleError("--engine ray runs the networks on the workers' CPUs: drop --device")
    return get_executor("ray", args.workers, args.threads_per_worker, args.ray_address)


def _int_at_least(text: str, low: int) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {text!r}") from None
    if v < low:
        raise argparse.ArgumentTypeError(f"must be >= {low}, got {v}")
    return v


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    return _int_at_least(text, 1)


def nonnegative_int(text: str) -> int:
    """argparse type: an integer >= 0."""
    return _int_at_least(text, 0)


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return v


class OneLineErrorParser(argparse.ArgumentParser):
    """An argument error is the usage line and one ``error: <prog>: ...`` line, exit code 2."""

    def error(self, message):
        self.print_usage(sys.stderr)
        self.exit(2, f"error: {self.prog}: {' '.join(message.split())}\n")


class _LazyArgumentParser(OneLineErrorParser):
    """A sub-command parser whose options are added on first use (parsing or help).

    ``match`` and ``eval-hpatches`` take their choices from modules that import torch and
    OpenCV; adding their options only when that command is used keeps ``localscale --help``
    and the other commands free of those imports."""

    def __init__(self, *args, add_options=None, **kwargs):
        super().__init__(*args, **kwargs)
        self._add_options = add_options

    def _populate(self) -> None:
        add, self._add_options = self._add_options, None
        if add is not None:
            add(self)

    def parse_known_args(self, args=None, namespace=None):
        self._populate()
        return super().parse_known_args(args, namespace)

    def format_help(self):
        self._populate()
        return super().format_help()

    def format_usage(self):
        self._populate()
        return super().format_usage()

    def set_defaults(self, **kwargs):
        if self.__dict__.get("_add_options") is None:
            return super().set_defaults(**kwargs)
        self.__dict__["_defaults"].update(kwargs)  # options added later take these defaults

    def __getattribute__(self, name):
        # code that inspects the options (``parser._actions``, ``get_default``) sees them all
        if name in ("_actions", "_option_string_actions", "_action_groups", "_defaults"):
            add = object.__getattribute__(self, "__dict__").get("_add_options")
            if add is not None:
                object.__getattribute__(self, "_populate")()
        return super().__getattribute__(name)
