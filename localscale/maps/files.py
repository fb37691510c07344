"""Scale maps and refined maps as files: ``.npy`` (float32), float TIFF, colour PNG, ``geometry.json``.

write_scale_map(pred, "out/", "a_b")                 # out/a_b_scale.{npy,tif,png}, a_b_confidence.npy
write_refinement("out/", "a_b_", res.refined_a)      # out/a_b_refined_scale.npy, ..., a_b_geometry.json
"""

from __future__ import annotations

import json
from pathlib import Path

from ..core.errors import LocalScaleError
from ..core.outputs import ensure_not_input, make_dir, write_image, write_npy, write_npy_bands, write_text


def write_scale_map(pred, out_dir: Path, stem: str, inputs=()) -> list[Path]:
    """Write ``<stem>_scale.npy`` (float32), ``_scale.tif`` (float32 TIFF), ``_scale.png`` (colour),
    ``_confidence.npy`` and, for models that predict it, ``_visible.npy``. ``inputs`` are never
    overwritten."""
    import cv2
    import numpy as np

    from ..viz import colorize_log2_scale

    out_dir = make_dir(Path(out_dir))
    has_visible = pred.has("visible") if hasattr(pred, "has") else getattr(pred, "visible", None) is not None
    paths = scale_map_paths(out_dir, stem, has_visible)
    for p in paths:
        ensure_not_input(p, inputs)
    banded = hasattr(pred, "bands")  # read out band by band: only the scale map is ever whole
    finite = pred.finite() if banded else bool(np.isfinite(pred.scale).all() and np.isfinite(pred.confidence).all())
    if not finite:
        raise LocalScaleError(f"the predicted scale map of {stem} is not finite (NaN or inf); nothing written")
    scale = np.asarray(pred.scale, np.float32)
    write_npy(paths[0], scale)
    write_image(paths[1], scale)
    colour = colorize_log2_scale(scale)
    write_image(paths[2], cv2.cvtColor(colour, cv2.COLOR_RGB2BGR, dst=colour))  # in place: no second copy
    del colour
    for path, name in zip(paths[3:], ("confidence", "visible")):
        if banded:
            write_npy_bands(path, scale.shape, pred.bands(name))
        else:
            write_npy(path, np.asarray(getattr(pred, name), np.float32))
    return paths


def scale_map_paths(out_dir: Path, stem: str, visible: bool) -> list[Path]:
    """The files :func:`write_scale_map` writes for ``stem`` (``visible``: with ``_visible.npy``)."""
    out_dir = Path(out_dir)
    return [
        out_dir / f"{stem}_scale.npy",
        out_dir / f"{stem}_scale.tif",
        out_dir / f"{stem}_scale.png",
        out_dir / f"{stem}_confidence.npy",
    ] + ([out_dir / f"{stem}_visible.npy"] if visible else [])


def write_refinement(out: Path, stem: str, refined_a, refined_b=None, meta=None, inputs=()) -> list[Path]:
    """Write ``<stem>refined_scale.npy`` (float32 ``S_{A->B}``), ``<stem>refined_source.npy`` (uint8
    source layer: 0 network, 1 homography, 2 matches) and its picture ``refined_source.png``,
    ``<stem>refined_weight.npy`` (float32 geometry weight, 0 network .. 1 geometry),
    ``<stem>refined_scale.png``, with ``refined_b`` the same for B (``..._b``), and
    ``<stem>geometry.json`` (the verification: H or F, inliers, verified, reasons)."""
    import numpy as np

    from ..viz import colorize_log2_scale, colorize_sources

    out = make_dir(Path(out))
    items = [("", refined_a)] + ([("_b", refined_b)] if refined_b is not None else [])
    paths = []
    for suffix, r in items:
        names = [
            out / f"{stem}refined_scale{suffix}.npy",
            out / f"{stem}refined_source{suffix}.npy",
            out / f"{stem}refined_scale{suffix}.png",
            out / f"{stem}refined_source{suffix}.png",
            out / f"{stem}refined_weight{suffix}.npy",
        ]
        for q in names:
            ensure_not_input(q, inputs)
        write_npy(names[0], r.scale.astype(np.float32))
        write_npy(names[1], r.source_layer.astype(np.uint8))
        write_image(names[2], colorize_log2_scale(r.scale)[..., ::-1])
        write_image(names[3], colorize_sources(r.source_layer)[..., ::-1])
        write_npy(names[4], r.source.astype(np.float32))
        paths += names
    geo = out / f"{stem}geometry.json"
    ensure_not_input(geo, inputs)
    doc = refined_a.verification.to_dict() | {"inliers": np.flatnonzero(refined_a.inliers).tolist()} | (meta or {})
    write_text(geo, json.dumps(doc, indent=1) + "\n")
    return paths + [geo]
