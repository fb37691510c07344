"""The pair graph of ``auto`` on a collection: relations compose along verified pairs."""

import itertools
import math

import pytest

from localscale.matching.auto.graph import PairGraph, Relation


def test_relations_compose_and_invert():
    close_to_photo = Relation(0.25, 1, 80)  # the photo shows the close-up's content 4x smaller, turned
    photo_to_other = Relation(1.2, 0, 300)
    r = close_to_photo.then(photo_to_other)
    assert r.scale == pytest.approx(0.3) and r.turn == 1 and r.strength == 80
    back = r.inverse()
    assert back.scale == pytest.approx(1 / 0.3) and back.turn == 3
    loop = r.then(back)
    assert loop.is_identity(0.01)
    assert Relation(1.1, 0).is_identity(0.25) and not Relation(1.1, 2).is_identity(0.25)
    assert not Relation(1.5, 0).is_identity(0.25)


def test_graph_composes_through_common_neighbours_strongest_first():
    g = PairGraph()
    g.add("close", "p1", Relation(0.25, 2, 80))
    g.add("p1", "p2", Relation(1.1, 0, 300))
    g.add("p2", "close", Relation(3.7, 2, 40))  # stored the other way round: close -> p2 is 1/3.7, turn 2
    g.add("p3", "p2", Relation(1.0, 0, 200))
    assert g.relation("close", "p2").scale == pytest.approx(1 / 3.7) and g.relation("close", "p2").turn == 2
    # close -> p3: via p2 only (p1 and p3 are not joined)
    via = g.composed("close", "p3")
    assert len(via) == 1 and via[0].turn == 2 and via[0].scale == pytest.approx(1 / 3.7)
    # close -> p2 through p1: 0.25 * 1.1, strength 80
    via = g.composed("close", "p2")
    assert via[0].scale == pytest.approx(0.275) and via[0].strength == 80
    assert g.connected("close", "p3") and not g.connected("close", "p4")


def test_graph_keeps_the_strongest_edge_and_ignores_bad_scales():
    g = PairGraph()
    g.add("a", "b", Relation(2.0, 0, 30))
    g.add("b", "a", Relation(0.4, 0, 90))  # stronger: replaces, seen from a as 2.5
    assert g.relation("a", "b").scale == pytest.approx(2.5) and len(g) == 1
    g.add("a", "b", Relation(9.0, 0, 10))  # weaker: ignored
    assert g.relation("a", "b").scale == pytest.approx(2.5)
    g.add("a", "c", Relation(math.nan, 0, 100))
    g.add("a", "d", Relation(0.0, 0, 100))
    assert g.relation("a", "c") is None and g.relation("a", "d") is None and not g.connected("a", "c")


def test_composed_hypotheses_are_distinct():
    g = PairGraph()
    for x, s in (("x1", 2.0), ("x2", 2.1), ("x3", 4.0)):
        g.add("a", x, Relation(s, 0, 100))
        g.add(x, "b", Relation(1.0, 0, 100))
    found = g.composed("a", "b", same_log2=0.25)
    assert sorted(round(r.scale, 1) for r in found) == [2.0, 4.0]  # 2.0 and 2.1 are one


def test_auto_on_a_collection_tries_the_graphs_hypotheses_before_the_networks(tmp_path):
    """The driver's steps with a scripted pair runner: close-up c verifies with p1 by the seed; c-p2
    gets the composed relation c -> p1 -> p2 and no network; p3 overlaps nothing, so only its pairs,
    which the graph cannot join, run the networks."""
    pytest.importorskip("h5py")
    from types import SimpleNamespace

    import numpy as np

    from localscale.matching import Hypothesis
    from localscale.matching.auto.collection import match_with_graph
    from localscale.sfm import match as M
    from localscale.sfm.keypoints import KeypointSet
    from localscale.sfm.pair_runner import PairResult

    names = ["c", "p1", "p2", "p3"]
    todo = [(a, b) for i, a in enumerate(names) for b in names[i + 1 :]]
    kp = np.array([[1.0, 1.0], [5.0, 5.0]], np.float32)
    calls = []

    def result(verified, relation=None, hypothesis=None, final=False):
        m = np.array([[0, 0], [1, 1]], np.int64)
        return PairResult(kp, kp, m, np.ones(2, np.float32), verified, "scripted", relation, hypothesis, final)

    def run_items(items, label):
        for k, (a, b, step, *args) in enumerate(items):
            calls.append((a, b, step, *args))
            if step == "as_they_are":
                r = result(True, Relation(1.05, 0, 200), final=True) if (a, b) == ("p1", "p2") else result(False)
            elif step == "seed":
                seed_h = Hypothesis(0.25, 1, "sift geometry", window=(1, 0, 0, 4, 4))
                r = result(None, Relation(0.25, 1, 50), seed_h) if (a, b) == ("c", "p1") else result(None)
            else:  # "hypotheses" (the auto loop: hypotheses, networks) or "levels" (hypotheses)
                hyps = args[0]
                ok = b != "p3" and any(h.turn == 1 and abs(math.log2(h.scale / 0.26)) < 0.6 for h in hyps)
                ok = ok or (b != "p3" and any(h.window is not None for h in hyps))
                r = result(True, Relation(0.26, 1, 60)) if ok else result(False)
            yield k, r

    sets = {n: KeypointSet(np.zeros((0, 2), np.float32)) for n in names}
    by_name = {n: SimpleNamespace(shape=(10, 10, 3)) for n in names}
    output = M._MatchOutput(tmp_path / "m.h5", tmp_path / "k.h5", sets, by_name, fresh=True)
    stats = M.MatchStats()

    def apply(results, pairs):
        M.apply_in_order(results, pairs, sets, output, stats, 1e9)

    match_with_graph(run_items, todo, apply, stats, same_log2=0.25)

    steps = {}
    for a, b, step, *args in calls:
        steps.setdefault((a, b), []).append((step, *args))
    assert steps[("p1", "p2")] == [("as_they_are",)]  # verified as it is: nothing else
    # c-p2: the composed relation at the images' levels, no network
    assert [s[0] for s in steps[("c", "p2")]] == ["as_they_are", "seed", "levels"]
    hyps = steps[("c", "p2")][-1][1]
    assert all(h.turn == 1 for h in hyps)
    # one hypothesis: a strong zoom half an octave less (the close-up keeps detail)
    assert [h.scale for h in hyps] == pytest.approx([0.26 * 1.05 * 2**0.5])  # c -> p1 (the anchor) -> p2
    for pair in (("c", "p3"), ("p1", "p3"), ("p2", "p3")):  # p3 is joined to nothing: the networks
        assert ("hypotheses", [], True) in steps[pair]
    # the anchor: the seed's geometry in its window, alone
    assert steps[("c", "p1")] == [("as_they_are",), ("seed",), ("hypotheses", [steps[("c", "p1")][-1][1][0]], False)]
    assert steps[("c", "p1")][-1][1][0].window is not None
    assert list(stats.steps) == ["as they are", "seed", "anchors", "graph", "graph, more"]
    record = {(r.a, r.b): r for r in stats.pairs}
    assert sorted(record) == sorted(todo)  # every pair written once
    assert record[("c", "p2")].verified and record[("c", "p2")].relation.turn == 1
    assert record[("c", "p1")].verified and not record[("c", "p3")].verified


def test_clear_pairs_fix_the_quarter_turns_that_hypotheses_must_keep():
    from localscale.matching.auto.collection import _quarter_turns, _turn_fits

    # a ring of upright views (a-b-c-d), and e, f: f is e turned by a quarter turn, joined to nothing else
    turns = _quarter_turns([("a", "b", 0), ("b", "c", 0), ("c", "d", 0), ("e", "f", 1)])
    assert turns["a"] == turns["d"] == ("a", 0) and turns["f"] == ("e", 3)
    assert _turn_fits(turns, "a", "d", 0) and not _turn_fits(turns, "a", "d", 2)  # opposite views: no half turn
    assert _turn_fits(turns, "e", "f", 1) and _turn_fits(turns, "f", "e", 3) and not _turn_fits(turns, "e", "f", 0)
    assert _turn_fits(turns, "a", "e", 2) and _turn_fits(turns, "a", "zoom", 3)  # not joined: anything goes


def test_mild_composed_zooms_are_not_tried_again():
    """Step 1 matched the pair as it is: a composed zoom under an octave with no turn adds nothing
    (around a ring of views the composed scales drift), a turned or strong one is tried."""
    from types import SimpleNamespace

    from localscale.matching.auto.collection import _graph_hypotheses

    g = PairGraph()
    g.add("a", "m", Relation(1.3, 0, 100))
    g.add("m", "b", Relation(1.2, 0, 100))  # a -> b: x1.56, upright
    g.add("a", "n", Relation(1.0, 1, 100))
    g.add("n", "c", Relation(1.2, 0, 100))  # a -> c: x1.2, a quarter turn
    g.add("a", "p", Relation(3.0, 0, 100))
    g.add("p", "d", Relation(1.1, 0, 100))  # a -> d: x3.3
    unverified = SimpleNamespace(verified=False, relation=None)
    assert _graph_hypotheses(g, "a", "b", unverified, None, [], 0.25) == []
    (turned,) = _graph_hypotheses(g, "a", "c", unverified, None, [], 0.25)
    assert turned.turn == 1 and turned.scale == pytest.approx(1.2)
    (zoom,) = _graph_hypotheses(g, "a", "d", unverified, None, [], 0.25)
    assert zoom.turn == 0 and zoom.scale == pytest.approx(3.3 / 2**0.5)  # half an octave less


def test_graph_pairs_run_in_rounds_charged_to_the_image_they_would_join():
    """Each image first tries its best supported pairs; an image gets its next best pairs only when
    one of its pairs of the round before verified (hypotheses that keep failing for a close-up are
    not tried further)."""
    from localscale.matching.auto.collection import GRAPH_PAIRS_PER_IMAGE, _first_round, _next_round

    g = PairGraph()
    photos = [f"p{k}" for k in range(1, 11)]
    for x, y in itertools.combinations(photos, 2):
        g.add(x, y, Relation(1.0, 0, 100))
    g.add("c", "p1", Relation(0.25, 1, 80))
    g.add("d", "p1", Relation(0.3, 2, 60))
    levels, support = {}, {}
    for k, (close, photo) in enumerate(itertools.product(("c", "d"), photos[1:])):
        levels[k] = (close, photo, "levels", [])
        support[k] = 100 - k  # the lower the index, the better supported
    first, rest, charged = _first_round(levels, support, g)
    assert {charged[i] for i in levels} == {"c", "d"}  # the close-ups, joined to one photo each
    assert sorted(i for i in first if charged[i] == "c") == [0, 1, 2]
    assert sorted(i for i in first if charged[i] == "d") == [9, 10, 11]
    assert len(first) == 2 * GRAPH_PAIRS_PER_IMAGE and set(first) | set(rest) == set(levels)
    # c's first-round pair 1 verified (it left the open pairs), none of d's did: c's next best three
    second, rest2 = _next_round(first, rest, charged, set(levels) - {1})
    assert sorted(second) == [3, 4, 5] and all(second[i] == levels[i] for i in second)
    assert set(second) | set(rest2) == set(rest) and not set(second) & set(rest2)
    # pair 4 of that round verified: the next three; none did: no third round
    third, _ = _next_round(second, rest2, charged, set(levels) - {1, 4})
    assert sorted(third) == [6, 7, 8]
    assert _next_round(second, rest2, charged, set(levels) - {1})[0] == {}
    # a pair that verified but was charged to another image does not open c's rest
    assert _next_round(first, rest, {**charged, 1: "p3"}, set(levels) - {1})[0] == {}
