"""``localscale match`` (two images, a matcher, a correction) and ``eval-hpatches``."""

from __future__ import annotations

import sys

from ..core.errors import LocalScaleError
from ..core.outputs import ensure_not_input
from ..loading import MODEL_KINDS
from .common import check_output_dir
from .options import executor_from_args

#: options of ``match`` that only a patch-based matcher (``--matcher hardnet``) reads
PATCH_OPTIONS = ("descriptor", "descriptor_precision", "detector", "orientation", "ratio")


def match_options(args) -> dict:
    """The :class:`~localscale.matching.MatchConfig` fields that ``match`` / ``eval-hpatches``
    options set (options left at None keep the matcher's own values)."""
    opts = {}
    for name in ("num_features", "max_side", "pyramid"):
        v = getattr(args, name, None)
        if v is not None:
            opts[name] = v or None if name == "max_side" else v
    if getattr(args, "matcher_weights", None) is not None:
        opts["weights"] = args.matcher_weights
    for name in PATCH_OPTIONS:
        v = getattr(args, name, None)
        if v is not None:
            opts[name] = v
    if getattr(args, "bf16", False):
        opts["bf16"] = True
    return opts


def cmd_match(args) -> int:
    from ..core.devices import resolve_device
    from ..matching import get_correction, get_matcher, match_config, run_match

    out = check_output_dir(args.output, ["matches.npz", "matches.png"])
    for f in ("matches.npz", "matches.png"):
        ensure_not_input(out / f, (args.image_a, args.image_b, args.H))
    resolve_device(args.device)
    correction = get_correction(args.correction)
    cfg = match_config(args.matcher, **_matcher_options(args))
    for kind in MODEL_KINDS:
        if getattr(args, f"{kind}_weights", None) is not None and kind not in correction.models:
            print(f"note: --{kind}-weights is not used by --correction {correction}", file=sys.stderr)
    camera_a, camera_b = _cameras(args)
    matcher = get_matcher(cfg)  # loads the matcher's weights: a missing file fails before the scale models load
    local_model, global_model = correction.load_models(args.local_weights, args.global_weights, args.device)
    run_match(
        args.image_a,
        args.image_b,
        out,
        correction,
        args.H,
        local_model,
        global_model,
        matcher,
        camera_a=camera_a,
        camera_b=camera_b,
    )
    return 0


def _cameras(args) -> tuple:
    """``(camera of A, camera of B)`` from ``--camera`` / ``--camera-a`` / ``--camera-b`` (None: not given)."""
    from ..geometry.cameras import as_camera

    if args.camera is not None and (args.camera_a is not None or args.camera_b is not None):
        raise LocalScaleError("--camera is the camera of both images: give it, or --camera-a / --camera-b, not both")
    a = args.camera if args.camera is not None else args.camera_a
    b = args.camera if args.camera is not None else args.camera_b
    return as_camera(a), as_camera(b)


def extractor_of(matcher: str) -> type:
    """The extractor class of a named matcher (what the options ask, not the matcher's name)."""
    from ..matching import MATCHERS

    return MATCHERS[matcher].extractor_class


def patch_matchers() -> str:
    """``only the hardnet matcher takes``: the named matchers whose extractor is patch-based."""
    from ..matching import MATCHERS

    names = [n for n, c in MATCHERS.items() if c.extractor_class.patch_based]
    return f"only the {' / '.join(names)} matcher{'s take' if len(names) > 1 else ' takes'}"


def _matcher_options(args) -> dict:
    """The MatchConfig fields of ``match``'s options, with the options that do not fit the matcher refused."""
    opts = match_options(args)
    extractor = extractor_of(args.matcher)
    if not extractor.patch_based:
        used = [f"--{n.replace('_', '-')}" for n in PATCH_OPTIONS if getattr(args, n, None) is not None]
        if used:
            raise LocalScaleError(f"{', '.join(used)}: {patch_matchers()} patch options, not --matcher {args.matcher}")
    if not extractor.weights and getattr(args, "matcher_weights", None) is not None:
        hint = " (--descriptor PATH for other descriptor weights)" if "descriptor" in extractor.default_conf else ""
        raise LocalScaleError(
            f"--matcher-weights: the {args.matcher} matcher loads no weight files (bundled weights or none){hint}"
        )
    opts.update(
        refine=getattr(args, "refine", False), max_passes=args.refine_passes, sift_seed=args.refine_seed == "sift"
    )
    if getattr(args, "geometry", None) is not None:
        import dataclasses

        from ..matching import MATCHERS

        opts["verification"] = dataclasses.replace(MATCHERS[args.matcher].verification, model=args.geometry)
    return opts


def cmd_eval_hpatches(args) -> int:
    from ..evaluation.hpatches import gate_from_args, load_hpatches, load_scale_models, make_pairs, result_tag, run
    from ..matching import get_matcher, match_config

    opts = match_options(args)
    opts.pop("max_side", None)  # one working resolution for every matcher, below
    if getattr(args, "base_radius", None) is not None:
        opts["base_radius"] = args.base_radius
    patch_opts = {k: opts.pop(k) for k in list(opts) if k in PATCH_OPTIONS + ("base_radius",)}
    weights = {"weights": opts.pop("weights")} if "weights" in opts else {}
    if patch_opts and not any(extractor_of(n).patch_based for n in args.matcher):
        raise LocalScaleError(
            f"--{', --'.join(k.replace('_', '-') for k in patch_opts)}: {patch_matchers()} patch options"
        )
    gate = gate_from_args(args)
    configs = [
        match_config(
            n,
            gate=gate,
            **opts,
            **(patch_opts if extractor_of(n).patch_based else {}),
            **(weights if extractor_of(n).weights else {}),
        )
        for n in dict.fromkeys(args.matcher)
    ]
    tags = [result_tag(c) for c in configs]
    check_output_dir(
        args.out,
        ["splits.csv", "results.md"]
        + [f"results_{t}.{e}" for t in tags for e in ("json", "md")]
        + [f"mma_{t}_rot30-90.png" for t in tags],
    )
    from ..core.devices import resolve_device

    resolve_device(args.device)
    matchers = [get_matcher(c) for c in configs]  # a missing weight file fails before any pair runs
    seqs = load_hpatches(args.root, args.include_illumination, args.exclude_hires, args.exclude, args.sequences)
    if args.pairs is not None:
        for s in seqs:
            s.homographies = {k: H for k, H in s.homographies.items() if k in args.pairs}
            s.bad = {k: v for k, v in s.bad.items() if k in args.pairs}
    skipped: list = []
    pairs = make_pairs(seqs, skipped)
    if not pairs:
        raise LocalScaleError(
            f"no pair of {args.root} can be evaluated ({len(skipped)} skipped; first: "
            f"{skipped[0]['pair']}: {skipped[0]['reason']})"
            if skipped
            else f"no pairs in {args.root}"
        )
    methods = list(dict.fromkeys(args.methods))
    models, notes = load_scale_models(methods, args.local_weights, args.global_weights, args.device)
    if not methods:
        raise LocalScaleError(f"none of the methods {list(args.methods)} can run: {'; '.join(notes)}")
    for n in notes:
        print("note:", n)
    print(f"{len(seqs)} sequences, {len(pairs)} pairs; matchers {[m.name for m in matchers]}; methods {methods}")
    executor = executor_from_args(args)
    try:
        run(
            pairs,
            methods,
            matchers,
            args.out,
            models,
            notes,
            skipped,
            args.max_side,
            extra={"gate": vars(gate), "args": {k: v for k, v in vars(args).items() if not callable(v)}},
            executor=executor,
        )
    finally:
        if executor is not None:
            executor.close()
    print(f"wrote {args.out}/")
    return 0
