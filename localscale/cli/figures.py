"""``localscale show`` / ``demo`` (figures of a map), ``scale`` (global ScaleNet) and ``rectify``."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

from .. import loading
from ..core.errors import LocalScaleError
from ..core.outputs import ensure_not_input, make_dir, write_image, write_text
from .common import ASSETS, _model, check_output_dir, pair_name

SHOW_MAX_SIDE = 2048


def show_pair(
    image_a, image_b, output, H=None, model=None, title=None, bf16: bool = False, refine=False, colmap_model=None
) -> Path:
    """Predict and write the figure (A, B, scale factor map, confidence, and GT/error when ``H`` is
    given) to the file ``output``; returns its path. ``refine``: the map refined by the verified
    geometry of SIFT matches (:func:`refined_map`), with its source layer; ``colmap_model``: a COLMAP
    sparse model with both images, whose shared 3D points give the per-point truth."""
    import numpy as np

    from ..geometry import covisible_mask, homography_scale_map
    from ..io import load_working_image, read_homography
    from ..viz import plot_scale_prediction

    output = ensure_not_input(output, (image_a, image_b, H))
    points = None
    if colmap_model is not None:  # bad input is refused before any model runs
        from ..point_truth import shared_point_truth

        xy, truth = shared_point_truth(colmap_model, image_a, image_b)
    model = model or loading.load_scale_model("local")
    a, to_a = load_working_image(image_a, SHOW_MAX_SIDE, "image A")  # a figure needs no more pixels
    b, to_b = load_working_image(image_b, SHOW_MAX_SIDE, "image B")
    if colmap_model is not None:  # in the working image's pixels; a scale ratio does not change with the resize
        points = (xy @ to_a[:2, :2].T + to_a[:2, 2], truth)
    pred = model.predict(a, b, bf16=bf16)
    scale, sources = pred.scale, None
    if refine:
        scale, sources = refined_map(a, b, scale)
    gt = mask = None
    if H is not None:
        Hm = to_b @ read_homography(H) @ np.linalg.inv(to_a)
        gt = homography_scale_map(Hm, *a.shape[:2])
        mask = covisible_mask(Hm, a.shape[:2], b.shape[:2])
    make_dir(Path(output).parent)
    try:
        plot_scale_prediction(
            a,
            b,
            scale,
            pred.confidence,
            gt,
            mask,
            output,
            title,
            visible=getattr(pred, "visible", None),
            sources=sources,
            points=points,
        )
    except (OSError, ValueError) as e:
        raise LocalScaleError(f"cannot write figure {output}: {e}") from None
    return Path(output)


def refined_map(a, b, scale):
    """``(map, source layer)``: ``scale`` (A's network map) refined by the geometry of OpenCV SIFT
    matches verified as COLMAP's two-view geometry chooses (homography, or fundamental matrix with
    the dense map of its matches); the network map where nothing verifies."""
    from ..matching.refinement import refine_scale_map, sift_seed_points
    from ..matching.verification import VerificationConfig, verify_matches

    pa, pb = sift_seed_points(a, b, 2000)
    v = verify_matches(pa, pb, a.shape[:2], b.shape[:2], scale, VerificationConfig(model="two_view"))
    if not v.verified:
        print(
            f"warning: the matches did not verify ({'; '.join(v.reasons)}): the network map is shown", file=sys.stderr
        )
    ref = refine_scale_map(scale, v)
    return ref.scale, ref.source_layer


def cmd_show(args) -> int:
    name = f"{pair_name(args.image_a, args.image_b)}_figure.png"
    out = check_output_dir(args.output, [name])
    fig = ensure_not_input(out / name, (args.image_a, args.image_b, args.H))
    model = _model(args, "local")
    print(
        show_pair(
            args.image_a,
            args.image_b,
            fig,
            args.H,
            model,
            bf16=args.bf16,
            refine=args.refine,
            colmap_model=args.colmap_model,
        )
    )
    return 0


def cmd_demo(args) -> int:
    a, b, H = ASSETS / "kodim01_a.jpg", ASSETS / "kodim01_b.jpg", ASSETS / "H_a_b.txt"
    out = check_output_dir(args.output, ["demo.png"]) / "demo.png"
    show_pair(a, b, out, H, _model(args, "local"), title="localscale demo: Local-ScaleNet", bf16=args.bf16)
    print(out)
    return 0


# ---------------------------------------------------------------- scale, rectify


def cmd_scale(args) -> int:
    if args.search:
        from ..search import search_global_scale

        p, found = search_global_scale(
            _model(args, "local"), _model(args, "global"), args.image_a, args.image_b, bf16=args.bf16
        )
        print(f"search: {found.candidates} window pairs scored; ScaleNet on {found.kept()}", file=sys.stderr)
    else:
        p = _model(args, "global").predict(args.image_a, args.image_b, bf16=args.bf16)
    import numpy as np

    if not (
        all(math.isfinite(v) for v in (p.scale, p.scale_ab, p.scale_ba, p.hard_scale)) and np.isfinite(p.probs_ab).all()
    ):
        raise LocalScaleError("ScaleNet predicted a non-finite scale (NaN or inf): the model is broken")
    if not p.reliable:
        print(f"warning: the global scale is unreliable: {'; '.join(unreliable_because(p))}", file=sys.stderr)
    if any(p.turns):
        which = "A" if p.turns[0] else "B"
        print(
            f"warning: the upright images gave inconsistent scales; this one comes from {which} turned by "
            f"{90 * max(p.turns)} deg",
            file=sys.stderr,
        )
    if args.json:
        print(
            json.dumps(
                allow_nan=False,
                obj={
                    "scale": p.scale,
                    "scale_ab": p.scale_ab,
                    "scale_ba": p.scale_ba,
                    "hard_scale": p.hard_scale,
                    "reliable": p.reliable,
                    "limits": p.limits,
                    "turns": list(p.turns),
                    "inconsistency_log2": p.inconsistency_log2,
                    "probs_ab": p.probs_ab.round(4).tolist(),
                },
            )
        )
    else:
        print(
            f"S(A->B) = {p.scale:.4f}  (A->B {p.scale_ab:.4f}, 1/(B->A) {1 / p.scale_ba:.4f}, "
            f"D-ScaleNet {p.hard_scale:.4f})"
        )
    return 0


def unreliable_because(p) -> list:
    """Why a :class:`~localscale.models.scalenet.GlobalScalePrediction` is not reliable (empty: it is)."""
    disagree = f"A->B {p.scale_ab:.3f} and 1/(B->A) {1 / p.scale_ba:.3f} disagree by x{2**p.inconsistency_log2:.2f}"
    return ([] if p.consistent else [disagree]) + list(p.limits)


def rectify_pair(image_a, image_b, output, model=None, bf16: bool = False) -> dict:
    """Downscale the image whose content is bigger by the global scale so the pair has scale ~1.

    Writes ``<output>/<A>_<B>_rectified_<A|B>.png`` (``<A>``, ``<B>`` = ``<parent>-<stem>``, so pairs
    of different sequences do not collide) and ``<A>_<B>_rectified.json`` (scale, which image was
    resized, factor, sizes, paths, ``reliable`` and why not); returns that record.
    """
    import cv2

    from ..io import image_shape, load_image_reduced

    name = pair_name(image_a, image_b, always_parent=True)
    out = check_output_dir(output, [f"{name}_rectified_A.png", f"{name}_rectified.json"])
    inputs = (image_a, image_b)
    for which in "AB":
        ensure_not_input(out / f"{name}_rectified_{which}.png", inputs)
    model = model or loading.load_scale_model("global")
    pred = model.predict(image_a, image_b, bf16=bf16)
    s = float(pred.scale)
    if not (math.isfinite(s) and s > 0):
        raise LocalScaleError(f"ScaleNet predicted a non-finite scale ({s}): the model is broken; nothing written")
    which, factor = ("B", 1 / s) if s > 1 else ("A", s)
    src = image_b if which == "B" else image_a
    h, w = image_shape(src, f"image {which}")
    size = (max(1, round(w * factor)), max(1, round(h * factor)))
    img, (h, w) = load_image_reduced(src, f"image {which}", max(size))  # decoded no larger than needed
    resized = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    dst = ensure_not_input(out / f"{name}_rectified_{which}.png", inputs)
    sidecar = ensure_not_input(out / f"{name}_rectified.json", inputs)
    make_dir(out)
    write_image(dst, resized[..., ::-1])
    record = {
        "image_a": "array" if hasattr(image_a, "shape") else str(image_a),
        "image_b": "array" if hasattr(image_b, "shape") else str(image_b),
        "scale": s,
        "resized": which,
        "resized_image": "array" if hasattr(src, "shape") else str(src),
        "factor": factor,
        "size_before": [w, h],
        "size_after": list(size),
        "output": str(dst),
        "reliable": pred.reliable,
        "unreliable_because": unreliable_because(pred),
    }
    write_text(sidecar, json.dumps(record, indent=1) + "\n")
    record["sidecar"] = str(sidecar)
    return record


def cmd_rectify(args) -> int:
    name = pair_name(args.image_a, args.image_b, always_parent=True)
    check_output_dir(args.output, [f"{name}_rectified_A.png", f"{name}_rectified.json"])
    r = rectify_pair(args.image_a, args.image_b, args.output, _model(args, "global"), bf16=args.bf16)
    if not r["reliable"]:
        print(f"warning: the global scale is unreliable: {'; '.join(r['unreliable_because'])}", file=sys.stderr)
    print(
        f"S(A->B) = {r['scale']:.4f}: image {r['resized']} resized by {r['factor']:.4f} -> {r['output']} "
        f"(record: {r['sidecar']})"
    )
    return 0
