"""locate_window: the part of the wide view a zoomed view shows, voted by matches that did not verify."""

import numpy as np
import pytest

from localscale.errors import LocalScaleError
from localscale.geometry import turn_matrix
from localscale.matching.auto import AutoConfig
from localscale.matching.localization import locate_turn, locate_window

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
        return found, auto._verify(found, a_, b_, vconf, cameras)

    monkeypatch.setattr(auto, "_run", stand_in_run)
    config = AutoConfig(budget=2, seed=None, locate=locate)
    h = auto.Hypothesis(zoom * 0.9, (4 - turn) % 4, "test")
    res = auto.auto_match(None, a, b, config=config, verification=VerificationConfig(), hypotheses=[h], networks=False)
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
    from localscale.matching.auto import Hypothesis, _Loop
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
    auto._run(matcher, a, b, h, (None, None), VerificationConfig(), window_max_side=window_max_side)
    f_window, f_close = factors[(75, 100)], factors[(480, 640)]
    assert f_window * 100 == pytest.approx(side)
    assert f_close == pytest.approx(0.125 * f_window)  # the pair still brought to one scale


@pytest.mark.parametrize("bad", [0, -5, 1.5, True])
def test_a_bad_window_max_side_is_refused(bad):
    with pytest.raises(LocalScaleError, match="window_max_side"):
        AutoConfig(window_max_side=bad).check()
