"""The settings of ``correction="auto"`` (:class:`AutoConfig`) and the ``--auto NAME=VALUE`` options
that set them (:func:`auto_options`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional

from ...core.errors import LocalScaleError


def _is_int_at_least(value, low: int) -> bool:
    """Whether ``value`` is an integer (not a bool) of at least ``low``."""
    return isinstance(value, int) and not isinstance(value, bool) and value >= low


@dataclass
class AutoConfig:
    """The hypothesis loop of ``correction="auto"``.

    Attributes:
        budget: matcher runs per pair at most (the first is always the identity).
        accept_inliers, accept_ratio: a verified hypothesis with at least this many inliers and this
            inlier ratio ends the loop at once (a clear margin); weaker verified ones are kept while
            the budget lasts and the one with the most inliers wins.
        turns: also try B's other quarter turns (ranked by ScaleNet).
        same_log2: hypotheses whose scales differ by less than this (log2) and have the same turn
            are tried once.
        geometry_log2: a verified result whose own geometry differs from its hypothesis by more
            than this (log2 of the scale), or by a quarter turn, is matched again at the geometry's
            scale and turn.
        seed: a name of :data:`~localscale.matching.MATCHERS` (scale- and rotation-invariant and cheap:
            ``"sift"``) run once when the identity is not clear; its verified geometry is the first
            hypothesis of the matcher's. Its run is listed among the trials but is not one of the
            budget's and never the result. ``None``: no seed.
        seed_features: keypoints of the seed matcher (its ``num_features``; ``None``: its
            configuration's, 4096 for ``sift``): a close-up's few correct SIFT matches are more
            among more keypoints, and so is the seed's geometry's support.
        window_share: a verified geometry's hypothesis matches only the window of the image whose
            content is smaller that the other image shows, when it is at most this share of that
            image (0: never a window).
        accept_consistent: a verified result whose own geometry agrees with its hypothesis ends the
            loop even without a clear margin (a collection, where the pair graph decides the rest).
        zoom_model, zoom_min_log2: the verification model of the seed and of every hypothesis of
            a zoom of at least ``zoom_min_log2`` octaves, whatever the pair's (``None``: the pair's).
            A strong zoom shows a small, nearly planar part of the wide view, where a fundamental
            or essential matrix also fits wrong matches; the chosen result is verified again with
            the pair's model (two-view geometry and pose with cameras) when it is another.
        locate, locate_votes: when nothing verified within the budget, the zoom of at least
            ``zoom_min_log2`` octaves whose matches agree most (at least ``locate_votes``) on where
            the zoomed view lies (:func:`~.localization.locate_window`) is matched again in that
            window of the wide view (at most two more runs). The seed's matches also vote: for the
            similarity their keypoints' sizes and orientations agree on (SIFT), tried first when
            the seed's geometry does not verify (or gives a strong zoom no window); and at the
            networks' first scale, for a quarter turn and its window, tried first when clear.
        window_max_side: the longest side a window of the wide view is enlarged to (``None``: as
            the wide view, ``zoom_max_side``'s rule); the close-up is shrunk for the rest of the zoom.
        zoom_max_side: the longest side the wide view (or its window) of a zoom of
            ``zoom_min_log2`` octaves or more is enlarged to, when the matcher's ``max_side`` is
            smaller (``None``: the matcher's); the close-up is shrunk for the rest, so it keeps
            more of its detail.
        zoom_min_coverage: the inliers' coverage (``VerificationConfig.min_coverage``) that a zoom
            of ``zoom_min_log2`` octaves or more needs (``None``: the pair's): its inliers lie in
            the small, nearly planar part of the wide view that the close-up shows.
        similarity_margin: the window of the seed's similarity is the zoomed view's outline under
            it grown by this share of its size on each side.
    """

    budget: int = 4
    accept_inliers: int = 60
    accept_ratio: float = 0.3
    turns: bool = True
    same_log2: float = 0.25
    geometry_log2: float = 0.5
    seed: Optional[str] = "sift"
    seed_features: Optional[int] = None
    window_share: float = 0.5
    accept_consistent: bool = False
    zoom_model: Optional[str] = "homography"
    zoom_min_log2: float = 1.0
    locate: bool = True
    locate_votes: int = 6
    zoom_min_coverage: Optional[float] = 0.025
    window_max_side: Optional[int] = None
    zoom_max_side: Optional[int] = None
    similarity_margin: float = 0.25

    def check(self) -> "AutoConfig":
        if self.seed is not None and not isinstance(self.seed, str):
            raise LocalScaleError(f"auto seed must be None or a matcher's name, got {self.seed!r}")
        if not (0 <= self.window_share <= 1):
            raise LocalScaleError(f"auto window_share must be in [0, 1], got {self.window_share!r}")
        if not (self.same_log2 >= 0 and self.geometry_log2 >= 0):
            raise LocalScaleError(
                f"auto same_log2 and geometry_log2 must be >= 0, got {self.same_log2!r}, {self.geometry_log2!r}"
            )
        if not _is_int_at_least(self.budget, 1):
            raise LocalScaleError(f"auto budget must be an integer >= 1, got {self.budget!r}")
        if not (isinstance(self.accept_inliers, int) and self.accept_inliers >= 4):
            raise LocalScaleError(f"auto accept_inliers must be an integer >= 4, got {self.accept_inliers!r}")
        if not (0 <= self.accept_ratio <= 1):
            raise LocalScaleError(f"auto accept_ratio must be in [0, 1], got {self.accept_ratio!r}")
        if self.zoom_model is not None:
            from ..verification import VERIFICATION_MODELS

            if self.zoom_model not in VERIFICATION_MODELS:
                raise LocalScaleError(
                    f"auto zoom_model must be None or one of {', '.join(VERIFICATION_MODELS)}, got {self.zoom_model!r}"
                )
        if self.seed_features is not None and not _is_int_at_least(self.seed_features, 1):
            raise LocalScaleError(f"auto seed_features must be None or an integer >= 1, got {self.seed_features!r}")
        if not _is_int_at_least(self.locate_votes, 3):
            raise LocalScaleError(f"auto locate_votes must be an integer >= 3, got {self.locate_votes!r}")
        if self.zoom_min_coverage is not None and not (0 <= self.zoom_min_coverage <= 1):
            raise LocalScaleError(f"auto zoom_min_coverage must be None or in [0, 1], got {self.zoom_min_coverage!r}")
        for name in ("window_max_side", "zoom_max_side"):
            value = getattr(self, name)
            if value is not None and not _is_int_at_least(value, 1):
                raise LocalScaleError(f"auto {name} must be None or an integer >= 1, got {value!r}")
        if not (isinstance(self.similarity_margin, (int, float)) and 0 <= self.similarity_margin <= 1):
            raise LocalScaleError(f"auto similarity_margin must be in [0, 1], got {self.similarity_margin!r}")
        if not self.zoom_min_log2 >= 0:
            raise LocalScaleError(f"auto zoom_min_log2 must be >= 0, got {self.zoom_min_log2!r}")
        return self


def auto_options(items) -> dict:
    """``NAME=VALUE`` strings as :class:`AutoConfig` fields (a command line's ``--auto``): each value
    read as its field's type (``none``: None; a field whose default is None: an integer, a number or
    a string). An unknown name or a value of the wrong type is a :class:`LocalScaleError`."""
    defaults = AutoConfig()
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or name not in {f.name for f in dataclasses.fields(AutoConfig)}:
            raise LocalScaleError(f"--auto {item}: give NAME=VALUE with NAME an AutoConfig field")
        default, text = getattr(defaults, name), value.strip()
        if text.lower() == "none":
            out[name] = None
        elif isinstance(default, bool):
            if text.lower() not in ("true", "false", "1", "0"):
                raise LocalScaleError(f"--auto {item}: {name} takes true or false")
            out[name] = text.lower() in ("true", "1")
        elif default is None or isinstance(default, (int, float)):
            kinds = (int, float, str) if default is None else (type(default),)
            for kind in kinds:
                try:
                    out[name] = kind(text)
                    break
                except ValueError:
                    continue
            else:
                raise LocalScaleError(f"--auto {item}: {name} takes {'an integer' if kinds[0] is int else 'a number'}")
        else:
            out[name] = text
    AutoConfig(**out).check()
    return out
