"""Matching one pair of a collection with the correction (the worker side of the matching step,
:mod:`.match`): the whole correction per pair, or the steps of ``auto`` that the pair graph
(:mod:`localscale.matching.auto.graph`) drives: the pair as it is, the seed's geometry, given hypotheses (through the
hypothesis loop, or at the images' levels)."""

from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from ..matching.auto.graph import Relation, relation_of
from .extract import FeatureConf, build_matcher, features_for_matcher, load_working, to_full


@dataclass
class PairResult:
    """What matching one pair gives the driver: the keypoints of A and B (full-image pixels), K x 2
    matches, K scores, whether it verified (None: not checked), the hypothesis chosen, the pair's
    :class:`~localscale.matching.auto.graph.Relation` when it verified, the seed step's hypothesis (with its window),
    whether the pair needs no other hypothesis, seconds and feature sets computed for it, and the
    seed's matches that agree with its hypothesis (what ranks the anchors)."""

    kp_a: np.ndarray
    kp_b: np.ndarray
    matches: np.ndarray
    scores: np.ndarray = None
    verified: Optional[bool] = None
    chosen: str = ""
    relation: Optional[Relation] = None
    hypothesis: Any = None
    final: bool = False  #: ``as_they_are``: verified clearly, or with no scale change or turn to try
    seconds: float = 0.0
    computed: int = 0
    support: int = 0
    geometry: Any = None


def costs_to_scores(costs: np.ndarray, lightglue: bool) -> np.ndarray:
    c = np.asarray(costs, np.float32)
    return (1.0 - c) if lightglue else (1.0 - 0.5 * c**2)


@dataclass(frozen=True)
class PairRunnerFactory:
    """Worker state of the matching step on an executor: a pair runner with its own level cache and networks."""

    images: tuple
    features_path: str
    conf: FeatureConf
    correction: Any  #: a :class:`~localscale.matching.Correction` or its name
    device: str = "cpu"
    local_model: Any = None  #: the networks to ship to the workers (None: each loads the bundled weights)
    global_model: Any = None
    cameras: Any = (
        None  #: the images' cameras (:func:`~.cameras.image_cameras`): the pairs as they are get their geometry
    )
    prune_mnn: int = 0  #: :mod:`.prune`'s threshold of the pairs matched as they are (0: none)

    def __call__(self):
        by_name = {im.name: im for im in self.images}
        runner = PairRunner(
            by_name,
            self.features_path,
            self.conf,
            self.correction,
            self.device,
            None,
            self.local_model,
            self.global_model,
            len(by_name),
            self.cameras,
        )
        runner.prune_mnn = self.prune_mnn
        return runner


@dataclass(frozen=True)
class MatchPair:
    """Work of one item: ``(name_a, name_b)`` (the whole correction) or ``(name_a, name_b, step,
    *arguments)`` with ``step`` a :class:`PairRunner` method (``as_they_are``, ``seed``,
    ``hypotheses``, ``levels``); returns the :class:`PairResult` with its seconds and feature sets computed."""

    def __call__(self, runner, item):
        t0, before = time.perf_counter(), runner.feature_sets
        a, b, *step = item
        out = getattr(runner, step[0])(a, b, *step[1:]) if step else runner.run(a, b)
        out.seconds, out.computed = time.perf_counter() - t0, runner.feature_sets - before
        return out


class PairRunner:
    """Matches one pair with the correction: ``run(a, b)`` (the whole correction) or, for the steps
    of ``auto`` on a collection, ``as_they_are(a, b)``, ``seed(a, b)``, ``hypotheses(a, b, ...)`` and
    ``levels(a, b, ...)``; each returns a :class:`PairResult`."""

    def __init__(
        self, by_name, features_path, conf, correction, device, matcher, local_model, global_model, num_images,
        cameras=None,
    ):  # fmt: skip
        from ..matching import get_correction

        self.by_name, self.features_path, self.conf, self.cameras = by_name, features_path, conf, cameras
        self.correction = get_correction(correction)
        self.matcher = matcher or build_matcher(conf, device, num_images)
        self.lightglue = self.matcher.config.matching == "lightglue"
        self.local_model, self.global_model = local_model, global_model
        if (local_model is None and "local" in self.correction.models) or (
            global_model is None and "global" in self.correction.models
        ):
            loaded = self.correction.load_models(device=device)  # the bundled weights of what is missing
            self.local_model = local_model if local_model is not None else loaded[0]
            self.global_model = global_model if global_model is not None else loaded[1]
        self.seed_matcher = None
        self.prune_mnn = 0
        seed_name = self.matcher.config.auto.seed
        if self.correction.auto and seed_name is not None and seed_name != self.matcher.config.name:
            from ..matching import match_config
            from .extract import LevelMatcher

            features = self.matcher.config.auto.seed_features
            options = {} if features is None else {"num_features": features}
            self.seed_matcher = LevelMatcher(
                match_config(seed_name, max_side=None, **options), device, cache_size=max(8, 2 * num_images)
            )
        self._features: OrderedDict = OrderedDict()
        self._images: OrderedDict = OrderedDict()
        self._seeded: set = set()

    @property
    def feature_sets(self) -> int:
        """Feature sets the level caches computed in this run (matcher and seed)."""
        count = getattr(self.matcher, "level_count", 0)
        return count + (self.seed_matcher.level_count if self.seed_matcher is not None else 0)

    def _stored(self, name):
        if name not in self._features:
            self._features[name] = features_for_matcher(self.features_path, name)
            while len(self._features) > 4 * max(8, len(self.by_name)):
                self._features.popitem(last=False)
        return self._features[name]

    def _image(self, name):
        if name not in self._images:
            self._images[name] = load_working(self.by_name[name], self.conf.max_side)
            while len(self._images) > 16:
                self._images.popitem(last=False)
        self._images.move_to_end(name)
        return self._images[name]

    def _match_stored(self, fa, fb):
        """The stored features matched, or no match when :func:`~.prune.skip_pair` skips the pair."""
        from .prune import skip_pair

        if self.lightglue and skip_pair(fa.descriptors, fb.descriptors, self.prune_mnn):
            return np.zeros((0, 2), np.int64), np.zeros(0, np.float32)
        return self.matcher.match_features(fa, fb)

    def _prepared(self, a: str, b: str):
        """``(stored features and maps of A, of B, working image and map of A, of B)``; the stored
        features are level 1 of the shared cache."""
        m = self.matcher
        (fa, Sa), (fb, Sb) = self._stored(a), self._stored(b)
        (ia, _), (ib, _) = self._image(a), self._image(b)
        if m.extractor.rectified:
            for name, f in ((a, fa), (b, fb)):
                if name not in self._seeded:
                    m.seed(name, f)  # level 1 of every pair is features.h5's
                    self._seeded.add(name)
        return fa, fb, ia, ib, Sa, Sb

    def run(self, a: str, b: str) -> "PairResult":
        """The pair matched with the whole correction (``auto``: the per-pair hypothesis loop)."""
        m = self.matcher
        if self.correction.as_is:
            (fa, Sa), (fb, Sb) = self._stored(a), self._stored(b)
            matches, costs = self._match_stored(fa, fb)
            return PairResult(
                to_full(fa.keypoints, Sa), to_full(fb.keypoints, Sb), matches, costs_to_scores(costs, self.lightglue)
            )
        if self.correction.auto:
            return self.hypotheses(a, b, None, True, per_pair=True)
        fa, fb, ia, ib, Sa, Sb = self._prepared(a, b)
        cfg = m.config
        sa, sb = self.correction.maps(ia, ib, None, self.local_model, self.global_model, cfg.gate, bf16=cfg.bf16)
        if m.extractor.rectified:
            from ..matching import pair_scale

            level = pair_scale(sa, sb)
            kp_a, kp_b, matches, scores = self._anchored(a, b, ia, ib, fa, fb, level, 0)
            chosen = f"level {level:.3g}"
        else:  # patches: the keypoints stay, each patch's size follows the maps
            found = m.match(ia, ib, sa, sb, (a, b))
            kp_a, kp_b, matches = found.keypoints_a, found.keypoints_b, found.matches
            scores, chosen = costs_to_scores(found.distances, self.lightglue), "maps"
        return PairResult(to_full(kp_a, Sa), to_full(kp_b, Sb), matches, scores, None, chosen)

    def as_they_are(self, a: str, b: str) -> "PairResult":
        """The stored features matched and verified with the two-view geometry (homography for
        planes, fundamental or essential matrix otherwise); a verified pair gets its relation. With
        the images' cameras, the geometry is the geometry step's own (:func:`~.geometry.pair_geometry`),
        kept with the result so that it is estimated once."""
        import dataclasses

        from ..matching import verify_matches

        m = self.matcher
        (fa, Sa), (fb, Sb) = self._stored(a), self._stored(b)
        matches, costs = self._match_stored(fa, fb)
        matches = np.asarray(matches, np.int64).reshape(-1, 2)
        kp_a, kp_b = to_full(fa.keypoints, Sa), to_full(fb.keypoints, Sb)
        vconf = dataclasses.replace(m.config.verification, model="two_view", coverage_of="either")
        geometry = two_view = None
        if self.cameras is not None:  # estimated in full-image pixels, decided in working pixels
            from .geometry import pair_geometry, two_view_of

            geometry = pair_geometry(kp_a, kp_b, matches, self.cameras.camera(a), self.cameras.camera(b))
            two_view = two_view_of(geometry, matches, Sa, Sb)
        pa, pb = fa.keypoints[matches[:, 0]], fb.keypoints[matches[:, 1]]
        v = verify_matches(pa, pb, fa.image_shape, fb.image_shape, None, vconf, geometry=two_view)
        scores = costs_to_scores(costs, self.lightglue)
        rel, c = relation_of(v, None), m.config.auto
        clear = v.num_inliers >= c.accept_inliers and v.inlier_ratio >= c.accept_ratio
        final = rel is not None and (clear or rel.is_identity(c.geometry_log2))
        out = PairResult(kp_a, kp_b, matches, scores, bool(v.verified), "as they are", rel, final=final)
        out.geometry = geometry
        return out

    def seed(self, a: str, b: str) -> "PairResult":
        """The seed matcher's (SIFT) run on the images as they are: no matches kept, only the
        relation and the hypothesis (with its window) of its verified geometry; when it does not
        verify, or gives a strong zoom no window, the hypothesis of the similarity its matches'
        keypoints agree on (:func:`~localscale.matching.auto.seed.seed_similarity`), if any."""
        import dataclasses

        from ..matching.auto.seed import seed_choices, seed_hypothesis

        empty = PairResult(np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32), np.zeros((0, 2), np.int64))
        if self.seed_matcher is None:
            return empty
        (ia, _), (ib, _) = self._image(a), self._image(b)
        cfg = self.matcher.config
        vconf = dataclasses.replace(cfg.verification, coverage_of="either")
        trials, matched, frames = [], [], []
        g = seed_hypothesis(
            self.seed_matcher, ia, ib, (a, b), vconf, trials, cfg.auto.window_share, matched=matched, frames=frames
        )
        if g is not None:
            empty.relation = Relation(g.scale, g.turn % 4, trials[-1].num_inliers)
        choices = seed_choices(g, trials[-1].num_inliers, matched, frames, ia.shape[:2], ib.shape[:2], cfg.auto)
        if choices:
            empty.hypothesis, empty.support = choices[0]
        return empty

    def hypotheses(self, a: str, b: str, hypotheses, networks: bool, per_pair: bool = False) -> "PairResult":
        """:func:`~localscale.matching.auto.try_hypotheses` on the pair: ``per_pair``: the whole loop (the
        images as they are, the seed, the networks); else ``hypotheses`` first, then the networks if
        ``networks``, a verified result that its own geometry confirms ending the loop. A winner
        matched at another level, turn or window is matched again with the image whose content
        is smaller at its stored level (its keypoints are those the other pairs use)."""
        import dataclasses

        from ..matching.auto.loop import try_hypotheses

        m = self.matcher
        fa, fb, ia, ib, Sa, Sb = self._prepared(a, b)
        if per_pair:
            out = try_hypotheses(
                m, ia, ib, self.local_model, self.global_model, keys=(a, b), seed_matcher=self.seed_matcher
            )
        else:  # a window no larger than the photos, a photo no larger than the working size: the cost of a photo
            c = m.config
            photos = None if c.max_side is None else min(c.max_side, max(ia.shape[:2] + ib.shape[:2]))
            config = dataclasses.replace(c.auto, accept_consistent=True, window_max_side=photos, zoom_max_side=None)
            out = try_hypotheses(
                m, ia, ib, self.local_model, self.global_model, config, (a, b), None,
                hypotheses=list(hypotheses or []), networks=networks,
            )  # fmt: skip
        found, verified, h = out.matches, bool(out.verified), out.chosen
        kp_a, kp_b, matches = found.keypoints_a, found.keypoints_b, np.asarray(found.matches).reshape(-1, 2)
        rel = relation_of(out.verification, h) if verified else None
        chosen, scores = h.describe(), costs_to_scores(found.distances, self.lightglue)
        if (
            m.extractor.rectified
            and verified
            and (h.turn % 4 or h.window is not None or abs(np.log2(h.scale)) >= m.config.auto.same_log2)
        ):
            kp_a, kp_b, matches, scores = _union(
                (kp_a, kp_b, matches, scores), self._anchored(a, b, ia, ib, fa, fb, h.scale, h.turn)
            )
            chosen += "; anchored"
        if m.extractor.rectified and verified and h.window is not None and m.extractor.describes:
            kp_a, kp_b, matches, scores = _union(
                (kp_a, kp_b, matches, scores), self._window_anchored(a, b, ia, ib, fa, fb, h, found.factors)
            )
            chosen += "; window anchored"
        return PairResult(to_full(kp_a, Sa), to_full(kp_b, Sb), matches, scores, verified, chosen, rel)

    def levels(self, a: str, b: str, hypotheses) -> "PairResult":
        """Each hypothesis in turn until one verifies: the pair brought to one scale with the wide
        view at its stored level (its features.h5 keypoints, never enlarged) and the close-up turned
        and shrunk by the hypothesis's scale (:meth:`_anchored`), so that a close-up is extracted
        once per level and turn whatever its pairs and a photo not at all; verified as the
        hypothesis loop verifies, in the pixels of the wide view. Unverified: the last run's matches."""
        import dataclasses

        from ..matching import verify_matches

        m = self.matcher
        fa, fb, ia, ib, Sa, Sb = self._prepared(a, b)
        vconf = dataclasses.replace(m.config.verification, coverage_of="either")
        out = None
        for h in hypotheses:
            kp_a, kp_b, matches, scores = self._anchored(a, b, ia, ib, fa, fb, h.scale, h.turn)
            matches = np.asarray(matches, np.int64).reshape(-1, 2)
            pa, pb = kp_a[matches[:, 0]], kp_b[matches[:, 1]]
            if h.scale >= 1:  # B is the close-up: verified from B to A
                v = verify_matches(pb, pa, ib.shape[:2], ia.shape[:2], None, vconf)
                rel = relation_of(v, None)
                rel = None if rel is None else rel.inverse()
            else:
                v = verify_matches(pa, pb, ia.shape[:2], ib.shape[:2], None, vconf)
                rel = relation_of(v, None)
            out = PairResult(to_full(kp_a, Sa), to_full(kp_b, Sb), matches, scores, bool(v.verified), h.describe(), rel)
            if v.verified:
                break
        return out

    def _anchored(self, a, b, ia, ib, fa, fb, scale: float, turn: int):
        """:meth:`_turned_close_up` with the wide view at its stored level 1 (its keypoints are
        those the other pairs use) and the close-up shrunk by the scale."""
        close = min(1.0, 1.0 / scale if scale >= 1.0 else scale)
        factors = (1.0, close) if scale >= 1.0 else (close, 1.0)
        return self._turned_close_up(a, b, ia, ib, fa, fb, scale, turn, *factors)

    def _window_anchored(self, a, b, ia, ib, fa, fb, h, factors: tuple):
        """``(kp A, kp B (working pixels), K x 2, scores)``: the wide view's stored keypoints inside
        the hypothesis's window (those the other pairs use), described on the window at the level
        its match ran (``factors``, A's and B's), matched with the close-up's features of that run;
        B turned by the hypothesis's turn as the run turned it."""
        from ..geometry import project, turn_matrix
        from ..matching.auto.turns import unturn_points

        m = self.matcher
        i, x0, y0, x1, y1 = (int(v) for v in h.window)
        k = int(h.turn) % 4
        images, stored, names = (ia, ib), (fa, fb), (a, b)
        kp = stored[i].keypoints
        inside = np.flatnonzero((kp[:, 0] >= x0) & (kp[:, 0] <= x1 - 1) & (kp[:, 1] >= y0) & (kp[:, 1] <= y1 - 1))
        if len(inside) == 0:
            return np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32), np.zeros((0, 2), np.int64), np.zeros(0)
        window = np.ascontiguousarray(images[i][y0:y1, x0:x1])
        points = kp[inside] - np.array([x0, y0], np.float32)
        close = images[1 - i]
        if k and i == 1:  # B is the window: turned with its keypoints
            points = project(turn_matrix(k, window.shape[:2]), points).astype(np.float32)
            window = np.ascontiguousarray(np.rot90(window, k))
        key = names[1 - i]
        if k and i == 0:  # B is the close-up: turned as the run turned it (and cached under that key)
            close, key = np.ascontiguousarray(np.rot90(close, k)), (key, "turn", k)
        fw = m.extractor.describe(window, points, factors[i])
        fc = m.extract(close, factors[1 - i], key)
        kc = unturn_points(fc.keypoints, k, images[1 - i].shape) if k and i == 0 else fc.keypoints
        if i == 1:
            matches, costs = m.match_features(fc, fw)
            return kc, kp[inside], matches, costs_to_scores(costs, self.lightglue)
        matches, costs = m.match_features(fw, fc)
        return kp[inside], kc, matches, costs_to_scores(costs, self.lightglue)

    def _turned_close_up(self, a, b, ia, ib, fa, fb, scale: float, turn: int, f_a: float, f_b: float):
        """``(kp A, kp B (working pixels), K x 2, scores)`` of the pair at ``S_{A->B} = scale`` with B
        turned by ``turn`` quarter turns: the close-up (the image whose content is bigger) is turned
        (B by ``turn``, or A by ``-turn``), each image extracted at its factor (``f_a``, ``f_b``,
        levels of the shared cache; the wide view's level 1 is its stored features ``fa`` / ``fb``)."""
        from ..matching.auto.turns import unturn_points
        from .extract import snap_factor

        m = self.matcher
        b_is_close = scale >= 1.0
        (nc, ic, f_c, k), (nw, iw, f_w, stored) = (
            ((b, ib, f_b, turn % 4), (a, ia, f_a, fa)) if b_is_close else ((a, ia, f_a, -turn % 4), (b, ib, f_b, fb))
        )
        fw = stored if snap_factor(f_w, getattr(m, "levels_per_octave", 2)) == 1.0 else m.extract(iw, f_w, nw)
        turned = np.ascontiguousarray(np.rot90(ic, k)) if k else ic
        fc = m.extract(turned, f_c, (nc, "turn", k) if k else nc)
        kc = unturn_points(fc.keypoints, k, ic.shape) if k else fc.keypoints
        if b_is_close:
            matches, costs = m.match_features(fw, fc)
            return fw.keypoints, kc, matches, costs_to_scores(costs, self.lightglue)
        matches, costs = m.match_features(fc, fw)
        return kc, fw.keypoints, matches, costs_to_scores(costs, self.lightglue)


def _union(first: tuple, second: tuple):
    """Two match sets of one pair ``(kp A, kp B, K x 2, scores)`` as one (keypoints concatenated;
    :func:`one_to_one` later keeps one match per keypoint)."""
    ka1, kb1, m1, s1 = first
    ka2, kb2, m2, s2 = second
    m2 = np.asarray(m2, np.int64).reshape(-1, 2) + np.array([len(ka1), len(kb1)], np.int64)
    return (
        np.concatenate([ka1, ka2]),
        np.concatenate([kb1, kb2]),
        np.concatenate([np.asarray(m1, np.int64).reshape(-1, 2), m2]),
        np.concatenate([s1, s2]),
    )
