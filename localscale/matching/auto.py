"""Scale- and rotation-aware matching for any matcher: the networks propose, the geometry decides.

``correction="auto"`` (:func:`auto_match`):

1. **The images as they are** are matched and verified first
   (:func:`~.verification.verify_matches`, the matcher's :class:`~.verification.VerificationConfig`,
   with the inliers' coverage counted in either image). A clear verification (:class:`AutoConfig`)
   ends the loop there, and the networks never run.
2. **Hypotheses** ``(scale S_{A->B}, quarter turn of B)`` otherwise: first the geometry of a
   cheap scale- and rotation-invariant seed matcher (OpenCV SIFT) when it verifies; if it does not
   (or gives no window for a strong zoom), the similarity most of its matches agree on by their
   keypoints' own sizes and orientations (:func:`~.localization.locate_similarity`: scale, turn and
   window at once); then, in the
   order of the networks' evidence (:func:`propose`): ScaleNet's consistency-checked scale, with the quarter turn it chose
   when the upright images disagreed; the Local-ScaleNet maps (their level over the part of A that
   B shows; the patch matcher uses the maps themselves); then B's other quarter turns at ScaleNet's
   scale, ranked by how well ScaleNet's two directions agree on each.
3. **Verify, don't trust**: for each hypothesis in turn, B is turned, the image whose content is
   bigger is shrunk by the scale (the patch matcher corrects its patch sizes instead), the matcher
   runs, the keypoints are mapped back to the original pixels and the matches are verified.
   A verified result whose own geometry (:func:`geometry_hypothesis`) gives another scale or
   quarter turn than its hypothesis is matched again at the geometry's, before anything else.
4. **Located zooms**: if nothing verified, the strong zoom whose matches agree most on where the
   zoomed view lies in the wide one (:func:`~.localization.locate_window`) is matched again in
   that window of the wide view, enlarged rather than the zoomed view shrunk (then at its own
   geometry's scale and turn if that differs).
5. **The choice**: the verified result with the most inliers; if none verifies, the result with
   the most inliers, flagged unverified. At most ``budget`` matcher runs per pair, and two for a located zoom.

Quarter turns are counter-clockwise, as :func:`numpy.rot90`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Optional

import cv2
import numpy as np

from ..errors import LocalScaleError
from .hypotheses import Hypothesis, propose
from .localization import homography_window, locate_similarity, locate_turn, locate_window
from .turns import match_turned, nearest_turn
from .verification import VerificationConfig, VerificationResult, verify_matches

#: inliers the seed matcher's geometry needs to be proposed, and the matcher's run at a verified
#: geometry's scale and turn needs to confirm it
GEOMETRY_MIN_INLIERS = 10


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
        seed: a name of :data:`~.matchers.MATCHERS` (scale- and rotation-invariant and cheap:
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
            from .verification import VERIFICATION_MODELS

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


@dataclass
class Trial:
    """One hypothesis run: its verification's inlier count and ratio, whether it verified, seconds."""

    hypothesis: Hypothesis
    num_matches: int
    num_inliers: int
    inlier_ratio: float
    verified: bool
    seconds: float

    def to_dict(self) -> dict:
        h = self.hypothesis
        return {
            "source": h.source,
            "scale": round(float(h.scale), 5),
            "turn": int(h.turn),
            "window": None if h.window is None else [int(x) for x in h.window],
            "num_matches": int(self.num_matches),
            "num_inliers": int(self.num_inliers),
            "inlier_ratio": round(float(self.inlier_ratio), 4),
            "verified": bool(self.verified),
            "seconds": round(float(self.seconds), 3),
        }


@dataclass
class AutoResult:
    """What :func:`auto_match` returns: the chosen run's matches in original pixels, its
    verification, the chosen hypothesis, every trial in the order tried, the seconds of the whole
    loop, and Local-ScaleNet's ungated maps of A and B (``None`` when the networks did not run)."""

    matches: object
    verification: VerificationResult
    chosen: Hypothesis
    trials: list = field(default_factory=list)
    seconds: float = 0.0
    network_maps: Optional[tuple] = None

    def to_dict(self) -> dict:
        """JSON-ready: the chosen hypothesis, whether it verified, and every trial."""
        return {
            "chosen": self.chosen.describe(),
            "scale": round(float(self.chosen.scale), 5),
            "turn": int(self.chosen.turn),
            "verified": self.verified,
            "trials": [t.to_dict() for t in self.trials],
            "seconds": round(self.seconds, 3),
        }

    @property
    def verified(self) -> bool:
        return bool(self.verification.verified)


def _same(h: Hypothesis, tried: list, same_log2: float) -> bool:
    return any(
        t.turn == h.turn
        and abs(math.log2(h.scale) - math.log2(t.scale)) < same_log2
        and (h.maps is None) == (t.maps is None)
        and (h.window is None) == (t.window is None)
        for t in tried
    )


# ---------------------------------------------------------------- the geometry's own hypothesis


def geometry_hypothesis(v: VerificationResult, margin: float = 0.25, max_share: float = 0.5) -> Optional[Hypothesis]:
    """The ``(scale, quarter turn of B)`` that a verified result's own geometry implies: the
    median geometric scale at its inliers, and the quarter turn of B that brings the homography's
    rotation at the inliers' centre closest to none, and the window of the image whose content is
    smaller that the other image covers under it (its bounding box grown by ``margin`` on each
    side), when that is at most ``max_share`` of it; for a fundamental or essential matrix, a
    similarity fitted to the inliers stands in for the homography. ``None`` if it did not verify."""
    if not v.verified or v.num_inliers == 0:
        return None
    inl = np.asarray(v.inliers, bool)
    s = np.asarray(v.local_scales, np.float64)[inl]
    s = s[np.isfinite(s) & (s > 0)]
    if not len(s):
        return None
    scale = float(np.exp(np.median(np.log(s))))
    pa, pb = np.asarray(v.points_a, np.float64)[inl], np.asarray(v.points_b, np.float64)[inl]
    if v.H is not None:
        return mapping_hypothesis(v.H, scale, pa, v.shape_a, v.shape_b, "geometry", margin, max_share)
    # a fundamental or essential matrix: a similarity fitted to the inliers stands in for H
    M, _ = cv2.estimateAffinePartial2D(pa, pb, method=cv2.LMEDS) if len(pa) >= 3 else (None, None)
    if M is None or not np.isfinite(M).all():
        return Hypothesis(scale, 0, "geometry")
    S = np.vstack([M, [0.0, 0.0, 1.0]])
    return mapping_hypothesis(S, scale, pa, v.shape_a, v.shape_b, "geometry", margin, max_share)


def mapping_hypothesis(
    H: np.ndarray,
    scale: float,
    points_a: np.ndarray,
    shape_a: tuple,
    shape_b: tuple,
    source: str,
    margin: float = 0.25,
    max_share: float = 0.5,
) -> Hypothesis:
    """The hypothesis of a mapping ``H`` (``3 x 3``, A's pixels to B's) at ``scale``: the quarter
    turn of B that brings its rotation at the centre of ``points_a`` (``N x 2``) closest to none, and
    the window of the image whose content is smaller that the other covers (:func:`homography_window`)."""
    turn = nearest_turn(H, np.asarray(points_a, np.float64).reshape(-1, 2).mean(0), shape_b)
    return Hypothesis(scale, turn, source, window=homography_window(H, scale, shape_a, shape_b, margin, max_share))


# ---------------------------------------------------------------- the loop


def auto_match(
    matcher,
    image_a: np.ndarray,
    image_b: np.ndarray,
    local_model=None,
    global_model=None,
    config: Optional[AutoConfig] = None,
    keys: tuple = (None, None),
    seed_matcher=None,
    cameras: tuple = (None, None),
    verification: Optional[VerificationConfig] = None,
    hypotheses: Optional[list] = None,
    networks: bool = True,
) -> AutoResult:
    """Match ``image_a`` and ``image_b`` (``H x W x 3`` uint8) with ``matcher`` under the networks'
    hypotheses, each verified by geometry (module docstring).

    Args:
        matcher: a :class:`~localscale.matching.Matcher`.
        local_model, global_model: the networks that propose (either may be None).
        config: the loop's settings (default: the matcher config's ``auto``).
        keys: cache keys of the two images (the turn is added to B's).
        seed_matcher: the :class:`~localscale.matching.Matcher` that ``config.seed`` names
            (:func:`~localscale.matching.match_pair` builds it; None: no seed).
        cameras: the cameras of A and B in the pixels of these images, for the two-view
            geometry (``verification.model="two_view"``: essential matrix and relative pose).
        verification: how each run is verified (default: the matcher config's ``verification``).
        hypotheses: tried instead of the images as they are and the seed (the caller tried those),
            possibly none; the networks follow unless ``networks`` is False. If nothing verifies, the
            run with the most inliers is returned, flagged (the images as they are when nothing else ran).
    Returns:
        :class:`AutoResult`; its ``matches`` are a :class:`~localscale.matching.Matches`
        with keypoints in the pixels of the images given.
    """
    t_start = time.perf_counter()
    loop = _Loop(
        matcher,
        image_a,
        image_b,
        (config or matcher.config.auto).check(),
        keys,
        cameras,
        verification or matcher.config.verification,
    )
    network_maps = loop.run(local_model, global_model, seed_matcher, hypotheses, networks)
    loop.run_located()
    if not loop.runs:  # every hypothesis given was the images as they are
        loop.attempt(loop.identity)
    # nothing verified: the run with the most inliers (the first of equals), flagged
    found, v, h = loop.best if loop.best is not None else max(loop.runs, key=lambda r: r[1].num_inliers)
    if v.verified and loop.vconf_for(h).model != loop.vconf.model:
        v = loop.verify_again(found, v)
    return AutoResult(found, v, h, loop.trials, time.perf_counter() - t_start, network_maps)


class _Loop:
    """The hypothesis loop of :func:`auto_match` for one pair: what was tried, what each run found."""

    def __init__(
        self,
        matcher,
        image_a: np.ndarray,
        image_b: np.ndarray,
        config: AutoConfig,
        keys: tuple,
        cameras: tuple,
        verification: VerificationConfig,
    ):
        self.matcher, self.a, self.b, self.config, self.keys = matcher, image_a, image_b, config, keys
        self.cameras = cameras
        # a zoom hypothesis is judged by the inliers' coverage of either image: the zoomed view shows
        # a small part of the wide one, and all of itself
        self.vconf = dataclasses.replace(verification, coverage_of="either")
        # the model of the seed and of strong zooms (the other runs keep the pair's)
        self.zoom_vconf = dataclasses.replace(
            self.vconf,
            model=config.zoom_model or verification.model,
            min_coverage=self.vconf.min_coverage if config.zoom_min_coverage is None else config.zoom_min_coverage,
        )
        self.geometric_vconf = dataclasses.replace(
            self.vconf, min_inliers=min(self.vconf.min_inliers, GEOMETRY_MIN_INLIERS)
        )
        self.tried, self.trials, self.runs, self.queue = [], [], [], []
        self.located = []  # (votes, hypothesis in the window they agree on)
        self.seed_matches = []  # the seed's matched points, which vote with every zoom's
        self.seed_frames = []  # their keypoints' sizes and orientations (a seed such as SIFT)
        self.best = None
        self.identity = Hypothesis(1.0, 0, "identity")

    def verify_again(self, found, v):
        """The chosen run's matches verified with the pair's model (its geometry, and the pose
        with cameras); the hypothesis's verification if they do not verify so."""
        again = _verify(found, self.a, self.b, self.vconf, self.cameras)
        return again if again.verified else v

    def vconf_for(self, h: Hypothesis):
        """How a run of ``h`` is verified: the pair's model (a verified geometry's run with fewer
        inliers), the zoom model for a zoom of ``zoom_min_log2`` octaves or more."""
        # a run at a verified geometry's scale and turn confirms that geometry: fewer inliers will do
        vconf = self.geometric_vconf if h.source.endswith("geometry") else self.vconf
        if self.is_zoom(h):
            return dataclasses.replace(vconf, model=self.zoom_vconf.model, min_coverage=self.zoom_vconf.min_coverage)
        return vconf

    def is_zoom(self, h: Hypothesis) -> bool:
        """Whether ``h`` zooms by ``zoom_min_log2`` octaves or more."""
        return h is not self.identity and abs(math.log2(h.scale)) >= self.config.zoom_min_log2

    def clear(self, v) -> bool:
        c = self.config
        return bool(v.verified) and v.num_inliers >= c.accept_inliers and v.inlier_ratio >= c.accept_ratio

    def note_location(self, h: Hypothesis) -> None:
        """Keeps where the last run's matches and the seed's put the zoomed view in the wide one, for a zoom of
        ``zoom_min_log2`` octaves or more matched without a window (:meth:`run_located`)."""
        c = self.config
        if not (c.locate and h.window is None and self.is_zoom(h)):
            return
        found = self.runs[-1][0]
        m = found.matches
        pa, pb = zip((found.keypoints_a[m[:, 0]], found.keypoints_b[m[:, 1]]), *self.seed_matches)
        located = locate_window(
            np.concatenate(pa),
            np.concatenate(pb),
            h.scale,
            h.turn,
            self.a.shape[:2],
            self.b.shape[:2],
            min_votes=c.locate_votes,
            max_share=c.window_share,
        )
        if located is not None:
            window, votes = located
            self.located.append((votes, Hypothesis(h.scale, h.turn, h.source + ", located", window=window)))

    def seed_located(self, h: Hypothesis) -> Optional[Hypothesis]:
        """At the networks' first scale (a zoom of ``zoom_min_log2`` octaves or more): the quarter
        turn and window the seed's matches agree on (:func:`~.localization.locate_turn`), or ``None``."""
        c = self.config
        if not (c.locate and self.seed_matches and self.is_zoom(h)):
            return None
        pa, pb = (np.concatenate(p) for p in zip(*self.seed_matches))
        found = locate_turn(
            pa, pb, h.scale, self.a.shape[:2], self.b.shape[:2], min_votes=c.locate_votes, max_share=c.window_share
        )
        if found is None:
            return None
        turn, window, _ = found
        return Hypothesis(h.scale, turn, "seed located at " + h.source, window=window)

    def run_located(self) -> None:
        """When nothing verified: the zoom whose matches agreed most on where the zoomed view lies,
        matched again in that window of the wide view, and its own geometry's if that differs."""
        if self.best is not None or not self.located:
            return
        h = max(self.located, key=lambda vh: vh[0])[1]
        self.queue = []
        if not self.settled(self.attempt(h), h) and self.queue:
            self.attempt(self.queue.pop(0))

    def attempt(self, h: Hypothesis):
        self.tried.append(h)
        t0 = time.perf_counter()
        c = self.config
        max_side = None
        if self.is_zoom(h) and c.zoom_max_side is not None:
            own = self.matcher.config.max_side
            max_side = c.zoom_max_side if own is None else max(own, c.zoom_max_side)
        if h.window is not None and c.window_max_side is not None:
            max_side = c.window_max_side
        found, v = _run(self.matcher, self.a, self.b, h, self.keys, self.vconf_for(h), self.cameras, max_side)
        self.trials.append(
            Trial(h, len(found.matches), v.num_inliers, v.inlier_ratio, bool(v.verified), time.perf_counter() - t0)
        )
        self.runs.append((found, v, h))
        if v.verified and (self.best is None or v.num_inliers > self.best[1].num_inliers):
            self.best = (found, v, h)
        return v

    def settled(self, v, h) -> bool:
        """Whether the loop ends after ``h``: on a clear verification, unless the result's own
        geometry says it was matched at another scale or turn: that hypothesis is then queued
        first (also after a weak verification), and the loop ends after it if it verifies or
        anything was clear. The identity's clear verification is final."""
        if h.source.endswith("geometry"):  # the geometry confirmed by the matcher ends the loop
            return bool(v.verified) or any(self.clear(r[1]) for r in self.runs)
        if not v.verified:
            self.note_location(h)
        g = geometry_hypothesis(v, max_share=self.config.window_share)
        if (
            g is not None
            and not _same(g, self.tried, self.config.geometry_log2)
            and not (self.clear(v) and h is self.identity)
        ):
            self.queue.insert(0, g)
            return False
        return self.clear(v) or (self.config.accept_consistent and bool(v.verified))

    def run(self, local_model, global_model, seed_matcher, hypotheses=None, networks=True):
        """Try the images as they are, then the seed's geometry (or ``hypotheses`` instead of both),
        then the networks' hypotheses, until one settles or the budget is spent; returns
        Local-ScaleNet's maps when the networks ran."""
        c, m = self.config, self.matcher
        if hypotheses is not None:
            self.queue = list(hypotheses)
            self.tried.append(self.identity)  # the caller's: not run again
        # the images as they are first: a pair that verifies clearly needs no network at all
        elif self.settled(self.attempt(self.identity), self.identity):
            return None
        if hypotheses is None and seed_matcher is not None and seed_matcher.name != m.config.name:
            g = seed_hypothesis(
                seed_matcher,
                self.a,
                self.b,
                self.keys,
                self.zoom_vconf,
                self.trials,
                c.window_share,
                self.cameras,
                self.seed_matches,
                self.seed_frames,
            )
            first = seed_choices(g, 0, self.seed_matches, self.seed_frames, self.a.shape[:2], self.b.shape[:2], c)
            self.queue[:0] = [h for h, _ in first if not _same(h, self.tried, c.geometry_log2)]
        hyps = more = network_maps = None  # the networks run once the geometry's hypotheses are spent
        turns_added = False
        while sum(not t.hypothesis.source.startswith("seed") for t in self.trials) < c.budget:
            if not self.queue:
                if not networks:
                    break
                if hyps is None:
                    hyps, more, network_maps = propose(
                        self.a,
                        self.b,
                        local_model,
                        global_model,
                        m.config.gate,
                        not m.extractor.rectified,
                        m.config.bf16,
                    )
                    self.queue += [h for h in hyps if h.source != "identity"]
                    seeded = self.seed_located(hyps[0])
                    if seeded is not None:
                        self.queue.insert(0, seeded)
                    continue
                if turns_added or not c.turns:
                    break
                self.queue, turns_added = more(hyps[0].scale if hyps else 1.0), True
                continue
            h = self.queue.pop(0)
            if h.maps is None and abs(math.log2(h.scale)) < c.same_log2:
                h = Hypothesis(1.0, h.turn, h.source)  # within the dead zone: the images as they are
            if _same(h, self.tried, c.geometry_log2 if h.source.endswith("geometry") else c.same_log2):
                continue
            if self.settled(self.attempt(h), h):
                break
        return network_maps


def seed_hypothesis(
    seed_matcher,
    a: np.ndarray,
    b: np.ndarray,
    keys: tuple,
    vconf,
    trials: list,
    window_share: float,
    cameras: tuple = (None, None),
    matched: Optional[list] = None,
    frames: Optional[list] = None,
) -> Optional[Hypothesis]:
    """The seed matcher's run on the images as they are (listed in ``trials``), and the hypothesis
    its verified geometry gives (``None`` if it did not verify). ``matched``: a list the run's
    matched points ``(N x 2 in A, N x 2 in B)`` are appended to; ``frames``: one their keypoints'
    ``(size, angle)`` (``N x 2`` each) are appended to, when the seed's detector has them."""
    name = seed_matcher.name
    seed = Hypothesis(1.0, 0, f"seed ({name})")
    t0 = time.perf_counter()
    # a proposal only (the matcher's own run at it is verified again): fewer inliers will do
    vconf = dataclasses.replace(vconf, min_inliers=min(vconf.min_inliers, GEOMETRY_MIN_INLIERS))
    found, v = _run(seed_matcher, a, b, seed, tuple(None if k is None else (k, "seed") for k in keys), vconf, cameras)
    trials.append(
        Trial(seed, len(found.matches), v.num_inliers, v.inlier_ratio, bool(v.verified), time.perf_counter() - t0)
    )
    m = found.matches
    if matched is not None:
        matched.append((found.keypoints_a[m[:, 0]], found.keypoints_b[m[:, 1]]))
    if frames is not None and found.frames_a is not None and found.frames_b is not None:
        frames.append((found.frames_a[m[:, 0]], found.frames_b[m[:, 1]]))
    g = geometry_hypothesis(v, max_share=window_share)
    return None if g is None else dataclasses.replace(g, source=f"{name} geometry")


def seed_similarity(
    points_a, points_b, frames_a, frames_b, shape_a: tuple, shape_b: tuple, config: AutoConfig
) -> Optional[tuple[Hypothesis, int]]:
    """The scale, quarter turn and window (``config.similarity_margin``, ``config.window_share``)
    that the seed's matches (``N x 2`` points and ``(size, angle)`` frames in A and B) agree on by
    their keypoints' own sizes and orientations (:func:`~.localization.locate_similarity`, at least
    ``config.locate_votes``), and how many agree; ``None`` without such agreement."""
    found = locate_similarity(points_a, points_b, frames_a, frames_b, shape_a, shape_b, min_votes=config.locate_votes)
    if found is None:
        return None
    M, votes, inliers = found
    scale = float(np.sqrt(abs(np.linalg.det(M[:2, :2]))))
    h = mapping_hypothesis(
        M,
        scale,
        np.asarray(points_a)[inliers],
        shape_a,
        shape_b,
        "seed similarity",
        config.similarity_margin,
        config.window_share,
    )
    return h, votes


def seed_choices(
    g: Optional[Hypothesis],
    support: int,
    matched: list,
    frames: list,
    shape_a: tuple,
    shape_b: tuple,
    config: AutoConfig,
) -> list[tuple[Hypothesis, int]]:
    """The seed's hypotheses in the order they are tried, each with its support: ``g``, its verified
    geometry's (``support`` inliers), if any; before it, when it did not verify or gives a zoom of
    ``config.zoom_min_log2`` octaves or more no window, :func:`seed_similarity` of the seed's matched
    points and frames (as :func:`seed_hypothesis` lists them), if found and, after a verified
    geometry, if it has a window."""
    first = [] if g is None else [(g, support)]
    zoom_without_window = g is not None and g.window is None and abs(math.log2(g.scale)) >= config.zoom_min_log2
    if config.locate and matched and frames and (g is None or zoom_without_window):
        found = seed_similarity(*matched[0], *frames[0], shape_a, shape_b, config)
        if found is not None and (g is None or found[0].window is not None):
            first.insert(0, found)
    return first


def _run(matcher, a: np.ndarray, b: np.ndarray, h: Hypothesis, keys: tuple, vconf, cameras=(None, None), max_side=None):
    """One hypothesis: crop its window, turn B, match with the hypothesis's maps or scale (the
    image whose content is smaller enlarged up to ``max_side``, None: the matcher's), map the
    keypoints back to the given images' pixels, verify."""
    keys = list(keys)
    offsets = [np.zeros(2, np.float32), np.zeros(2, np.float32)]
    images = [a, b]
    if h.window is not None:
        i, x0, y0, x1, y1 = h.window
        images[i] = np.ascontiguousarray(images[i][y0:y1, x0:x1])
        offsets[i] = np.array([x0, y0], np.float32)
        keys[i] = None if keys[i] is None else (keys[i], "window", tuple(h.window))
    sa, sb = h.maps if h.maps is not None else (h.scale, 1.0 / h.scale)
    found = match_turned(
        matcher, images[0], images[1], sa, sb, h.turn, tuple(keys), maps_turned=True, max_side=max_side
    )
    found = dataclasses.replace(
        found, keypoints_a=found.keypoints_a + offsets[0], keypoints_b=found.keypoints_b + offsets[1]
    )
    return found, _verify(found, a, b, vconf, cameras)


def _verify(found, a: np.ndarray, b: np.ndarray, vconf, cameras: tuple):
    """The matches of ``found`` (keypoints in the pixels of ``a`` and ``b``) verified by ``vconf``."""
    m = found.matches
    return verify_matches(
        found.keypoints_a[m[:, 0]], found.keypoints_b[m[:, 1]], a.shape[:2], b.shape[:2], None, vconf, *cameras
    )
