"""Step 3: match the pairs (``matches.h5``) and give every image one keypoint set (``keypoints.h5``).

``correction``:

* ``none``: the cached features of ``features.h5`` matched with the matcher (LightGlue or
  nearest neighbours), what an hloc user runs;
* ``auto``: the library's hypothesis loop per pair (:func:`~localscale.matching.auto_match`: the
  images as they are, then scales and quarter turns proposed by a SIFT seed and the networks, each
  verified), with one :class:`~.extract.LevelMatcher` shared by all pairs so that an image's
  features at a level and turn are computed once;
* ``global``, ``local``, ``fused``, ``searched``: the pair rectified by the correction's maps
  (:mod:`localscale.matching.correction`), again with the shared level cache.

Keypoints matched at another level, turn or window are mapped back to full-image pixels and merged
into the image's keypoint set (:class:`KeypointSet`: a keypoint within ``merge_px`` of one already
in the set is that keypoint; hloc merges the keypoints of dense matchers the same way), so that the
matches of different pairs share keypoints and form tracks. The set starts with ``features.h5``'s
keypoints (with ``none`` it is exactly them).

A pair already in ``matches.h5`` (either order) is skipped: a rerun resumes. ``matches.h5`` and
``keypoints.h5`` are flushed together (keypoints first) every ``flush_s`` seconds and at the end.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from ..errors import LocalScaleError
from .extract import FeatureConf, build_matcher, features_for_matcher, load_working, to_full
from .h5io import H5FileError, H5Writer, groups_with, matches0_from_matches, read_group
from .images import names_to_pair
from .progress import progress
from .report import warn

#: corrections the matching step runs (``gt`` needs a homography, ``refined`` is a two-pass pipeline)
SFM_CORRECTIONS = ("none", "auto", "global", "local", "fused", "searched")


class KeypointSet:
    """One image's keypoints (full-image pixels), grown by the matches of every pair: a point
    within ``merge_px`` of a keypoint already in the set is that keypoint (the nearest), any other
    point is appended. The first keypoints (``base``) keep their indices."""

    def __init__(self, base: np.ndarray, merge_px: float = 1.0):
        self.merge_px = float(merge_px)
        self._points: list = [tuple(p) for p in np.asarray(base, np.float64).reshape(-1, 2)]
        self.num_base = len(self._points)
        self._grid: dict = {}
        for i, p in enumerate(self._points):
            self._grid.setdefault(self._cell(p), []).append(i)

    def _cell(self, p) -> tuple:
        return int(np.floor(p[0] / self.merge_px)), int(np.floor(p[1] / self.merge_px))

    def __len__(self) -> int:
        return len(self._points)

    @property
    def keypoints(self) -> np.ndarray:
        return np.asarray(self._points, np.float32).reshape(-1, 2)

    def index(self, points: np.ndarray) -> np.ndarray:
        """The index of each point in the set (added when no keypoint is within ``merge_px``)."""
        out = np.empty(len(points), np.int64)
        r2 = self.merge_px**2
        for k, p in enumerate(np.asarray(points, np.float64).reshape(-1, 2)):
            cx, cy = self._cell(p)
            best, best_d = -1, r2
            for dx in (-1, 0, 1):
                for dy in (-1, 0, 1):
                    for i in self._grid.get((cx + dx, cy + dy), ()):
                        q = self._points[i]
                        d = (q[0] - p[0]) ** 2 + (q[1] - p[1]) ** 2
                        if d <= best_d:
                            best, best_d = i, d
            if best < 0:
                best = len(self._points)
                self._points.append((float(p[0]), float(p[1])))
                self._grid.setdefault((cx, cy), []).append(best)
            out[k] = best
        return out


def one_to_one(ia: np.ndarray, ib: np.ndarray, scores: np.ndarray):
    """Matches ``(ia, ib)`` with each index used once on either side (merged keypoints can repeat
    one): the best-scored match wins. Returns ``(K x 2, K scores)``."""
    order = np.argsort(-scores, kind="stable")
    used_a, used_b, keep = set(), set(), []
    for k in order:
        a, b = int(ia[k]), int(ib[k])
        if a in used_a or b in used_b:
            continue
        used_a.add(a)
        used_b.add(b)
        keep.append(k)
    keep = np.asarray(sorted(keep), np.int64)
    return np.stack([ia[keep], ib[keep]], 1).reshape(-1, 2).astype(np.int64), scores[keep].astype(np.float32)


@dataclass
class PairRecord:
    """What matching one pair found: matches, whether the matcher's own verification passed
    (``auto``; None otherwise), the hypothesis chosen, seconds."""

    a: str
    b: str
    num_matches: int
    verified: Optional[bool] = None
    chosen: str = ""
    seconds: float = 0.0

    def to_dict(self) -> dict:
        return {
            "a": self.a,
            "b": self.b,
            "num_matches": self.num_matches,
            "verified": self.verified,
            "chosen": self.chosen,
            "seconds": round(self.seconds, 3),
        }


@dataclass
class MatchStats:
    pairs: list = field(default_factory=list)  # PairRecord, resumed ones included
    matched: int = 0  # pairs matched in this run
    resumed: int = 0  # pairs found in matches.h5
    feature_sets: int = 0  # feature sets the level cache computed
    added_keypoints: int = 0  # keypoints beyond features.h5's, all images
    seconds: float = 0.0

    def to_dict(self) -> dict:
        return {
            "matched": self.matched,
            "resumed": self.resumed,
            "feature_sets_computed": self.feature_sets,
            "added_keypoints": self.added_keypoints,
            "seconds": round(self.seconds, 2),
            "pairs": [p.to_dict() for p in self.pairs],
        }


def _costs_to_scores(costs: np.ndarray, lightglue: bool) -> np.ndarray:
    c = np.asarray(costs, np.float32)
    return (1.0 - c) if lightglue else (1.0 - 0.5 * c**2)


def match_pairs(
    images: list,
    pairs: list,
    features_path,
    matches_path,
    keypoints_path,
    conf: FeatureConf = FeatureConf(),
    correction: str = "none",
    device: str = "cpu",
    matcher=None,
    local_model=None,
    global_model=None,
    merge_px: float = 1.0,
    overwrite: bool = False,
    flush_s: float = 30.0,
    show_progress: bool = True,
    executor=None,
) -> MatchStats:
    """Match ``pairs`` (``[(name_a, name_b), ...]``) of ``images`` and write ``matches_path`` and
    ``keypoints_path`` (module docstring). ``features_path`` must hold every image of the pairs
    (:func:`~.extract.extract_features` with the same ``conf``).

    ``matcher``: a :class:`~.extract.LevelMatcher` to share (default: built from ``conf``);
    ``local_model`` / ``global_model``: the networks of the correction (default: bundled weights).
    ``overwrite``: rematch every pair (else pairs in ``matches_path`` are skipped).
    ``executor``: an :class:`~localscale.engine.Executor` other than the local one matches the pairs
    on its workers (each with its own level cache and the bundled networks); the driver merges the
    keypoints in pair order, so the outputs are those of the local run.
    """
    if correction not in SFM_CORRECTIONS:
        raise LocalScaleError(
            f"correction must be one of {', '.join(SFM_CORRECTIONS)} for reconstruction, got {correction!r}"
        )
    t_start = time.perf_counter()
    by_name = {im.name: im for im in images}
    _check_extracted(features_path, pairs)
    sets = _keypoint_sets(images, features_path, keypoints_path, merge_px, fresh=overwrite)
    stats, todo = _split_resumed(pairs, {} if overwrite else _done_pairs(matches_path))
    output = _MatchOutput(matches_path, keypoints_path, sets, by_name, fresh=overwrite)
    if todo and executor is not None and executor.name != "local":
        factory = PairRunnerFactory(
            tuple(images), str(features_path), conf, correction, device, local_model, global_model
        )
        label = f"match ({correction})" if show_progress else None
        _match_todo_on(executor, factory, todo, sets, output, stats, flush_s, label)
    elif todo:
        runner = _PairRunner(
            by_name, features_path, conf, correction, device, matcher, local_model, global_model, len(images)
        )
        _match_todo(runner, todo, sets, output, stats, flush_s, f"match ({correction})", show_progress)
    else:
        output.flush()
    stats.added_keypoints = sum(len(s) - s.num_base for s in sets.values())
    stats.seconds = time.perf_counter() - t_start
    if correction == "auto":
        unverified = [p for p in stats.pairs if p.verified is False]
        if unverified and len(unverified) == len(stats.pairs):
            warn(f"auto verified none of the {len(stats.pairs)} pairs: the images may not overlap")
    return stats


def _check_extracted(features_path, pairs) -> None:
    """Every image of ``pairs`` has its features in ``features_path`` (else :class:`H5FileError`)."""
    have = set(groups_with(features_path, "keypoints"))
    missing = sorted({n for p in pairs for n in p} - have)
    if missing:
        raise H5FileError(
            f"{features_path} lacks the features of {missing[0]}"
            f"{f' and {len(missing) - 1} more' if len(missing) > 1 else ''}: run the extraction first"
        )


def _split_resumed(pairs, done: dict):
    """``(stats holding the pairs already in done (either order), the pairs still to match)``."""
    stats = MatchStats()
    todo = []
    for a, b in pairs:
        key = names_to_pair(a, b) if names_to_pair(a, b) in done else names_to_pair(b, a)
        if key in done:
            stats.pairs.append(done[key])
            stats.resumed += 1
        else:
            todo.append((a, b))
    return stats, todo


def _match_todo(runner, todo, sets, output, stats: MatchStats, flush_s: float, desc: str, show_progress: bool):
    """Match the ``todo`` pairs in this process into ``output`` and ``stats`` (:func:`_apply_in_order`)."""
    work = MatchPair()
    pairs = progress(todo, desc, unit="pair", disable=not show_progress)
    _apply_in_order(((i, work(runner, p)) for i, p in enumerate(pairs)), todo, sets, output, stats, flush_s)
    stats.feature_sets = runner.feature_sets  # with the level cache shared with extraction, its levels too


def _match_todo_on(executor, factory, todo, sets, output, stats: MatchStats, flush_s: float, label):
    """:func:`_match_todo` with the pairs matched on ``executor``'s workers."""
    results = executor.map(MatchPair(), todo, state=factory, progress=label, unit="pair")
    _apply_in_order(results, todo, sets, output, stats, flush_s)


def _apply_in_order(results, todo, sets, output, stats: MatchStats, flush_s: float) -> None:
    """Add the ``(index, MatchPair result)`` of ``results`` (any order) to ``output`` and ``stats`` in pair
    order, so that the keypoint sets grow as in a run in this process; flush every ``flush_s`` seconds
    and at the end (also when interrupted: what was applied is kept). A failed pair ends the run."""
    last, pending, applied = time.monotonic(), {}, 0
    try:
        for i, result in results:
            if isinstance(result, Exception):
                raise result
            pending[i] = result
            while applied in pending:
                (a, b), (kp_a, kp_b, m, scores, verified, chosen, seconds, computed) = (
                    todo[applied],
                    pending.pop(applied),
                )
                mm, ss = _index_matches(sets, a, b, kp_a, kp_b, m, scores)
                stats.pairs.append(output.add(a, b, mm, ss, verified, chosen, seconds))
                stats.matched += 1
                stats.feature_sets += computed
                applied += 1
            if time.monotonic() - last >= flush_s:
                output.flush()
                last = time.monotonic()
    finally:
        output.flush()


def _index_matches(sets: dict, a: str, b: str, kp_a, kp_b, m, scores):
    """The matches ``m`` of keypoints ``kp_a``, ``kp_b`` (full-image pixels) as ``(K x 2 indices into the
    keypoint sets of A and B (new points added to them), one match per keypoint; K scores)``."""
    ia = sets[a].index(kp_a[m[:, 0]]) if len(m) else np.zeros(0, np.int64)
    ib = sets[b].index(kp_b[m[:, 1]]) if len(m) else np.zeros(0, np.int64)
    return one_to_one(ia, ib, scores[: len(m)]) if len(m) else (np.zeros((0, 2), np.int64), np.zeros(0, np.float32))


@dataclass(frozen=True)
class PairRunnerFactory:
    """Worker state of the matching step on an executor: a pair runner with its own level cache and networks."""

    images: tuple
    features_path: str
    conf: FeatureConf
    correction: str
    device: str = "cpu"
    local_model: Any = None  #: the networks to ship to the workers (None: each loads the bundled weights)
    global_model: Any = None

    def __call__(self):
        by_name = {im.name: im for im in self.images}
        return _PairRunner(
            by_name,
            self.features_path,
            self.conf,
            self.correction,
            self.device,
            None,
            self.local_model,
            self.global_model,
            len(by_name),
        )


@dataclass(frozen=True)
class MatchPair:
    """Work of one pair ``(name_a, name_b)``: ``(keypoints A, keypoints B, matches, scores, verified,
    chosen, seconds, feature sets computed for it)``."""

    def __call__(self, runner, pair):
        t0, before = time.perf_counter(), runner.feature_sets
        out = runner.run(*pair)
        return (*out, time.perf_counter() - t0, runner.feature_sets - before)


class _MatchOutput:
    """``matches.h5`` and ``keypoints.h5`` being written: the matches of each pair added, and the
    keypoint sets of the images they touched, flushed together (keypoints first)."""

    def __init__(self, matches_path, keypoints_path, sets: dict, by_name: dict, fresh: bool):
        self.matches_path, self.keypoints_path = matches_path, keypoints_path
        self.sets, self.by_name = sets, by_name
        self.m_writer = H5Writer(matches_path, fresh=fresh)
        self.k_writer = H5Writer(keypoints_path, fresh=fresh)
        self.changed = set(by_name) if (fresh or not Path(keypoints_path).exists()) else set()

    def add(self, a: str, b: str, mm: np.ndarray, ss: np.ndarray, verified, chosen: str, seconds: float) -> PairRecord:
        """Add the matches ``mm`` (scores ``ss``) of a pair matched in ``seconds``; returns its record."""
        self.changed.update((a, b))
        m0, s0 = matches0_from_matches(mm, ss, len(self.sets[a]))
        rec = PairRecord(a, b, int(len(mm)), verified, chosen, seconds)
        attrs = {
            "num_matches": rec.num_matches,
            "chosen": chosen,
            "seconds": rec.seconds,
            "name0": a,
            "name1": b,
        }
        if verified is not None:
            attrs["verified"] = bool(verified)
        self.m_writer.add(names_to_pair(a, b), {"matches0": m0, "matching_scores0": s0}, attrs)
        return rec

    def flush(self) -> None:
        """Write what was added: the changed keypoint sets, then the matches."""
        for n in sorted(self.changed):
            im = self.by_name[n]
            self.k_writer.add(
                n,
                {"keypoints": self.sets[n].keypoints, "image_size": np.array([im.shape[1], im.shape[0]], np.int64)},
                {"num_base": self.sets[n].num_base},
            )
        self.changed.clear()
        if self.k_writer.pending or not Path(self.keypoints_path).exists():
            self.k_writer.flush()  # first: the matches index only keypoints it holds
        if self.m_writer.pending or not Path(self.matches_path).exists():
            self.m_writer.flush()


def _done_pairs(matches_path) -> dict:
    out = {}
    for key in groups_with(matches_path, "matches0"):
        g = read_group(matches_path, key, ("matches0",))
        at = g["attrs"]
        a, b = str(at.get("name0", "")), str(at.get("name1", ""))
        v = at.get("verified")
        out[key] = PairRecord(
            a,
            b,
            int(np.sum(g["matches0"] >= 0)),
            None if v is None else bool(v),
            str(at.get("chosen", "")),
            float(at.get("seconds", 0.0)),
        )
    return out


def _keypoint_sets(images, features_path, keypoints_path, merge_px: float, fresh: bool) -> dict:
    """Every image's :class:`KeypointSet`: ``keypoints.h5``'s (a resumed run) or ``features.h5``'s."""
    have = set() if fresh else set(groups_with(keypoints_path, "keypoints"))
    extracted = set(groups_with(features_path, "keypoints"))
    sets = {}
    for im in images:
        base = (
            read_group(features_path, im.name, ("keypoints",))["keypoints"]
            if im.name in extracted
            else np.zeros((0, 2), np.float32)
        )
        s = KeypointSet(base, merge_px)
        if im.name in have:
            stored = read_group(keypoints_path, im.name, ("keypoints",))["keypoints"]
            if len(stored) < len(base) or not np.array_equal(stored[: len(base)], base):
                raise H5FileError(
                    f"{keypoints_path}: the keypoints of {im.name} do not start with those of "
                    f"{features_path} (written by another extraction): rerun with overwrite"
                )
            s.index(stored[len(base) :])
            if len(s) != len(stored):
                raise H5FileError(
                    f"{keypoints_path}: the keypoints of {im.name} were merged with another "
                    "merge distance: rerun with overwrite"
                )
        sets[im.name] = s
    return sets


class _PairRunner:
    """Matches one pair with the correction: ``run(a, b) -> (keypoints A, keypoints B (full-image
    pixels), K x 2 matches, K scores, verified or None, chosen hypothesis)``."""

    def __init__(
        self, by_name, features_path, conf, correction, device, matcher, local_model, global_model, num_images
    ):
        from ..matching import get_correction

        self.by_name, self.features_path, self.conf, self.correction = by_name, features_path, conf, correction
        self.matcher = matcher or build_matcher(conf, device, num_images)
        self.lightglue = self.matcher.config.matching == "lightglue"
        self.method = get_correction(correction)
        self.local_model, self.global_model = local_model, global_model
        if correction != "none" and (
            (local_model is None and "local" in self.method.models)
            or (global_model is None and "global" in self.method.models)
        ):
            loaded = self.method.load_models(device=device)  # the bundled weights of what is missing
            self.local_model = local_model if local_model is not None else loaded[0]
            self.global_model = global_model if global_model is not None else loaded[1]
        self.seed = None
        seed_name = self.matcher.config.auto.seed
        if correction == "auto" and seed_name is not None and seed_name != self.matcher.config.name:
            from ..matching import match_config
            from .extract import LevelMatcher

            self.seed = LevelMatcher(match_config(seed_name, max_side=None), device, cache_size=max(8, 2 * num_images))
        self._features: OrderedDict = OrderedDict()
        self._images: OrderedDict = OrderedDict()
        self._seeded: set = set()

    @property
    def feature_sets(self) -> int:
        """Feature sets the level caches computed in this run (matcher and seed)."""
        count = getattr(self.matcher, "level_count", 0)
        return count + (self.seed.level_count if self.seed is not None else 0)

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

    def run(self, a: str, b: str):
        m = self.matcher
        (fa, Sa), (fb, Sb) = self._stored(a), self._stored(b)
        if self.correction == "none":
            matches, costs = m.match_features(fa, fb)
            return (
                to_full(fa.keypoints, Sa),
                to_full(fb.keypoints, Sb),
                matches,
                _costs_to_scores(costs, self.lightglue),
                None,
                "",
            )
        (ia, Sa), (ib, Sb) = self._image(a), self._image(b)
        if m.extractor.rectified:
            for name, f in ((a, fa), (b, fb)):
                if name not in self._seeded:
                    m.seed(name, f)  # level 1 of every pair is features.h5's
                    self._seeded.add(name)
        if self.correction == "auto":
            from ..matching import auto_match

            out = auto_match(m, ia, ib, self.local_model, self.global_model, keys=(a, b), seed_matcher=self.seed)
            found, verified, chosen = out.matches, bool(out.verified), out.chosen.describe()
            h = out.chosen
            kp_a, kp_b = found.keypoints_a, found.keypoints_b
            matches, scores = found.matches, _costs_to_scores(found.distances, self.lightglue)
            if (
                m.extractor.rectified
                and verified
                and (h.turn % 4 or h.window is not None or abs(np.log2(h.scale)) >= m.config.auto.same_log2)
            ):
                # the winner matched at another level, turn or window: match again with the image whose
                # content is smaller at its stored level, so its keypoints are those the other pairs use
                kp_a, kp_b, matches, scores = _union(
                    (kp_a, kp_b, matches, scores), self._anchored(a, b, ia, ib, fa, fb, h.scale, h.turn)
                )
                chosen += "; anchored"
        else:
            cfg = m.config
            sa, sb = self.method.maps(ia, ib, None, self.local_model, self.global_model, cfg.gate, bf16=cfg.bf16)
            verified = None
            if m.extractor.rectified:
                from ..matching import pair_scale

                level = pair_scale(sa, sb)
                kp_a, kp_b, matches, scores = self._anchored(a, b, ia, ib, fa, fb, level, 0)
                chosen = f"level {level:.3g}"
            else:  # patches: the keypoints stay, each patch's size follows the maps
                found = m.match(ia, ib, sa, sb, (a, b))
                kp_a, kp_b, matches = found.keypoints_a, found.keypoints_b, found.matches
                scores, chosen = _costs_to_scores(found.distances, self.lightglue), "maps"
        return to_full(kp_a, Sa), to_full(kp_b, Sb), matches, scores, verified, chosen

    def _anchored(self, a, b, ia, ib, fa, fb, scale: float, turn: int):
        """Match the pair at ``S_{A->B} = scale`` with B turned by ``turn`` quarter turns, keeping the
        image whose content is smaller as it is (its stored level-1 features) and bringing the
        other one (the close-up) to it: turned (B by ``turn``, or A by ``-turn``) and shrunk by the
        scale, at a level of the shared cache. Returns ``(kp A, kp B (working pixels), K x 2, scores)``."""
        from ..matching.auto import turn_matrix

        m = self.matcher
        b_is_close = scale >= 1.0
        name, image = (b, ib) if b_is_close else (a, ia)
        factor = min(1.0, 1.0 / scale if b_is_close else scale)
        k = (turn if b_is_close else -turn) % 4
        turned = np.ascontiguousarray(np.rot90(image, k)) if k else image
        fc = m.extract(turned, factor, (name, "turn", k) if k else name)
        kc = fc.keypoints
        if k:
            M = np.linalg.inv(turn_matrix(k, image.shape))
            kc = (np.asarray(kc, np.float64) @ M[:2, :2].T + M[:2, 2]).astype(np.float32)
        if b_is_close:
            matches, costs = m.match_features(fa, fc)
            return fa.keypoints, kc, matches, _costs_to_scores(costs, self.lightglue)
        matches, costs = m.match_features(fc, fb)
        return kc, fb.keypoints, matches, _costs_to_scores(costs, self.lightglue)


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


def read_all_matches(matches_path) -> dict:
    """``{(name_a, name_b): (K x 2 matches, K scores)}`` of ``matches.h5`` (indices into
    ``keypoints.h5``; the names as matched, from the groups' ``name0`` / ``name1``)."""
    from .h5io import matches_from_matches0, open_h5

    out = {}
    keys = groups_with(matches_path, "matches0")
    with open_h5(matches_path) as f:
        for key in keys:
            g = f[key]
            a, b = str(g.attrs.get("name0", "")), str(g.attrs.get("name1", ""))
            if not a or not b:
                a, b = key.split("/", 1)  # written by another tool: names without '/'
            out[(a, b)] = matches_from_matches0(g["matches0"][()], g["matching_scores0"][()])
    return out
