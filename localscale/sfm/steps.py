"""Each step of :mod:`localscale.sfm` run alone, from files (hloc style): each step module holds a
function with paths (``extract.extract_folder``, ``pairs.pairs_of_features``, ``match.match_files``,
``geometry.verify_files``, ``database.database_of_files``, ``mapping.map_files``) and
``python -m localscale.sfm.<step>`` (its ``main``: that function behind the small parser here).

The steps share only files: ``features.h5`` -> ``pairs.txt`` -> ``matches.h5`` + ``keypoints.h5``
-> ``geometries.h5`` -> ``database.db`` -> ``sparse/``. Their options come from a
:class:`~.config.ReconstructConfig` (``--config``: a ``run.json`` of :func:`~.reconstruction.reconstruct`
or a JSON of :meth:`~.config.ReconstructConfig.asdict`) with the step's flags over it; bad input is
one ``error:`` line and exit code 2.

Example (what ``reconstruct`` runs, step by step)::

    python -m localscale.sfm.extract photos/ out/features.h5 --matcher sift
    python -m localscale.sfm.pairs out/features.h5 out/pairs.txt
    python -m localscale.sfm.match photos/ out/ --matcher sift
    python -m localscale.sfm.geometry photos/ out/
    python -m localscale.sfm.database photos/ out/
    python -m localscale.sfm.mapping photos/ out/
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Optional

from ..core.errors import LocalScaleError
from .config import ReconstructConfig

#: the flags a step may take: option name -> (flag, type, help)
FLAGS = {
    "matcher": ("--matcher", str, "features and matching rule (localscale.matching.MATCHERS)"),
    "max_side": ("--max-side", int, "working resolution (longer side, pixels)"),
    "num_keypoints": ("--num-keypoints", int, "keypoints per image at most"),
    "lightglue_precision": ("--lightglue-precision", str, "LightGlue's precision: auto, fp32, bf16 or int8"),
    "pairs": (
        "--pairs",
        str,
        "'auto' (every pair up to a number of images, retrieval beyond), 'exhaustive' or a pairs file",
    ),
    "pairs_nearest": ("--pairs-nearest", int, "each image with its N most similar (with --pairs auto)"),
    "correction": ("--correction", str, "none, auto, global, local, fused or searched"),
    "prune_mnn": ("--prune-mnn", int, "skip LightGlue on pairs with fewer mutual nearest neighbours (0: none)"),
    "merge_px": ("--merge-px", float, "keypoints closer than this (full-image pixels) are one"),
    "camera_mode": ("--camera-mode", str, "auto, single or per_image"),
    "camera_file": ("--camera", str, "a cameras.txt (line) or JSON with the camera of every image"),
    "mapper": ("--mapper", str, "incremental or global"),
    "mapping_trials": ("--mapping-trials", int, "runs of the mapper while it leaves images out"),
}


def parser(step: str, module_doc: str, options: tuple) -> argparse.ArgumentParser:
    """The parser of ``python -m localscale.sfm.<step>``: ``--config`` and the flags of ``options`` (names of :data:`FLAGS`)."""
    first = (module_doc or "").strip().split("\n\n")[0]
    p = argparse.ArgumentParser(
        prog=f"python -m localscale.sfm.{step}", description=first, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--config", default=None, metavar="JSON", help="run.json of reconstruct, or a ReconstructConfig")
    for name in options:
        flag, kind, text = FLAGS[name]
        p.add_argument(flag, dest=name, type=kind, default=None, help=f"{text} (default: the configuration's)")
    return p


def config_of(args: argparse.Namespace) -> ReconstructConfig:
    """The configuration of ``--config`` (default: the defaults) with the flags given over it, checked."""
    conf = ReconstructConfig()
    if args.config is not None:
        try:
            d = json.loads(Path(args.config).read_text())
        except (OSError, ValueError) as e:
            raise LocalScaleError(f"cannot read the configuration {args.config}: {e}") from None
        conf = ReconstructConfig.from_dict(d.get("config", d) if isinstance(d, dict) else {})
    given = {k: v for k, v in vars(args).items() if k in FLAGS and v is not None}
    conf = conf.replace(**given)
    conf.check()
    return conf


def run_step(fn, *args, **kwargs) -> int:
    """``fn(*args, **kwargs)``; a :class:`~localscale.core.errors.LocalScaleError` is one ``error:`` line, exit 2."""
    try:
        fn(*args, **kwargs)
    except LocalScaleError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


def step_images(images_dir, out_dir, conf: ReconstructConfig, names: Optional[set] = None) -> list:
    """The usable images of ``images_dir`` (``out_dir`` left out; with ``names``, those only)."""
    from .images import find_images

    images = find_images(images_dir, exclude=[out_dir], max_side=conf.features.max_side)
    return images if names is None else [im for im in images if im.name in names]


def cameras_of(images, conf: ReconstructConfig):
    from .cameras import image_cameras

    return image_cameras(images, conf.mapping.camera_mode, conf.mapping.camera_file)
