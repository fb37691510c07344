"""The summary of a reconstruction (``summary.json``): its numbers, its ``warning:`` lines and its table."""

from __future__ import annotations

from ..core.tables import markdown_table
from .report import no_model_reason, warn


def build_summary(images, pair_list, mstats, gstats, mapping, cameras, options, seconds, state) -> dict:
    best = (
        mapping.stats[0]
        if mapping.stats
        else {
            "registered": 0,
            "points": 0,
            "observations": 0,
            "mean_track_length": 0.0,
            "mean_reprojection_error": None,
            "registered_images": [],
            "bogus_cameras": [],
        }
    )
    names = [im.name for im in images]
    return {
        "images": len(images),
        "registered": best["registered"],
        "points": best["points"],
        "observations": best["observations"],
        "mean_track_length": best["mean_track_length"],
        "mean_reprojection_error": best["mean_reprojection_error"],
        "unregistered_images": sorted(set(names) - set(best["registered_images"])),
        "implausible_cameras": best.get("bogus_cameras", []),
        "images_in_other_models": sorted(
            {n for s in mapping.stats[1:] for n in s["registered_images"]} - set(best["registered_images"])
        ),
        "models": [
            {k: v for k, v in s.items() if k not in ("registered_images", "bogus_cameras")} for s in mapping.stats
        ],
        "mapper": options.get("mapper", "incremental"),
        "mapper_options": mapping.overrides,
        "view_graph_calibrated": mapping.calibrated,
        "mapping_runs": mapping.trials,
        "pairs": len(pair_list),
        "pairs_verified": gstats.verified,
        "geometry_estimator": gstats.estimator,
        "geometry": gstats.to_dict(),
        "matching": mstats.to_dict(),
        "camera_mode": cameras.mode,
        "camera_source": cameras.source,
        "options": options,
        "run": state,
        "seconds": {k: round(v, 2) for k, v in seconds.items()},
    }


def placement_summary(mapping, names: list, closeups: dict, reference, focal_priors: list) -> dict:
    """The summary's close-ups (``{close-up: {"photo", "zoom"}}``, :mod:`.registration_check`), the
    close-ups whose camera started from the zoom's focal length, what the registration check did
    (``suspect_images``: ``[{"image", "reason", "action"}]``, ``left_out_images``), ``placement``
    (:func:`.placement.placement` of the largest model against ``reference`` and the close-ups' photos;
    None when neither gives a reference) and ``implausible_cameras`` (COLMAP's test, less the close-ups
    whose focal length fits their zoom, :func:`.registration_check.plausible_closeups`)."""
    from .mapping import camera_centers
    from .placement import placement
    from .registration_check import plausible_closeups

    centres, zooms = {}, set()
    if mapping.models:
        centres = dict(zip(*camera_centers(mapping.models[0])))
        zooms = plausible_closeups(mapping.models[0], closeups)
    implausible = mapping.stats[0].get("bogus_cameras", []) if mapping.stats else []
    sources = {k: v[0] for k, v in closeups.items()}
    placed = placement(centres, names, reference, sources) if reference is not None or sources else None
    return {
        "closeups": {k: {"photo": v[0], "zoom": round(float(v[1]), 3)} for k, v in closeups.items()},
        "closeup_focal_priors": list(focal_priors),
        "suspect_images": list(mapping.checked),
        "left_out_images": sorted(r["image"] for r in mapping.checked if r["action"] == "left out"),
        "placement": placed if placed is None or placed["checked"] else None,
        "implausible_cameras": [n for n in implausible if n not in zooms],
    }


def _flag_checks(summary: dict) -> None:
    """The ``warning:`` lines of the registration check and of the placement."""
    for action, what in (
        ("left out", "left out of the model"),
        ("re-registered", "registered again with a fixed focal length"),
    ):
        hit = [r for r in summary.get("suspect_images", []) if r["action"] == action]
        if hit:
            shown = "; ".join(f"{r['image']}: {r['reason']}" for r in hit[:4])
            warn(
                f"{len(hit)} registered image(s) {what}, their pose was not to be trusted ({shown}{'; ...' if len(hit) > 4 else ''})"
            )
    p = summary.get("placement")
    if p and p["wrong"]:
        shown = ", ".join(p["wrong"][:6])
        ref = "the reference model" if p["reference"] == "model" else "their photos' centres (close-ups)"
        warn(
            f"{p['placed_right']} of {p['checked']} images placed right against {ref}; not: {shown}"
            f"{', ...' if len(p['wrong']) > 6 else ''}"
        )


def flag(summary: dict) -> None:
    """``warning:`` lines for a result that should not be trusted as it is."""
    n, r = summary["images"], summary["registered"]
    if r == 0:
        warn(f"no model: the mapper registered no images ({no_model_reason(summary)})")
    elif r < n:
        shown = ", ".join(summary["unregistered_images"][:6])
        warn(
            f"only {r} of {n} images registered in the largest model (not: {shown}"
            f"{', ...' if len(summary['unregistered_images']) > 6 else ''})"
        )
    if summary["images_in_other_models"]:
        shown = ", ".join(summary["images_in_other_models"][:6])
        warn(
            f"the images split into {len(summary['models'])} models: {len(summary['images_in_other_models'])} "
            f"image(s) are only in smaller models, not aligned with the largest ({shown})"
        )
    if summary.get("implausible_cameras"):
        shown = ", ".join(summary["implausible_cameras"][:6])
        warn(
            f"{len(summary['implausible_cameras'])} registered image(s) have implausible intrinsics (focal "
            f"length outside 0.1-10 x the image size or distortion > 1): their poses are not to be trusted ({shown})"
        )
    _flag_checks(summary)
    if summary.get("view_graph_calibrated") is False:
        warn("the view-graph calibration failed: the global mapper ran on guessed focal lengths")
    err = summary["mean_reprojection_error"]
    if err is not None and err > 2.0:
        warn(f"mean reprojection error {err:.2f} px is high: wrong matches or a wrong camera model")


SUMMARY_COLUMNS = [
    ("registered", "registered"),
    ("points", "points"),
    ("observations", "observations"),
    ("mean_track_length", "mean track"),
    ("mean_reprojection_error", "reproj. error (px)"),
    ("pairs_verified", "verified pairs"),
]


def summary_table(summary: dict) -> str:
    """The markdown table of one run: results and seconds per stage."""
    row = dict(summary)
    row["registered"] = f"{summary['registered']}/{summary['images']}"
    row["pairs_verified"] = f"{summary['pairs_verified']}/{summary['pairs']}"
    stages = [(k, f"{k} s") for k in summary["seconds"]]
    row.update(summary["seconds"])
    return markdown_table([row], SUMMARY_COLUMNS + stages)
