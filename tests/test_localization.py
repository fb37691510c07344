"""locate_window: the part of the wide view a zoomed view shows, voted by matches that did not verify."""

import numpy as np
import pytest

from localscale.core.errors import LocalScaleError
from localscale.geometry import turn_matrix
from localscale.matching.auto import AutoConfig
from localscale.matching.auto.localization import locate_turn, locate_window

SHAPE = (600, 800)  # (H, W) of both images


def _zoomed_matches(rng, zoom, turn, centre, n_true=12, n_false=60):
    """Matches of a wide view A and a zoomed view B (``zoom`` times bigger around ``centre`` of A,
    then turned): ``n_true`` correct ones among ``n_false`` random ones, in the pixels of A and B."""
    h, w = SHAPE
    # B before its turn: x_B = zoom (x_A - centre) + (w / 2, h / 2)
    pa_true = centre + (rng.random((n_true, 2)) - 0.5) * np.array([w, h]) / zoom * 0.9
    pb_true = zoom * (pa_true - centre) + np.array([(w - 1) / 2, (h - 1) / 2])
    # B as given is the turned image: its points are the turned ones
    T = turn_matrix(turn, SHAPE)
    pb_true = pb_true @ T[:2, :2].T + T[:2, 2]
    shape_b = (w, h) if turn % 2 else SHAPE
    pa_false = rng.random((n_false, 2)) * np.array([w, h])
    pb_false = rng.random((n_false, 2)) * np.array([shape_b[1], shape_b[0]])
    return np.vstack([pa_true, pa_false]), np.vstack([pb_true, pb_false]), shape_b


@pytest.mark.parametrize("turn", [0, 1, 2, 3])
def test_the_window_of_the_wide_view_holds_what_the_zoomed_view_shows(rng, turn):
    zoom, centre = 4.0, np.array([520.0, 180.0])
    pa, pb, shape_b = _zoomed_matches(rng, zoom, turn, centre)
    # the hypothesis names the turn that undoes B's: B turned back by (4 - turn)
    window, votes = locate_window(pa, pb, zoom * 0.85, (4 - turn) % 4, SHAPE, shape_b)
    assert window[0] == 0 and votes >= 10
    _, x0, y0, x1, y1 = window
    assert x0 < centre[0] < x1 and y0 < centre[1] < y1
    # what B shows (800 / 4 x 600 / 4 around the centre) lies inside
    assert x0 <= centre[0] - 100 and x1 >= centre[0] + 100 and y0 <= centre[1] - 75 and y1 >= centre[1] + 75
    assert (x1 - x0) * (y1 - y0) < 0.2 * SHAPE[0] * SHAPE[1]


@pytest.mark.parametrize("turn", [1, 2])
def test_when_a_is_the_zoomed_view_the_window_is_in_b_as_given(rng, turn):
    zoom, centre = 3.0, np.array([250.0, 400.0])
    pa, pb, shape_b = _zoomed_matches(rng, zoom, turn, centre)
    # A and B swapped: A is the zoomed view (turned by `turn`), S_{A->B} = 1 / zoom, and B, the
    # wide view, lines up with A once turned by `turn` as well
    window, votes = locate_window(pb, pa, 1 / zoom, turn, shape_b, SHAPE)
    assert window[0] == 1 and votes >= 10
    _, x0, y0, x1, y1 = window
    assert x0 < centre[0] < x1 and y0 < centre[1] < y1, (window, centre)
    assert x1 <= SHAPE[1] and y1 <= SHAPE[0]
    assert (x1 - x0) * (y1 - y0) < 0.3 * SHAPE[0] * SHAPE[1]


def test_random_matches_locate_nothing(rng):
    pa = rng.random((200, 2)) * [800, 600]
    pb = rng.random((200, 2)) * [800, 600]
    assert locate_window(pa, pb, 4.0, 0, SHAPE, SHAPE) is None
    assert locate_window(pa[:3], pb[:3], 4.0, 0, SHAPE, SHAPE) is None  # too few to vote


def test_a_window_too_large_to_help_is_none(rng):
    pa, pb, shape_b = _zoomed_matches(rng, 1.2, 0, np.array([400.0, 300.0]))
    assert locate_window(pa, pb, 1.2, 0, SHAPE, shape_b) is None


def test_a_bad_vote_count_is_refused():
    with pytest.raises(LocalScaleError, match="locate_votes"):
        AutoConfig(locate_votes=2).check()


@pytest.mark.parametrize("locate", [True, False])
def test_auto_matches_again_where_the_matches_of_a_failed_zoom_agree(rng, monkeypatch, locate):
    """The loop's wiring, with a stand-in matcher: shrunk, the zoomed view gives a dozen correct
    matches among many wrong ones (no verification); in the located window it gives many."""
    from localscale.matching import auto
    from localscale.matching.auto import trial
    from localscale.matching.matcher import Matches
    from localscale.matching.verification import VerificationConfig

    zoom, turn, centre = 4.0, 1, np.array([560.0, 170.0])
    a = np.zeros(SHAPE + (3,), np.uint8)
    b = np.zeros((SHAPE[1], SHAPE[0], 3), np.uint8)  # B as given is turned

    def stand_in_run(matcher, a_, b_, h, keys, vconf, cameras=(None, None), window_max_side=None):
        n_true, n_false = (80, 5) if h.window is not None else (12, 40)
        pa, pb, _ = _zoomed_matches(rng, zoom, turn, centre, n_true, n_false)
        idx = np.arange(len(pa))
        found = Matches(pa.astype(np.float32), pb.astype(np.float32), np.stack([idx, idx], 1), np.zeros(len(pa)))
        return found, trial.verify_found(found, a_, b_, vconf, cameras)

    monkeypatch.setattr(trial, "run_hypothesis", stand_in_run)
    config = AutoConfig(budget=2, seed=None, locate=locate)
    h = auto.Hypothesis(zoom * 0.9, (4 - turn) % 4, "test")
    res = auto.try_hypotheses(
        None, a, b, config=config, verification=VerificationConfig(), hypotheses=[h], networks=False
    )
    sources = [t.hypothesis.source for t in res.trials]
    if not locate:
        assert sources == ["test"] and not res.verified
        return
    assert sources[:2] == ["test", "test, located"] and len(sources) <= 3, sources
    assert res.verified and res.chosen.window is not None and res.chosen.window[0] == 0
    _, x0, y0, x1, y1 = res.chosen.window
    assert x0 < centre[0] < x1 and y0 < centre[1] < y1


def test_the_turn_the_matches_agree_on_is_found_and_an_unclear_one_is_not(rng):
    zoom, turn, centre = 3.0, 3, np.array([300.0, 250.0])
    pa, pb, shape_b = _zoomed_matches(rng, zoom, turn, centre, n_true=15, n_false=40)
    found = locate_turn(pa, pb, zoom * 1.2, SHAPE, shape_b)
    assert found is not None
    k, window, votes = found
    assert k == (4 - turn) % 4 and votes >= 12
    assert window[0] == 0 and window[1] < centre[0] < window[3] and window[2] < centre[1] < window[4]
    # the same matches plus as many agreeing under another turn: no clear turn
    pa2, pb2, _ = _zoomed_matches(rng, zoom, 1, np.array([600.0, 400.0]), n_true=15, n_false=0)
    assert locate_turn(np.vstack([pa, pa2]), np.vstack([pb, pb2]), zoom, SHAPE, shape_b) is None


def test_a_bad_zoom_coverage_is_refused():
    with pytest.raises(LocalScaleError, match="zoom_min_coverage"):
        AutoConfig(zoom_min_coverage=1.5).check()


def test_strong_zooms_are_verified_with_their_own_coverage():
    from localscale.matching.auto import Hypothesis
    from localscale.matching.auto.loop import _Loop
    from localscale.matching.verification import VerificationConfig

    config = AutoConfig(zoom_min_coverage=0.02, zoom_min_log2=1.0)
    loop = _Loop(None, None, None, config, (None, None), (None, None), VerificationConfig(min_coverage=0.05))
    assert loop.vconf_for(Hypothesis(4.0, 1, "ScaleNet")).min_coverage == 0.02
    assert loop.vconf_for(Hypothesis(0.3, 0, "ScaleNet")).min_coverage == 0.02
    assert loop.vconf_for(Hypothesis(1.5, 0, "ScaleNet")).min_coverage == 0.05
    assert loop.vconf_for(loop.identity).min_coverage == 0.05


@pytest.mark.parametrize("window_max_side, side", [(None, 800), (640, 640)])
def test_a_window_is_enlarged_up_to_window_max_side(rng, window_max_side, side):
    """A close-up (A) of 8x the content of a 100-px window of B: the window is enlarged to the
    matcher's max_side (1024: 8x gives 800 px) or to window_max_side, and the close-up shrunk for
    the rest of the zoom."""
    from localscale.matching import auto
    from localscale.matching.auto import trial
    from localscale.matching.config import match_config
    from localscale.matching.matcher import Matcher
    from localscale.matching.verification import VerificationConfig

    matcher = Matcher(match_config("sift", max_side=1024), cache_size=0)
    factors = {}
    extract = matcher.extract

    def recorded(image, scale=None, key=None):
        factors[image.shape[:2]] = scale
        return extract(image, scale, key)

    matcher.extract = recorded
    a = rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)
    b = rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)
    window = (1, 200, 150, 300, 225)  # 100 x 75 px of B
    h = auto.Hypothesis(0.125, 0, "test", window=window)
    trial.run_hypothesis(matcher, a, b, h, (None, None), VerificationConfig(), max_side=window_max_side)
    f_window, f_close = factors[(75, 100)], factors[(480, 640)]
    assert f_window * 100 == pytest.approx(side)
    assert f_close == pytest.approx(0.125 * f_window)  # the pair still brought to one scale


@pytest.mark.parametrize("bad", [0, -5, 1.5, True])
def test_a_bad_window_max_side_is_refused(bad):
    with pytest.raises(LocalScaleError, match="window_max_side"):
        AutoConfig(window_max_side=bad).check()


def _close_up(photo, box, zoom, turn):
    """B: ``box`` (x0, y0, x1, y1) of ``photo`` enlarged ``zoom`` times, then turned ``turn`` quarter turns."""
    import cv2

    x0, y0, x1, y1 = box
    crop = photo[y0:y1, x0:x1]
    big = cv2.resize(crop, (round((x1 - x0) * zoom), round((y1 - y0) * zoom)), interpolation=cv2.INTER_CUBIC)
    return np.ascontiguousarray(np.rot90(big, turn))


@pytest.mark.parametrize("turn", [0, 1, 3])
def test_sift_frames_give_the_scale_turn_and_window_of_a_close_up(photos, turn):
    """OpenCV SIFT matches of a photo and a 3x close-up of part of it, turned: the similarity their
    keypoints' sizes and orientations agree on gives the zoom, the turn that undoes B's, and a
    window of A around the part B shows."""
    from localscale.matching.auto import mapping_hypothesis
    from localscale.matching.auto.localization import locate_similarity
    from localscale.matching.matcher import Matcher

    a = np.ascontiguousarray(photos["astronaut"])  # 512 x 512
    box, zoom = (200, 60, 360, 220), 3.0
    b = _close_up(a, box, zoom, turn)
    found = Matcher("sift").match(a, b)
    assert found.frames_a is not None and found.frames_a.shape == (len(found.keypoints_a), 2)
    m = found.matches
    pa, pb = found.keypoints_a[m[:, 0]], found.keypoints_b[m[:, 1]]
    located = locate_similarity(pa, pb, found.frames_a[m[:, 0]], found.frames_b[m[:, 1]], a.shape[:2], b.shape[:2])
    assert located is not None
    M, votes, inliers = located
    assert votes >= 20 and inliers.sum() == votes
    scale = float(np.sqrt(np.linalg.det(M[:2, :2])))
    assert scale == pytest.approx(zoom, rel=0.1)
    h = mapping_hypothesis(M, scale, pa[inliers], a.shape[:2], b.shape[:2], "test")
    assert h.turn == (4 - turn) % 4
    assert h.window is not None and h.window[0] == 0
    _, x0, y0, x1, y1 = h.window
    assert x0 <= box[0] + 10 and y0 <= box[1] + 10 and x1 >= box[2] - 10 and y1 >= box[3] - 10
    assert (x1 - x0) * (y1 - y0) < 0.4 * a.shape[0] * a.shape[1]


def test_random_frames_locate_no_similarity(rng):
    from localscale.matching.auto.localization import locate_similarity

    pa, pb = rng.random((300, 2)) * [800, 600], rng.random((300, 2)) * [800, 600]
    frames_a = np.stack([rng.uniform(2, 40, 300), rng.uniform(0, 360, 300)], 1)
    frames_b = np.stack([rng.uniform(2, 40, 300), rng.uniform(0, 360, 300)], 1)
    assert locate_similarity(pa, pb, frames_a, frames_b, SHAPE, SHAPE) is None
    assert locate_similarity(pa, pb, None, None, SHAPE, SHAPE) is None  # a detector without frames


def test_an_unverified_seed_proposes_the_similarity_of_its_keypoints_first(photos, monkeypatch):
    """The loop's wiring, with a stand-in matcher that finds nothing: the SIFT seed's real matches
    are taken as unverified, and the similarity of their keypoints is the first hypothesis the
    matcher runs after it, with the zoom, the turn and a window of A."""
    import dataclasses
    from types import SimpleNamespace

    from localscale.matching import auto
    from localscale.matching.auto import trial
    from localscale.matching.matcher import Matcher, Matches
    from localscale.matching.verification import VerificationConfig

    a = np.ascontiguousarray(photos["astronaut"])
    b = _close_up(a, (200, 60, 360, 220), 3.0, 1)
    seed, real_run = Matcher("sift"), trial.run_hypothesis

    def stand_in_run(matcher, a_, b_, h, keys, vconf, cameras=(None, None), window_max_side=None):
        if matcher is seed:
            found, v = real_run(matcher, a_, b_, h, keys, vconf, cameras)
            return found, dataclasses.replace(v, verified=False)
        none = np.zeros((0, 2), np.float32)
        found = Matches(none, none, np.zeros((0, 2), np.int64), np.zeros(0))
        return found, trial.verify_found(found, a_, b_, vconf, cameras)

    monkeypatch.setattr(trial, "run_hypothesis", stand_in_run)
    matcher = SimpleNamespace(config=SimpleNamespace(name="stand-in"))
    config = AutoConfig(budget=2, turns=False)
    res = auto.try_hypotheses(
        matcher, a, b, config=config, seed_matcher=seed, verification=VerificationConfig(), networks=False
    )
    assert [t.hypothesis.source for t in res.trials] == ["identity", "seed (sift)", "seed similarity"]
    h = res.trials[2].hypothesis
    assert h.scale == pytest.approx(3.0, rel=0.1) and h.turn == 3 and h.window is not None and h.window[0] == 0
    assert not res.verified
    # without locating, the seed's unverified matches propose nothing
    res = auto.try_hypotheses(
        matcher,
        a,
        b,
        config=dataclasses.replace(config, locate=False),
        seed_matcher=seed,
        verification=VerificationConfig(),
        networks=False,
    )
    assert [t.hypothesis.source for t in res.trials] == ["identity", "seed (sift)"]


@pytest.mark.parametrize("turn", [1, 3])
def test_a_few_correct_sift_matches_among_many_wrong_ones_still_agree(photos, rng, turn):
    """Eight correct SIFT matches of a 3x close-up, turned, hidden among 150 random ones (random
    points, sizes and orientations): their sizes and orientations put them in one Hough bin."""
    from localscale.matching.auto.localization import locate_similarity, similarity_votes
    from localscale.matching.matcher import Matcher

    a = np.ascontiguousarray(photos["astronaut"])
    box, zoom = (200, 60, 360, 220), 3.0
    b = _close_up(a, box, zoom, turn)
    found = Matcher("sift").match(a, b)
    m = found.matches
    pa, pb = found.keypoints_a[m[:, 0]], found.keypoints_b[m[:, 1]]
    fa, fb = found.frames_a[m[:, 0]], found.frames_b[m[:, 1]]
    # the correct ones: B's point back in A within 3 px
    T = np.linalg.inv(turn_matrix(turn, (round(160 * zoom), round(160 * zoom))))
    back = (pb @ T[:2, :2].T + T[:2, 2]) / zoom + np.array(box[:2]) + (1 / zoom - 1) / 2
    correct = np.flatnonzero(np.linalg.norm(back - pa, axis=1) < 3)
    assert len(correct) >= 20
    # each correct match alone says where B's centre lies in A (the box's centre) and its zoom
    log_s, _, centre = similarity_votes(pa[correct], pb[correct], fa[correct], fb[correct], b.shape[:2])
    near = np.linalg.norm(centre - [(box[0] + box[2] - 1) / 2, (box[1] + box[3] - 1) / 2], axis=1) < 12
    assert near.mean() > 0.8 and np.median(log_s) == pytest.approx(np.log2(zoom), abs=0.15)
    keep = rng.choice(correct, 8, replace=False)
    n = 150
    pa = np.vstack([pa[keep], rng.random((n, 2)) * 512])
    pb = np.vstack([pb[keep], rng.random((n, 2)) * 480])
    fa = np.vstack([fa[keep], np.stack([rng.uniform(2, 30, n), rng.uniform(0, 360, n)], 1)])
    fb = np.vstack([fb[keep], np.stack([rng.uniform(6, 90, n), rng.uniform(0, 360, n)], 1)])
    located = locate_similarity(pa, pb, fa, fb, a.shape[:2], b.shape[:2])
    assert located is not None
    M, votes, inliers = located
    assert inliers[:8].sum() >= 7 and votes <= 10
    assert float(np.sqrt(np.linalg.det(M[:2, :2]))) == pytest.approx(zoom, rel=0.15)


@pytest.mark.parametrize("bad", [-0.1, 1.5, "wide"])
def test_a_bad_similarity_margin_is_refused(bad):
    with pytest.raises(LocalScaleError, match="similarity_margin"):
        AutoConfig(similarity_margin=bad).check()


def test_a_collection_seed_that_does_not_verify_gives_its_similarity(photos, monkeypatch):
    """``reconstruct``'s seed step: the SIFT seed's matches taken as unverified give the pair no
    relation (nothing for the pair graph) but the similarity's hypothesis, with its window of the
    wide view and the matches that agree with it (what ranks the anchors)."""
    import dataclasses

    pytest.importorskip("h5py")
    from localscale.matching.auto import trial
    from localscale.matching.matcher import Matcher
    from localscale.sfm.pair_runner import PairRunner

    a = np.ascontiguousarray(photos["astronaut"])
    images = {"wide": a, "close": _close_up(a, (200, 60, 360, 220), 3.0, 1)}
    real_run = trial.run_hypothesis

    def unverified_run(*args, **kwargs):
        found, v = real_run(*args, **kwargs)
        return found, dataclasses.replace(v, verified=False)

    monkeypatch.setattr(trial, "run_hypothesis", unverified_run)
    runner = PairRunner({}, None, None, "auto", "cpu", Matcher("hardnet"), None, None, 2)
    runner._image = lambda name: (images[name], 1.0)
    r = runner.seed("wide", "close")
    assert r.relation is None and r.hypothesis is not None and r.hypothesis.source == "seed similarity"
    assert r.hypothesis.scale == pytest.approx(3.0, rel=0.1) and r.hypothesis.turn == 3
    assert r.hypothesis.window is not None and r.hypothesis.window[0] == 0 and r.support >= 20
    monkeypatch.setattr(trial, "run_hypothesis", real_run)  # verified: the geometry's relation and hypothesis
    r = runner.seed("wide", "close")
    assert r.relation is not None and r.relation.turn == 3 and r.hypothesis.source == "sift geometry"


@pytest.mark.parametrize("bad", [0, 2.5, True])
def test_a_bad_seed_feature_count_is_refused(bad):
    with pytest.raises(LocalScaleError, match="seed_features"):
        AutoConfig(seed_features=bad).check()
