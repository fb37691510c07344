"""Step 3: match the pairs (``matches.h5``) and give every image one keypoint set (``keypoints.h5``).

``correction``:

* ``none``: the cached features of ``features.h5`` matched with the matcher (LightGlue or
  nearest neighbours), what an hloc user runs;
* ``auto``: scales and quarter turns found for the collection as a whole (:func:`_match_with_graph`):
  every pair as it is with a two-view verification, the SIFT seed's geometry of the pairs that do
  not verify, then hypotheses composed along the verified pairs (:mod:`.pair_graph`: a close-up
  verified against one photo is related to that photo's neighbours) and the networks only for
  pairs that the graph cannot join; ``auto_graph=False``: the whole hypothesis loop
  (:func:`~localscale.matching.auto_match`) on every pair. One :class:`~.extract.LevelMatcher` is
  shared by all pairs, so that an image's features at a level and turn are computed once;
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

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import LocalScaleError
from .extract import FeatureConf
from .h5io import H5FileError, H5Writer, groups_with, matches0_from_matches, read_group
from .images import names_to_pair
from .keypoints import KeypointSet, one_to_one
from .pair_graph import PairGraph, Relation
from .pair_runner import MatchPair, PairRunner, PairRunnerFactory
from .progress import progress
from .report import warn

#: corrections the matching step runs (``gt`` needs a homography, ``refined`` is a two-pass pipeline)
SFM_CORRECTIONS = ("none", "auto", "global", "local", "fused", "searched")


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
    relation: Optional[Relation] = None  #: ``auto``: the verified pair's scale and quarter turn

    def to_dict(self) -> dict:
        out = {
            "a": self.a,
            "b": self.b,
            "num_matches": self.num_matches,
            "verified": self.verified,
            "chosen": self.chosen,
            "seconds": round(self.seconds, 3),
        }
        if self.relation is not None:
            out["relation"] = {"scale": round(self.relation.scale, 4), "turn": self.relation.turn}
        return out


@dataclass
class MatchStats:
    pairs: list = field(default_factory=list)  # PairRecord, resumed ones included
    matched: int = 0  # pairs matched in this run
    resumed: int = 0  # pairs found in matches.h5
    feature_sets: int = 0  # feature sets the level cache computed
    added_keypoints: int = 0  # keypoints beyond features.h5's, all images
    seconds: float = 0.0
    steps: dict = field(default_factory=dict)  # auto on the pair graph: {step: {"pairs", "verified", "seconds"}}

    def to_dict(self) -> dict:
        return {
            "matched": self.matched,
            "resumed": self.resumed,
            "feature_sets_computed": self.feature_sets,
            "added_keypoints": self.added_keypoints,
            "seconds": round(self.seconds, 2),
            **({"auto_steps": self.steps} if self.steps else {}),
            "pairs": [p.to_dict() for p in self.pairs],
        }


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
    auto_graph: bool = True,
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
    ``auto_graph``: ``auto`` driven by the pair graph (:func:`_match_with_graph`); False: the whole
    hypothesis loop on every pair that does not verify clearly as it is.
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
    runner = None
    if todo and executor is not None and executor.name != "local":
        factory = PairRunnerFactory(
            tuple(images), str(features_path), conf, correction, device, local_model, global_model
        )

        def run_items(items, label):
            return executor.map(
                MatchPair(), items, state=factory, progress=label if show_progress else None, unit="pair"
            )
    elif todo:
        runner = PairRunner(
            by_name, features_path, conf, correction, device, matcher, local_model, global_model, len(images)
        )

        def run_items(items, label):
            work = MatchPair()
            return (
                (i, work(runner, it))
                for i, it in enumerate(progress(items, label, unit="pair", disable=not show_progress))
            )

    if todo and correction == "auto" and auto_graph:
        _match_with_graph(run_items, todo, sets, output, stats, flush_s, conf.match_config().auto.same_log2)
    elif todo:
        _apply_in_order(run_items(todo, f"match ({correction})"), todo, sets, output, stats, flush_s)
    else:
        output.flush()
    if runner is not None:
        stats.feature_sets = runner.feature_sets  # with the level cache shared with extraction, its levels too
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


def _apply_in_order(results, todo, sets, output, stats: MatchStats, flush_s: float) -> None:
    """Add the ``(index, PairResult)`` of ``results`` (any order) to ``output`` and ``stats`` in pair
    order, so that the keypoint sets grow as in a run in this process; flush every ``flush_s`` seconds
    and at the end (also when interrupted: what was applied is kept). A failed pair ends the run."""
    last, pending, applied = time.monotonic(), {}, 0
    try:
        for i, result in results:
            if isinstance(result, Exception):
                raise result
            pending[i] = result
            while applied in pending:
                (a, b), r = todo[applied], pending.pop(applied)
                mm, ss = _index_matches(sets, a, b, r.kp_a, r.kp_b, r.matches, r.scores)
                stats.pairs.append(output.add(a, b, mm, ss, r.verified, r.chosen, r.seconds, r.relation))
                stats.matched += 1
                stats.feature_sets += r.computed
                applied += 1
            if time.monotonic() - last >= flush_s:
                output.flush()
                last = time.monotonic()
    finally:
        output.flush()


#: inliers of a pair verified as it is for its quarter turn to bind the hypotheses of the images it
#: joins (fewer: chance verifications would bind truly turned photos)
TURN_INLIERS = 40

#: pairs per image on which the networks run while the graph does not join the pair's images
NETWORK_PAIRS_PER_IMAGE = 3

#: pairs per image matched in the window of the wide view that the seed's geometry gives
ANCHOR_PAIRS_PER_IMAGE = 2

#: hypotheses per pair in the graph step
LEVEL_HYPOTHESES = 1

#: pairs per image in the graph step's first round (its best supported); an image gets the rest of
#: its pairs in a second round when one of its first round verified
GRAPH_PAIRS_PER_IMAGE = 3

#: a relation composed through the graph is tried when it turns, or zooms by at least this many
#: octaves (a milder zoom the matcher takes as it is, which step 1 tried)
COMPOSED_MIN_LOG2 = 1.0


def _match_with_graph(
    run_items, todo, sets, output, stats: MatchStats, flush_s: float, same_log2: float, turn_inliers: int = TURN_INLIERS
) -> None:
    """``auto`` on a collection, in steps that each run on the pairs still open (on the executor's
    workers when there is one); the driver adds the pairs each step settles, in pair order:

    1. every pair as it is (the stored features, two-view verification): settled when it verifies
       clearly or with no scale change or turn to try;
    2. the seed's (SIFT) geometry of each open pair; where it does not verify (or gives a strong
       zoom no window), the similarity its matches' keypoints agree on
       (:meth:`~.pair_runner.PairRunner.seed`);
    3. anchors: the seed's hypothesis matched in the window of the wide view that the close-up shows
       (:attr:`~localscale.matching.AutoConfig.window_share`), on at most
       :data:`ANCHOR_PAIRS_PER_IMAGE` pairs per image, the best supported first;
    4. the verified pairs (steps 1 to 3, and a resumed run's) make a :class:`~.pair_graph.PairGraph`;
       each open pair tries :data:`LEVEL_HYPOTHESES` of: the seed's scale and turn, its own
       geometry's, and those composed through a common neighbour that turn or zoom by
       :data:`COMPOSED_MIN_LOG2` octaves or more (a strong zoom half an octave less: the close-up
       keeps detail), at the images' levels
       (:meth:`~.pair_runner.PairRunner.levels`: each image extracted once per level and turn
       whatever its pairs); a pair with none whose images the graph does not join runs the
       networks (on at most :data:`NETWORK_PAIRS_PER_IMAGE` pairs per image, those with the most
       matches first). The hypotheses run in rounds (:func:`_first_round`, :func:`_next_round`): each
       image's :data:`GRAPH_PAIRS_PER_IMAGE` best supported pairs, then, for each image that one
       of its pairs of the round before joined, its next :data:`GRAPH_PAIRS_PER_IMAGE`.

    The pairs of step 1 with at least ``turn_inliers`` inliers, then those of step 3, fix the
    images' quarter turns (:func:`_quarter_turns`); a hypothesis or seed geometry that turns two
    images these pairs join otherwise is dropped (a symmetric object seen from opposite sides
    verifies turned). A pair that nothing verified keeps its step-1 matches."""
    graph = PairGraph()
    for rec in stats.pairs:
        if rec.relation is not None:
            graph.add(rec.a, rec.b, rec.relation)
    every = list(range(len(todo)))
    best = _run_some(run_items, {i: (*todo[i], "as_they_are") for i in every}, "as they are", stats)
    for i in every:
        if best[i].verified and best[i].relation is not None:
            graph.add(*todo[i], best[i].relation)
    open_ = [i for i in every if not best[i].final]
    _apply_some([i for i in every if best[i].final], best, todo, sets, output, stats, flush_s)
    clear = [
        (*todo[i], best[i].relation.turn) for i in every if best[i].final and best[i].relation.strength >= turn_inliers
    ]
    turns = _quarter_turns(clear)
    seeds = _run_some(run_items, {i: (*todo[i], "seed") for i in open_}, "seed", stats)
    for i, r in seeds.items():
        stats.feature_sets += r.computed
        h = r.relation if r.relation is not None else r.hypothesis
        if h is not None and not _turn_fits(turns, *todo[i], h.turn % 4):
            r.relation = r.hypothesis = None
        if r.relation is not None:
            graph.add(*todo[i], r.relation)
    tried: dict = {i: [] for i in open_}
    anchors, count = {}, {}
    for i in sorted((i for i in open_ if seeds[i].hypothesis is not None), key=lambda i: (-seeds[i].support, i)):
        a, b = todo[i]
        if seeds[i].hypothesis.window is not None and max(count.get(a, 0), count.get(b, 0)) < ANCHOR_PAIRS_PER_IMAGE:
            count[a], count[b] = count.get(a, 0) + 1, count.get(b, 0) + 1
            anchors[i] = (a, b, "hypotheses", [seeds[i].hypothesis], False)
    open_ = _settle(run_items, anchors, "anchors", open_, best, tried, graph, todo, sets, output, stats, flush_s)
    clear += [
        (*todo[i], best[i].relation.turn)
        for i in anchors
        if best[i].verified and best[i].relation.strength >= turn_inliers
    ]
    turns = _quarter_turns(clear)
    items, levels, quota = {}, {}, {}
    for i in sorted(open_, key=lambda i: (-len(best[i].matches), i)):
        a, b = todo[i]
        hyps = _graph_hypotheses(graph, a, b, best[i], seeds.get(i), tried[i], same_log2)
        hyps = [h for h in hyps if _turn_fits(turns, a, b, h.turn)][:LEVEL_HYPOTHESES]
        if hyps:
            levels[i] = (a, b, "levels", hyps)
        elif not graph.connected(a, b) and max(quota.get(a, 0), quota.get(b, 0)) < NETWORK_PAIRS_PER_IMAGE:
            quota[a], quota[b] = quota.get(a, 0) + 1, quota.get(b, 0) + 1
            items[i] = (a, b, "hypotheses", [], True)
    support = {i: _support(graph, *todo[i], seeds.get(i), same_log2) for i in levels}
    first, rest, charged = _first_round(levels, support, graph)
    open_ = _settle(
        run_items, {**items, **first}, "graph", open_, best, tried, graph, todo, sets, output, stats, flush_s
    )
    done_round = first
    while True:
        more, rest = _next_round(done_round, rest, charged, set(open_))
        open_ = _settle(run_items, more, "graph, more", open_, best, tried, graph, todo, sets, output, stats, flush_s)
        if not more:
            break
        done_round = more
    _apply_some(sorted(open_), best, todo, sets, output, stats, flush_s)


def _support(graph: PairGraph, a: str, b: str, seed, same_log2: float) -> int:
    """Inliers behind a pair's hypotheses: the strongest of its seed geometry and the relations the
    graph composes for it."""
    relations = graph.composed(a, b, same_log2=same_log2)
    relations += [] if seed is None or seed.relation is None else [seed.relation]
    return max((r.strength for r in relations), default=0)


def _first_round(levels: dict, support: dict, graph: PairGraph) -> tuple:
    """``(first, rest, charged)``: the graph step's first round and the pairs left. Each pair is
    charged to the image of the two with fewer verified pairs (the one the pair would join to the
    collection: ``charged[i]``); the first round tries the :data:`GRAPH_PAIRS_PER_IMAGE` best
    supported pairs of each image."""
    ordered = {i: levels[i] for i in sorted(levels, key=lambda i: (-support[i], i))}
    charged = {i: min(item[:2], key=lambda x: (len(graph.neighbours(x)), x)) for i, item in ordered.items()}
    first, rest = _best_per_image(ordered, charged, set(charged.values()))
    return first, rest, charged


def _next_round(done_round: dict, rest: dict, charged: dict, still_open: set) -> tuple:
    """``(next, rest)``: the next round of the graph step takes, of the pairs ``rest``, the
    :data:`GRAPH_PAIRS_PER_IMAGE` best supported charged to each image that one of its own pairs of
    the round just run verified: hypotheses that keep failing for an image are not tried further."""
    return _best_per_image(rest, charged, {charged[i] for i in done_round if i not in still_open})


def _best_per_image(items: dict, charged: dict, images: set) -> tuple:
    """``(taken, left)``: of ``items`` (in the order of support), the first
    :data:`GRAPH_PAIRS_PER_IMAGE` charged to each of ``images``, and the others."""
    taken, left, count = {}, {}, {}
    for i, item in items.items():
        if charged[i] in images and count.get(charged[i], 0) < GRAPH_PAIRS_PER_IMAGE:
            count[charged[i]] = count.get(charged[i], 0) + 1
            taken[i] = item
        else:
            left[i] = item
    return taken, left


def _settle(run_items, items: dict, step: str, open_, best, tried, graph, todo, sets, output, stats, flush_s) -> list:
    """Runs the ``items`` of the ``auto`` step ``step``; the pairs that verify get their result in
    ``best`` and their relation in ``graph``, and are applied; returns the pairs still open."""
    found = _run_some(run_items, items, step, stats)
    settled = []
    for i, r in found.items():
        tried[i] += items[i][3]
        if r.verified:
            best[i] = r
            settled.append(i)
            graph.add(*todo[i], r.relation)
    _apply_some(sorted(settled), best, todo, sets, output, stats, flush_s)
    done = set(settled)
    return [i for i in open_ if i not in done]


def _quarter_turns(edges) -> dict:
    """``{image: (component, quarter turns)}`` from pairs ``(a, b, turn)`` (B turned by ``turn`` is
    upright with A): each image's turn relative to the first image of its component, by a
    breadth-first walk (where the pairs disagree, the first path wins)."""
    adjacent: dict = {}
    for a, b, k in edges:
        adjacent.setdefault(a, []).append((b, k))
        adjacent.setdefault(b, []).append((a, -k))
    out: dict = {}
    for start in sorted(adjacent):
        if start in out:
            continue
        out[start], queue = (start, 0), [start]
        while queue:
            x = queue.pop(0)
            for y, k in adjacent[x]:
                if y not in out:
                    out[y] = (start, (out[x][1] - k) % 4)
                    queue.append(y)
    return out


def _turn_fits(turns: dict, a: str, b: str, turn: int) -> bool:
    """Whether turning B by ``turn`` agrees with :func:`_quarter_turns` (True where they do not join A and B)."""
    if a in turns and b in turns and turns[a][0] == turns[b][0]:
        return (turns[a][1] - turns[b][1]) % 4 == turn % 4
    return True


def _run_some(run_items, items: dict, step: str, stats: MatchStats) -> dict:
    """``{index: PairResult}`` of the work ``items`` (``{index: item}``) of the ``auto`` step ``step``
    (its pairs, verified pairs and seconds go to ``stats.steps``); a failed item ends the run."""
    keys, out, t0 = sorted(items), {}, time.perf_counter()
    for k, r in run_items([items[i] for i in keys], f"match (auto: {step})") if keys else ():
        if isinstance(r, Exception):
            raise r
        out[keys[k]] = r
    verified = sum(bool(r.verified) or (r.verified is None and r.relation is not None) for r in out.values())
    done = stats.steps.get(step, {"pairs": 0, "verified": 0, "seconds": 0.0})  # a step may run in rounds
    stats.steps[step] = {
        "pairs": done["pairs"] + len(keys),
        "verified": done["verified"] + verified,
        "seconds": round(done["seconds"] + time.perf_counter() - t0, 2),
    }
    return out


def _apply_some(indices: list, results: dict, todo, sets, output, stats: MatchStats, flush_s: float) -> None:
    """:func:`_apply_in_order` of the pairs ``indices`` of ``todo`` with their ``results``."""
    _apply_in_order(
        ((k, results[i]) for k, i in enumerate(indices)), [todo[i] for i in indices], sets, output, stats, flush_s
    )


def _graph_hypotheses(graph: PairGraph, a: str, b: str, first, seed, tried: list, same_log2: float) -> list:
    """The hypotheses of an open pair not tried yet (windows left out): the seed's, its own
    geometry's, then the graph's that turn or zoom by :data:`COMPOSED_MIN_LOG2` octaves or more."""
    from ..matching import Hypothesis

    relations = [] if seed is None or seed.relation is None else [seed.relation]
    relations += [first.relation] if first.verified else []
    relations += [
        r
        for r in graph.composed(a, b, same_log2=same_log2)
        if r.turn % 4 or abs(math.log2(r.scale)) >= COMPOSED_MIN_LOG2 - 1e-9
    ]
    candidates = []
    for r in relations:
        if r is None:
            continue
        scale = r.scale
        if abs(math.log2(scale)) >= 1:  # a strong zoom: half an octave less (the close-up keeps detail)
            scale *= 2.0 ** (0.5 if scale < 1 else -0.5)
        candidates.append(Hypothesis(scale, r.turn, "collection"))
    out: list = []
    for h in candidates:
        r = Relation(h.scale, h.turn % 4)
        if r.is_identity(same_log2):
            continue  # step 1 tried the images as they are
        if any(Relation(t.scale, t.turn % 4).same_as(r, same_log2) for t in tried + out):
            continue
        out.append(h)
    return out


def _index_matches(sets: dict, a: str, b: str, kp_a, kp_b, m, scores):
    """The matches ``m`` of keypoints ``kp_a``, ``kp_b`` (full-image pixels) as ``(K x 2 indices into the
    keypoint sets of A and B (new points added to them), one match per keypoint; K scores)``."""
    ia = sets[a].index(kp_a[m[:, 0]]) if len(m) else np.zeros(0, np.int64)
    ib = sets[b].index(kp_b[m[:, 1]]) if len(m) else np.zeros(0, np.int64)
    return one_to_one(ia, ib, scores[: len(m)]) if len(m) else (np.zeros((0, 2), np.int64), np.zeros(0, np.float32))


class _MatchOutput:
    """``matches.h5`` and ``keypoints.h5`` being written: the matches of each pair added, and the
    keypoint sets of the images they touched, flushed together (keypoints first)."""

    def __init__(self, matches_path, keypoints_path, sets: dict, by_name: dict, fresh: bool):
        self.matches_path, self.keypoints_path = matches_path, keypoints_path
        self.sets, self.by_name = sets, by_name
        self.m_writer = H5Writer(matches_path, fresh=fresh)
        self.k_writer = H5Writer(keypoints_path, fresh=fresh)
        self.changed = set(by_name) if (fresh or not Path(keypoints_path).exists()) else set()

    def add(self, a: str, b: str, mm, ss, verified, chosen: str, seconds: float, relation=None) -> PairRecord:
        """Add the matches ``mm`` (scores ``ss``) of a pair matched in ``seconds``; returns its record."""
        self.changed.update((a, b))
        m0, s0 = matches0_from_matches(mm, ss, len(self.sets[a]))
        rec = PairRecord(a, b, int(len(mm)), verified, chosen, seconds, relation)
        attrs = {
            "num_matches": rec.num_matches,
            "chosen": chosen,
            "seconds": rec.seconds,
            "name0": a,
            "name1": b,
        }
        if verified is not None:
            attrs["verified"] = bool(verified)
        if relation is not None:
            attrs["relation"] = np.array([relation.scale, relation.turn, relation.strength], np.float64)
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
        v, rel = at.get("verified"), at.get("relation")
        out[key] = PairRecord(
            a,
            b,
            int(np.sum(g["matches0"] >= 0)),
            None if v is None else bool(v),
            str(at.get("chosen", "")),
            float(at.get("seconds", 0.0)),
            None if rel is None else Relation(float(rel[0]), int(rel[1]), int(rel[2])),
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
