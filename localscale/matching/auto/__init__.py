"""``correction="auto"``: scale- and rotation-aware matching for any matcher, the networks propose
and the geometry decides; for one pair and for a collection.

One module per part: :mod:`.config` (:class:`AutoConfig`, :func:`auto_options`), :mod:`.hypotheses`
(:class:`Hypothesis`, :func:`propose`, the hypothesis of a verified geometry), :mod:`.turns` (B
turned by quarter turns), :mod:`.localization` (where a zoomed view lies in the wide one),
:mod:`.trial` (one hypothesis run and verified; :class:`AutoResult`), :mod:`.seed` (the seed
matcher's hypotheses), :mod:`.loop` (:func:`try_hypotheses`: the loop for one pair),
:mod:`.graph` (:class:`PairGraph`, :class:`Relation`) and :mod:`.collection`
(:func:`match_with_graph`: the steps for a collection over the pair graph). The modules (OpenCV,
the matcher) are imported on first use of a name below.

Example::

    from localscale.matching import get_matcher
    from localscale.matching.auto import try_hypotheses
    out = try_hypotheses(get_matcher("aliked-lightglue"), image_a, image_b, local_model, global_model)
    out.verified, out.chosen.describe(), out.matches
"""

from ...core.lazy import lazy_exports

_EXPORTS = {
    ".config": ("AutoConfig", "auto_options"),
    ".hypotheses": ("Hypothesis", "propose", "geometry_hypothesis", "mapping_hypothesis"),
    ".turns": ("turn_matrix", "nearest_turn", "unturn_points", "match_turned"),
    ".localization": ("locate_window", "locate_turn", "locate_similarity", "homography_window"),
    ".trial": ("Trial", "AutoResult", "run_hypothesis", "verify_found"),
    ".seed": ("GEOMETRY_MIN_INLIERS", "seed_hypothesis", "seed_similarity", "seed_choices"),
    ".loop": ("try_hypotheses",),
    ".graph": ("PairGraph", "Relation", "relation_of"),
    ".collection": ("match_with_graph",),
}


def _deprecated(name):
    """``auto_match``: the old name of :func:`try_hypotheses`, kept for one release."""
    if name == "auto_match":
        import warnings

        from .loop import try_hypotheses

        warnings.warn(
            "localscale.matching.auto.auto_match is deprecated and goes in the next release: use try_hypotheses",
            DeprecationWarning,
            stacklevel=2,
        )
        return try_hypotheses
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, _deprecated)
