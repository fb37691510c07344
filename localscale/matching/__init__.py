"""Matching two images with scale maps: matcher configurations, the matcher, verification,
refinement, correction methods, ``auto`` and the pipeline that runs them.

One module per concept: :mod:`.config` (:class:`MatchConfig`, :data:`MATCHERS`), :mod:`.matcher`
(:class:`Matcher`), :mod:`.nearest_neighbour`, :mod:`.lightglue`, :mod:`.rectification`,
:mod:`.correction`, :mod:`.verification` (with :mod:`localscale.geometry.two_view`), :mod:`.refinement`,
:mod:`.auto` (the hypothesis loop, its hypotheses, localisation, turns and the pair graph),
:mod:`.metrics`, :mod:`.result`, :mod:`.viz` and :mod:`.pipeline` (:func:`match_pair`).
The submodules (torch, kornia, OpenCV) are imported on first use of a name below.

Example::

    from localscale.matching import match_pair
    res = match_pair("a.jpg", "b.jpg", "auto", matcher="aliked-lightglue")
"""

from ..core.lazy import lazy_exports

_EXPORTS = {
    ".config": ("MATCHERS", "MatchConfig", "match_config"),
    ".matcher": ("Matcher", "Matches", "get_matcher"),
    ".nearest_neighbour": ("match_descriptors", "ratio_mutual_matches"),
    ".rectification": ("pair_scale", "rectify_factors"),
    ".metrics": ("reprojection_errors", "matching_accuracy", "corner_error", "homography_auc"),
    ".correction": (
        "CORRECTIONS",
        "CORRECTION_METHODS",
        "Correction",
        "CorrectionGate",
        "NO_GATE",
        "GATE_WEIGHTINGS",
        "get_correction",
        "models_for_correction",
        "scale_maps_for_pair",
        "fuse_local_global",
    ),
    "..two_view": ("TwoViewConfig", "TwoViewGeometry", "estimate_two_view_geometry", "relative_pose_error", "pose_auc"),
    ".verification": (
        "VerificationConfig",
        "VerificationResult",
        "verify_matches",
        "estimate_homography",
        "estimate_fundamental",
        "local_affine_scales",
    ),
    ".refinement": (
        "RefinedScale",
        "RefinedMatching",
        "refine_scale_map",
        "refine_pair_maps",
        "refine_passes",
        "describe_and_match",
        "sift_seed_points",
    ),
    ".auto.hypotheses": ("Hypothesis", "propose"),
    ".auto.localization": ("locate_window", "locate_turn", "locate_similarity", "homography_window"),
    ".auto.config": ("AutoConfig",),
    ".auto.trial": ("AutoResult",),
    ".auto.loop": ("try_hypotheses",),
    ".auto.turns": ("turn_matrix", "nearest_turn", "unturn_points", "match_turned"),
    ".result": ("MatchResult", "save_matches"),
    ".viz": ("draw_matches",),
    ".pipeline": (
        "match_pair",
        "match_refined_pair",
        "run_match",
        "match_auto",
        "match_refined",
        "match_result",
        "match_with_truth",
    ),
}
#: old names kept for one release (they go in the next): old name -> (module, new name)
_RENAMED = {
    "auto_match": (".auto.loop", "try_hypotheses"),
    "refine_match": (".pipeline", "match_refined_pair"),
    "refine_matching": (".refinement", "refine_passes"),
}


def _renamed(name):
    if name not in _RENAMED:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib
    import warnings

    module, new = _RENAMED[name]
    warnings.warn(
        f"localscale.matching.{name} is deprecated and goes in the next release: use {new}",
        DeprecationWarning,
        stacklevel=3,
    )
    return getattr(importlib.import_module(module, __name__), new)


__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, fallback=_renamed)
