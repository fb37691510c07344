"""``auto`` on a collection: the steps that drive the matching of a collection's pairs over the pair
graph (:func:`match_with_graph`). The caller runs the pairs (``run_items``: e.g.
:class:`~localscale.sfm.pair_runner.PairRunner` in this process or on an executor's workers) and
keeps what each step settles (``apply``: e.g. :func:`localscale.sfm.match.match_pairs` writes it)."""

from __future__ import annotations

import math
import time

from .graph import PairGraph, Relation

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


def match_with_graph(run_items, todo, apply, stats, same_log2: float, turn_inliers: int = TURN_INLIERS) -> None:
    """``auto`` on a collection, in steps that each run on the pairs still open: ``run_items(items,
    label)`` yields ``(index into items, PairResult or Exception)``; ``apply(results, pairs)`` keeps the
    ``(k, PairResult)`` of ``results`` of the pairs ``pairs`` (``(a, b)`` of ``todo``) that a step settles,
    in pair order; ``stats`` (:class:`~localscale.sfm.match.MatchStats`) holds the relations of a
    resumed run's pairs (``stats.pairs``) and gets each step's counts (``stats.steps``). The steps:

    1. every pair as it is (the stored features, two-view verification): settled when it verifies
       clearly or with no scale change or turn to try;
    2. the seed's (SIFT) geometry of each open pair; where it does not verify (or gives a strong
       zoom no window), the similarity its matches' keypoints agree on
       (:meth:`~localscale.sfm.pair_runner.PairRunner.seed`);
    3. anchors: the seed's hypothesis matched in the window of the wide view that the close-up shows
       (:attr:`~localscale.matching.AutoConfig.window_share`), on at most
       :data:`ANCHOR_PAIRS_PER_IMAGE` pairs per image, the best supported first;
    4. the verified pairs (steps 1 to 3, and a resumed run's) make a :class:`~.graph.PairGraph`;
       each open pair tries :data:`LEVEL_HYPOTHESES` of: the seed's scale and turn, its own
       geometry's, and those composed through a common neighbour that turn or zoom by
       :data:`COMPOSED_MIN_LOG2` octaves or more (a strong zoom half an octave less: the close-up
       keeps detail), at the images' levels
       (:meth:`~localscale.sfm.pair_runner.PairRunner.levels`: each image extracted once per level and turn
       whatever its pairs); a pair with none whose images the graph does not join runs the
       networks (on at most :data:`NETWORK_PAIRS_PER_IMAGE` pairs per image, those with the most
       matches first). The hypotheses run in rounds (:func:`_first_round`, :func:`_next_round`): each
       image's :data:`GRAPH_PAIRS_PER_IMAGE` best supported pairs, then, for each image that one
       of its pairs of the round before joined, its next :data:`GRAPH_PAIRS_PER_IMAGE`.

    The pairs of step 1 with at least ``turn_inliers`` inliers, then those of step 3, fix the
    images' quarter turns (:func:`_quarter_turns`); a hypothesis or seed geometry that turns two
    images these pairs join otherwise is dropped (a symmetric object seen from opposite sides
    verifies turned). A pair that nothing verified keeps its step-1 matches."""
    run = _GraphRun(run_items, todo, apply, stats)
    open_, clear = run.as_they_are(turn_inliers)
    seeds = run.seeds(open_, _quarter_turns(clear))
    anchors = _anchors(open_, seeds, todo)
    open_ = run.settle(anchors, "anchors", open_)
    clear += [
        (*todo[i], run.best[i].relation.turn)
        for i in anchors
        if run.best[i].verified and run.best[i].relation.strength >= turn_inliers
    ]
    open_ = run.graph_step(open_, seeds, _quarter_turns(clear), same_log2)
    run.apply(sorted(open_), run.best)


class _GraphRun:
    """The state of :func:`match_with_graph`: the pairs ``todo``, their best results so far
    (:attr:`best`), the hypotheses each open pair tried (:attr:`tried`) and the pair graph of the
    verified pairs (:attr:`graph`, a resumed run's relations included); what is settled goes to
    ``apply`` and ``stats``."""

    def __init__(self, run_items, todo, apply, stats):
        self.run_items, self.todo, self.keep, self.stats = run_items, todo, apply, stats
        self.graph = PairGraph()
        for rec in stats.pairs:
            if rec.relation is not None:
                self.graph.add(rec.a, rec.b, rec.relation)
        self.best: dict = {}
        self.tried: dict = {}

    def as_they_are(self, turn_inliers: int) -> tuple:
        """Step 1: ``(the pairs left open, the clear pairs (a, b, turn) that fix the quarter turns)``."""
        todo, every = self.todo, list(range(len(self.todo)))
        best = self.best = _run_some(
            self.run_items, {i: (*todo[i], "as_they_are") for i in every}, "as they are", self.stats
        )
        for i in every:
            if best[i].verified and best[i].relation is not None:
                self.graph.add(*todo[i], best[i].relation)
        self.apply([i for i in every if best[i].final], best)
        clear = [
            (*todo[i], best[i].relation.turn)
            for i in every
            if best[i].final and best[i].relation.strength >= turn_inliers
        ]
        open_ = [i for i in every if not best[i].final]
        self.tried = {i: [] for i in open_}
        return open_, clear

    def seeds(self, open_: list, turns: dict) -> dict:
        """Step 2: the seed's geometry of the open pairs (a turn that ``turns`` contradict is dropped)."""
        seeds = _run_some(self.run_items, {i: (*self.todo[i], "seed") for i in open_}, "seed", self.stats)
        for i, r in seeds.items():
            self.stats.feature_sets += r.computed
            h = r.relation if r.relation is not None else r.hypothesis
            if h is not None and not _turn_fits(turns, *self.todo[i], h.turn % 4):
                r.relation = r.hypothesis = None
            if r.relation is not None:
                self.graph.add(*self.todo[i], r.relation)
        return seeds

    def graph_step(self, open_: list, seeds: dict, turns: dict, same_log2: float) -> list:
        """Step 4: the hypotheses of the graph in rounds, the networks where it joins nothing; returns the pairs left open."""
        items, levels, quota = {}, {}, {}
        best, graph = self.best, self.graph
        for i in sorted(open_, key=lambda i: (-len(best[i].matches), i)):
            a, b = self.todo[i]
            hyps = _graph_hypotheses(graph, a, b, best[i], seeds.get(i), self.tried[i], same_log2)
            hyps = [h for h in hyps if _turn_fits(turns, a, b, h.turn)][:LEVEL_HYPOTHESES]
            if hyps:
                levels[i] = (a, b, "levels", hyps)
            elif not graph.connected(a, b) and max(quota.get(a, 0), quota.get(b, 0)) < NETWORK_PAIRS_PER_IMAGE:
                quota[a], quota[b] = quota.get(a, 0) + 1, quota.get(b, 0) + 1
                items[i] = (a, b, "hypotheses", [], True)
        support = {i: _support(graph, *self.todo[i], seeds.get(i), same_log2) for i in levels}
        first, rest, charged = _first_round(levels, support, graph)
        open_ = self.settle({**items, **first}, "graph", open_)
        done_round = first
        while True:
            more, rest = _next_round(done_round, rest, charged, set(open_))
            open_ = self.settle(more, "graph, more", open_)
            if not more:
                return open_
            done_round = more

    def settle(self, items: dict, step: str, open_: list) -> list:
        """Runs the ``items`` of the step ``step``; the pairs that verify get their result in
        :attr:`best` and their relation in :attr:`graph`, and are applied; returns the pairs still open."""
        found = _run_some(self.run_items, items, step, self.stats)
        settled = []
        for i, r in found.items():
            self.tried[i] += items[i][3]
            if r.verified:
                self.best[i] = r
                settled.append(i)
                self.graph.add(*self.todo[i], r.relation)
        self.apply(sorted(settled), self.best)
        done = set(settled)
        return [i for i in open_ if i not in done]

    def apply(self, indices: list, results: dict) -> None:
        """The caller's ``apply`` of the pairs ``indices`` of ``todo`` with their ``results``."""
        self.keep(((k, results[i]) for k, i in enumerate(indices)), [self.todo[i] for i in indices])


def _anchors(open_: list, seeds: dict, todo) -> dict:
    """Step 3's items: the seed's hypothesis in its window, on at most :data:`ANCHOR_PAIRS_PER_IMAGE`
    pairs per image, the best supported first."""
    anchors, count = {}, {}
    for i in sorted((i for i in open_ if seeds[i].hypothesis is not None), key=lambda i: (-seeds[i].support, i)):
        a, b = todo[i]
        if seeds[i].hypothesis.window is not None and max(count.get(a, 0), count.get(b, 0)) < ANCHOR_PAIRS_PER_IMAGE:
            count[a], count[b] = count.get(a, 0) + 1, count.get(b, 0) + 1
            anchors[i] = (a, b, "hypotheses", [seeds[i].hypothesis], False)
    return anchors


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


def _run_some(run_items, items: dict, step: str, stats) -> dict:
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


def _graph_hypotheses(graph: PairGraph, a: str, b: str, first, seed, tried: list, same_log2: float) -> list:
    """The hypotheses of an open pair not tried yet (windows left out): the seed's, its own
    geometry's, then the graph's that turn or zoom by :data:`COMPOSED_MIN_LOG2` octaves or more."""
    from .hypotheses import Hypothesis

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
