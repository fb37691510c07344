"""``localscale predict``: the scale map of a pair (``--search``, ``--refine``); ``--pairs`` runs many."""

from __future__ import annotations

import sys

from ..core.errors import LocalScaleError
from ..maps.files import scale_map_paths, write_refinement, write_scale_map
from .common import _model, check_output_dir, pair_name
from .match import extractor_of
from .predict_pairs import _predict_pairs

#: what ``predict --refine`` writes beside the refined maps
_REFINE_META = ("passes", "inlier_counts", "seed_inliers")


def cmd_predict(args) -> int:
    out = check_output_dir(args.output)
    if args.pairs:
        _check_pairs_options(args)
        return _predict_pairs(args, out)
    _check_pair_options(args)
    inputs = (args.image_a, args.image_b)
    check_output_dir(out, [p.name for p in scale_map_paths(out, pair_name(*inputs), True)])
    from ..reliability import check_pair

    model = _model(args, "local")
    if args.search and (args.hard or args.planar):
        raise LocalScaleError("predict: --search uses the soft read-out; drop --hard/--planar")
    check = check_pair(model, args.image_a, args.image_b, bf16=args.bf16, hard=args.hard, planar=args.planar)
    pred = _searched_prediction(model, args) if args.search else _anchored(model, args, check)
    _write_prediction(args, pred, check, out, inputs)
    if getattr(args, "refine", False) and not extractor_of(args.matcher).patch_based:
        _refine_with_matcher(args, model, out, inputs)
    elif getattr(args, "refine", False):
        _refine_hardnet(args, model, pred, check.backward, out, inputs)
    return 0


def _check_pairs_options(args) -> None:
    """The options ``--pairs FILE`` cannot be combined with."""
    if args.image_a or args.image_b:
        raise LocalScaleError("predict: give two images A B or --pairs FILE, not both")
    if getattr(args, "refine", False):
        raise LocalScaleError("predict: --refine works on one pair A B, not with --pairs")
    if args.search:
        raise LocalScaleError("predict: --search works on one pair A B, not with --pairs")


def _check_pair_options(args) -> None:
    """The options of one pair A B: ``--refine-passes``, ``--matcher`` (needs ``--refine``, not ``--search``), A and B."""
    if getattr(args, "refine", False) and args.refine_passes < 1:
        raise LocalScaleError(f"--refine-passes must be >= 1, got {args.refine_passes}")
    from ..matching.config import MATCHERS

    if args.matcher is None:
        from ..matching.pipeline import default_refine_matcher

        use_default = getattr(args, "refine", False) and not args.search
        args.matcher = default_refine_matcher(args.matcher_weights) if use_default else "hardnet"
    if args.matcher not in MATCHERS:
        raise LocalScaleError(f"predict: --matcher {args.matcher!r}: not a matcher ({', '.join(MATCHERS)})")
    if not extractor_of(args.matcher).patch_based:
        if not getattr(args, "refine", False):
            raise LocalScaleError(f"predict: --matcher {args.matcher} is the matcher of --refine; add --refine")
        if args.search:
            raise LocalScaleError(f"predict: --search refines with a patch matcher, not {args.matcher}; drop --matcher")
    if not (args.image_a and args.image_b):
        raise LocalScaleError("predict: give two images A B, or --pairs FILE")


def _anchored(model, args, check):
    """The map of A anchored on ScaleNet (the default), with its line on stderr; the one-pass map
    of the check with ``--no-anchor``."""
    if args.no_anchor:
        return check.forward
    pred = model.predict(args.image_a, args.image_b, hard=args.hard, bf16=args.bf16, planar=args.planar)
    a = pred.meta["anchor"]
    win = a["window"]
    where = f", local pass on {win['image']} window {tuple(win['box'])}" if win else ""
    print(f"anchor: ScaleNet S(A->B) {a['scale']:.3f}, B turned {90 * a['turns']} deg{where}", file=sys.stderr)
    return pred


def _searched_prediction(model, args):
    """The map of A from ``--search`` (window pairs), with its line on stderr."""
    from ..search import search_scale_map

    found = search_scale_map(model, args.image_a, args.image_b, bf16=args.bf16)
    print(
        f"search: {found.candidates} window pairs scored; kept {found.kept()} "
        f"(score {found.score:.1f}, whole images {found.base_score:.1f})",
        file=sys.stderr,
    )
    return found.prediction


def _write_prediction(args, pred, check, out, inputs) -> None:
    """Write the scale map, print its files, its summary and the warning of an unreliable map."""
    for p in write_scale_map(pred, out, pair_name(*inputs), inputs):
        print(p)
    import numpy as np

    s = pred.sampled("scale")
    print(f"S(A->B): median {np.median(s):.3f}, min {s.min():.3f}, max {s.max():.3f}", file=sys.stderr)
    if not check.reliable:
        scope = " (checked on the whole images)" if args.search else ""
        print(f"warning: this scale map is unreliable{scope}: {'; '.join(check.reasons)}", file=sys.stderr)


def _refine_with_matcher(args, model, out, inputs) -> None:
    """``--refine --matcher M``: :func:`~localscale.matching.pipeline.refine_by_auto`."""
    from ..matching.pipeline import refine_by_auto

    options = {"weights": args.matcher_weights} if args.matcher_weights else {}
    res = refine_by_auto(args.image_a, args.image_b, args.matcher, model, None, **options)
    v = res.verification
    extra = {k: res.meta[k] for k in _REFINE_META} | {"auto": res.meta["auto"]}
    for p in write_refinement(out, pair_name(*inputs) + "_", res.refined_a, None, extra, inputs):
        print(p)
    state = "verified" if v.verified else f"not verified ({'; '.join(v.reasons)}), network map kept"
    print(
        f"refine: {args.matcher} auto chose {res.meta['auto']['chosen']}; {v.model} with {v.num_inliers} "
        f"inliers, {state}",
        file=sys.stderr,
    )


def _refine_hardnet(args, model, pred, back, out, inputs) -> None:
    """``--refine``: the gated maps of A and B matched, verified and refined (:func:`~localscale.matching.pipeline.refine_predictions`)."""
    from ..matching.pipeline import refine_predictions
    from ..matching.verification import VerificationConfig

    if args.search:  # B's map from its own search, as the searched correction of match does
        from ..search import search_scale_map

        back = search_scale_map(model, args.image_b, args.image_a, bf16=args.bf16).prediction
    res = refine_predictions(
        args.image_a,
        args.image_b,
        pred,
        back,
        matcher=args.matcher,
        max_passes=args.refine_passes,
        sift_seed=args.refine_seed == "sift",
        verification=VerificationConfig(model="two_view"),  # H for planes, F (map of the matches) for 3D scenes
    )
    v = res.verification
    extra = {k: res.meta[k] for k in _REFINE_META}
    for p in write_refinement(out, pair_name(*inputs) + "_", res.refined_a, None, extra, inputs):
        print(p)
    state = "verified" if v.verified else f"not verified ({'; '.join(v.reasons)}), network map kept"
    print(f"refine: {v.model} with {v.num_inliers}/{len(v.inliers)} inliers, {state}", file=sys.stderr)
