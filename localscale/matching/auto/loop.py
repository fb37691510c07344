"""Scale- and rotation-aware matching for any matcher: the networks propose, the geometry decides.

``correction="auto"`` (:func:`try_hypotheses`):

1. **The images as they are** are matched and verified first
   (:func:`~localscale.matching.verification.verify_matches`, the matcher's :class:`~localscale.matching.verification.VerificationConfig`,
   with the inliers' coverage counted in either image). A clear verification (:class:`~.config.AutoConfig`)
   ends the loop there, and the networks never run.
2. **Hypotheses** ``(scale S_{A->B}, quarter turn of B)`` otherwise: first the geometry of a
   cheap scale- and rotation-invariant seed matcher (OpenCV SIFT) when it verifies; if it does not
   (or gives no window for a strong zoom), the similarity most of its matches agree on by their
   keypoints' own sizes and orientations (:func:`~.localization.locate_similarity`: scale, turn and
   window at once); then, in the
   order of the networks' evidence (:func:`~.hypotheses.propose`): ScaleNet's consistency-checked scale, with the quarter turn it chose
   when the upright images disagreed; the Local-ScaleNet maps (their level over the part of A that
   B shows; the patch matcher uses the maps themselves); then B's other quarter turns at ScaleNet's
   scale, ranked by how well ScaleNet's two directions agree on each.
3. **Verify, don't trust**: for each hypothesis in turn, B is turned, the image whose content is
   bigger is shrunk by the scale (the patch matcher corrects its patch sizes instead), the matcher
   runs, the keypoints are mapped back to the original pixels and the matches are verified.
   A verified result whose own geometry (:func:`~.hypotheses.geometry_hypothesis`) gives another scale or
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
from typing import Optional

import numpy as np

from ..verification import VerificationConfig
from . import trial
from .config import AutoConfig
from .hypotheses import Hypothesis, already_tried, geometry_hypothesis, propose
from .localization import locate_turn, locate_window
from .seed import GEOMETRY_MIN_INLIERS, seed_choices, seed_hypothesis


def try_hypotheses(
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
) -> trial.AutoResult:
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
        :class:`~.trial.AutoResult`; its ``matches`` are a :class:`~localscale.matching.Matches`
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
    return trial.AutoResult(found, v, h, loop.trials, time.perf_counter() - t_start, network_maps)


class _Loop:
    """The hypothesis loop of :func:`try_hypotheses` for one pair: what was tried, what each run found."""

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
        again = trial.verify_found(found, self.a, self.b, self.vconf, self.cameras)
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
        found, v = trial.run_hypothesis(
            self.matcher, self.a, self.b, h, self.keys, self.vconf_for(h), self.cameras, max_side
        )
        self.trials.append(
            trial.Trial(
                h, len(found.matches), v.num_inliers, v.inlier_ratio, bool(v.verified), time.perf_counter() - t0
            )
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
            and not already_tried(g, self.tried, self.config.geometry_log2)
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
            self.queue[:0] = [h for h, _ in first if not already_tried(h, self.tried, c.geometry_log2)]
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
            if already_tried(h, self.tried, c.geometry_log2 if h.source.endswith("geometry") else c.same_log2):
                continue
            if self.settled(self.attempt(h), h):
                break
        return network_maps
