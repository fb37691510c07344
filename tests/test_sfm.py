"""Structure from motion (localscale.sfm) on a rendered scene with known cameras: the whole
reconstruction, its resume, the h5 files and the COLMAP database read back, and the pieces the
matching step relies on (keypoint merging, the level cache, pairs). No data files."""

import json
import os

import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")
h5py = pytest.importorskip("h5py")

os.environ.setdefault("OMP_NUM_THREADS", "1")

from localscale.sfm import (  # noqa: E402
    KeypointSet,
    extract_features,
    find_images,
    pairs_exhaustive,  # noqa: E402
    pairs_from_file,
    pairs_from_retrieval,
    read_all_matches,
    read_database,
    read_geometries,
    reconstruct,
    snap_factor,
)
from localscale.sfm.extract import FeatureConf, LevelMatcher, read_features  # noqa: E402
from localscale.sfm.h5io import H5Writer, matches0_from_matches, matches_from_matches0, read_group  # noqa: E402
from localscale.sfm.synthetic import write_scene  # noqa: E402


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scene")
    cameras = write_scene(folder, num_views=6, shape=(240, 320), seed=0)
    return folder, cameras


@pytest.fixture(scope="module")
def run(scene, tmp_path_factory):
    folder, _ = scene
    out = tmp_path_factory.mktemp("sfm") / "out"
    summary = reconstruct(folder, out, matcher="sift", num_keypoints=2048, num_threads=1, show_progress=False)
    return out, summary


def _similarity_residual(x: np.ndarray, y: np.ndarray) -> float:
    """RMS distance after the best similarity x -> y (Umeyama), relative to y's spread."""
    mx, my = x.mean(0), y.mean(0)
    xc, yc = x - mx, y - my
    u, s, vt = np.linalg.svd(yc.T @ xc)
    d = np.diag([1, 1, np.sign(np.linalg.det(u @ vt))])
    R = u @ d @ vt
    scale = np.trace(np.diag(s) @ d) / (xc**2).sum()
    err = yc - scale * xc @ R.T
    return float(np.sqrt((err**2).sum(1).mean()) / np.sqrt((yc**2).sum(1).mean()))


def test_reconstruct_registers_every_view_at_the_true_poses(scene, run):
    folder, cameras = scene
    out, summary = run
    assert summary["images"] == 6 and summary["registered"] == 6
    assert summary["points"] > 100 and summary["mean_track_length"] > 2.5
    assert summary["mean_reprojection_error"] < 1.5
    assert summary["pairs"] == 15 and summary["pairs_verified"] >= 12
    assert json.loads((out / "summary.json").read_text())["registered"] == 6
    assert (out / "reconstruction.png").stat().st_size > 10_000
    rec = pycolmap.Reconstruction(out / "sparse" / "0")
    est = {im.name: np.asarray(im.projection_center()) for im in rec.images.values() if im.has_pose}
    names = sorted(est)
    truth = np.array([cameras[int(n.split("_")[1].split(".")[0])].center for n in names])
    # the camera centres agree with the rendering cameras up to a similarity (SfM's gauge)
    assert _similarity_residual(np.array([est[n] for n in names]), truth) < 0.05


def test_global_mapper_registers_every_view_at_the_true_poses(scene, run, tmp_path):
    """COLMAP's global mapper (GLOMAP) on the same matches: a rerun with ``mapper="global"`` resumes
    the matching and maps again; every view sits at its true place up to a similarity."""
    import shutil

    folder, cameras = scene
    out = tmp_path / "out"
    shutil.copytree(run[0], out)
    summary = reconstruct(
        folder, out, matcher="sift", num_keypoints=2048, num_threads=1, show_progress=False, mapper="global"
    )
    assert summary["run"] == "resume" and summary["matching"]["matched"] == 0
    assert summary["options"]["mapper"] == "global"
    assert summary["mapping_runs"] == [{"seed": 0, "registered": 6}]  # all registered: one run
    assert summary["registered"] == 6 and summary["mean_reprojection_error"] < 1.5
    # no focal lengths known (COLMAP's 1.2 x side guess): the view-graph calibration found them first
    assert summary["view_graph_calibrated"] is True
    rec = pycolmap.Reconstruction(out / "sparse" / "0")
    true_f = cameras[0].K[0, 0]
    assert all(abs(c.focal_length / true_f - 1) < 0.1 for c in rec.cameras.values()), (true_f, rec.cameras)
    est = {im.name: np.asarray(im.projection_center()) for im in rec.images.values() if im.has_pose}
    names = sorted(est)
    truth = np.array([cameras[int(n.split("_")[1].split(".")[0])].center for n in names])
    assert _similarity_residual(np.array([est[n] for n in names]), truth) < 0.05


def test_implausible_intrinsics_are_flagged(run, capsys):
    """A model whose camera drifted to an absurd focal length (COLMAP's own bounds: 0.1-10 x the
    image size) is named in the summary and gets a warning instead of being reported as fine."""
    from localscale.sfm.mapping import model_stats
    from localscale.sfm.reconstruction import _flag

    out, summary = run
    rec = pycolmap.Reconstruction(out / "sparse" / "0")
    assert model_stats(rec)["bogus_cameras"] == [] and summary["implausible_cameras"] == []
    image = next(im for im in rec.images.values() if im.has_pose)
    camera = rec.cameras[image.camera_id]
    camera.params = [3e7, *list(camera.params)[1:]]
    rec.cameras[image.camera_id] = camera
    bad = [im.name for im in rec.images.values() if im.has_pose and im.camera_id == image.camera_id]
    assert model_stats(rec)["bogus_cameras"] == sorted(bad)
    _flag({**summary, "implausible_cameras": sorted(bad)})
    assert "implausible intrinsics" in capsys.readouterr().err


def test_the_mapper_runs_again_while_images_are_left_out(run, tmp_path, monkeypatch):
    """The incremental mapper depends on its random seed; while its largest model leaves images out,
    it runs again with the next seed and the run that registers the most is kept."""
    from localscale.sfm.mapping import run_mapping

    out, _ = run
    full = pycolmap.Reconstruction(out / "sparse" / "0")
    partial = pycolmap.Reconstruction(out / "sparse" / "0")
    partial.deregister_frame(next(im.frame_id for im in partial.images.values() if im.has_pose))
    seeds = []

    def mapper(database, images, output, options):  # seed 0 leaves one image out, seed 1 does not
        seeds.append(options.random_seed)
        return {0: partial if options.random_seed == 0 else full}

    monkeypatch.setattr(pycolmap, "incremental_mapping", mapper)
    res = run_mapping(out / "database.db", out, tmp_path / "sparse", num_threads=1, trials=3)
    assert seeds == [0, 1] and res.stats[0]["registered"] == 6
    assert res.trials == [{"seed": 0, "registered": 5}, {"seed": 1, "registered": 6}]
    assert pycolmap.Reconstruction(tmp_path / "sparse" / "0").num_reg_images() == 6
    seeds.clear()
    assert run_mapping(out / "database.db", out, tmp_path / "one", num_threads=1, trials=1).stats[0]["registered"] == 5
    assert seeds == [0]


def test_an_unknown_mapper_is_refused_before_anything_is_written(scene, tmp_path):
    from localscale.core.errors import LocalScaleError

    with pytest.raises(LocalScaleError, match="mapper must be one of incremental, global"):
        reconstruct(scene[0], tmp_path / "out", matcher="sift", mapper="glomap", show_progress=False)
    assert not (tmp_path / "out").exists()


def test_mapper_options_reach_pycolmap_by_name(run, tmp_path, monkeypatch):
    """``mapper_options`` set pycolmap's options by dotted name, strings read as the option's type;
    the mapper is given them, and the summary records them."""
    from localscale.sfm.mapper_options import mapping_options
    from localscale.sfm.mapping import run_mapping

    opts = mapping_options(
        1,
        overrides={
            "ba_refine_extra_params": "false",
            "mapper.abs_pose_min_num_inliers": "15",
            "mapper.init_max_error": 2,
        },
    )
    assert opts.ba_refine_extra_params is False
    assert opts.mapper.abs_pose_min_num_inliers == 15 and opts.mapper.init_max_error == 2.0
    assert mapping_options(1).ba_refine_extra_params is True  # each call starts from pycolmap's defaults
    out, _ = run
    seen = []

    def mapper(database, images, output, options):
        seen.append((options.ba_refine_extra_params, options.mapper.abs_pose_min_num_inliers))
        return {0: pycolmap.Reconstruction(out / "sparse" / "0")}

    monkeypatch.setattr(pycolmap, "incremental_mapping", mapper)
    overrides = {"ba_refine_extra_params": False, "mapper.abs_pose_min_num_inliers": 12}
    run_mapping(out / "database.db", out, tmp_path / "sparse", num_threads=1, overrides=overrides)
    assert seen == [(False, 12)]


def test_reconstruct_with_mapper_options_records_them(scene, tmp_path):
    """A camera per image keeps the distortion out of the incremental mapper's refinement unless
    the user's options say otherwise; a shared camera keeps pycolmap's defaults."""
    from localscale.sfm.mapper_options import PER_IMAGE_CAMERA_OPTIONS, default_overrides

    assert default_overrides("incremental", "per_image") == PER_IMAGE_CAMERA_OPTIONS
    assert default_overrides("incremental", "single") == {} and default_overrides("global", "per_image") == {}
    common = dict(matcher="sift", num_threads=1, show_progress=False, plot=False)
    summary = reconstruct(scene[0], tmp_path / "single", camera_mode="single", **common)
    assert summary["registered"] == 6 and summary["mapper_options"] == {}
    summary = reconstruct(
        scene[0],
        tmp_path / "per_image",
        camera_mode="per_image",
        mapper_options={"ba_refine_extra_params": "true"},
        **common,
    )
    assert summary["registered"] == 6
    assert summary["options"]["mapper_options"] == {"ba_refine_extra_params": "true"}
    assert summary["mapper_options"] == {"ba_refine_extra_params": "true", "mapper.abs_pose_refine_extra_params": False}


@pytest.mark.parametrize(
    "options, message",
    [
        ({"ba_refine_extra_param": "false"}, "incremental mapper has no option 'ba_refine_extra_param'"),
        ({"mapper.no_such_thing": 1}, "no option 'mapper.no_such_thing'"),
        ({"ba_refine_extra_params": "maybe"}, "takes true or false"),
        ({"mapper.abs_pose_min_num_inliers": "many"}, "takes an integer"),
        ({"mapper.abs_pose_min_num_inliers": 1.5}, "takes an integer"),
    ],
)
def test_bad_mapper_options_are_refused_before_anything_is_written(scene, tmp_path, options, message):
    from localscale.core.errors import LocalScaleError

    with pytest.raises(LocalScaleError, match=message):
        reconstruct(scene[0], tmp_path / "out", matcher="sift", mapper_options=options, show_progress=False)
    assert not (tmp_path / "out").exists()


def test_rerun_resumes_and_other_options_are_refused(scene, run):
    folder, _ = scene
    out, first = run
    again = reconstruct(folder, out, matcher="sift", num_keypoints=2048, num_threads=1, show_progress=False)
    assert again["run"] == "resume"
    assert again["matching"]["resumed"] == 15 and again["matching"]["matched"] == 0
    assert again["registered"] == first["registered"]
    from localscale.sfm import OutputFolderError

    with pytest.raises(OutputFolderError, match="other options"):
        reconstruct(folder, out, matcher="sift", num_keypoints=1000, show_progress=False)


def test_h5_files_hold_hloc_layout(run):
    out, _ = run
    images = ["view_%d.png" % i for i in range(6)]
    for name in images:
        f = read_features(out / "features.h5", name)
        assert f["keypoints"].dtype == np.float32 and f["keypoints"].shape[1] == 2
        n = len(f["keypoints"])
        assert f["descriptors"].shape == (128, n) and f["scores"].shape == (n,)
        assert list(f["image_size"]) == [320, 240]
        assert (f["keypoints"] >= -0.5).all() and (f["keypoints"][:, 0] <= 320).all()
        # correction none: the keypoint set the matches index is exactly the extracted one
        kp = read_group(out / "keypoints.h5", name, ("keypoints",))["keypoints"]
        np.testing.assert_array_equal(kp, f["keypoints"])
    matches = read_all_matches(out / "matches.h5")
    assert len(matches) == 15
    for (a, b), (m, s) in matches.items():
        na = len(read_group(out / "keypoints.h5", a, ("keypoints",))["keypoints"])
        nb = len(read_group(out / "keypoints.h5", b, ("keypoints",))["keypoints"])
        assert len(m) > 20 and m[:, 0].max() < na and m[:, 1].max() < nb
        assert len(np.unique(m[:, 0])) == len(m) and len(np.unique(m[:, 1])) == len(m)  # one to one
        assert s.dtype == np.float32 and len(s) == len(m)


def test_h5_writer_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(1)
    kps = rng.random((50, 2)).astype(np.float32) * 100
    desc = rng.random((64, 50)).astype(np.float32)
    w = H5Writer(tmp_path / "f.h5")
    w.add("sub/a.jpg", {"keypoints": kps, "descriptors": desc}, {"note": "x"})
    w.flush()
    w.add("b.png", {"keypoints": kps[:3]})
    w.flush()  # a second flush keeps the first groups
    got = read_group(tmp_path / "f.h5", "sub/a.jpg")
    assert got["keypoints"].dtype == np.float32
    np.testing.assert_array_equal(got["keypoints"], kps)
    np.testing.assert_array_equal(got["descriptors"], desc)
    assert got["attrs"]["note"] == "x"
    np.testing.assert_array_equal(read_group(tmp_path / "f.h5", "b.png")["keypoints"], kps[:3])
    m = np.array([[0, 5], [3, 1], [7, 2]])
    m0, s0 = matches0_from_matches(m, np.array([0.9, 0.5, 0.1], np.float32), 10)
    back, s = matches_from_matches0(m0, s0)
    np.testing.assert_array_equal(back, m)
    np.testing.assert_allclose(s, [0.9, 0.5, 0.1])


def test_database_reads_back_what_was_written(run):
    out, _ = run
    db = read_database(out / "database.db")
    assert len(db.cameras) == 1  # auto: same size, no EXIF -> one camera
    assert sorted(db.images) == ["view_%d.png" % i for i in range(6)]
    for name in db.images:
        kp = read_group(out / "keypoints.h5", name, ("keypoints",))["keypoints"]
        np.testing.assert_allclose(db.keypoints[name], kp, atol=1e-4)
    matches = read_all_matches(out / "matches.h5")
    geometries = read_geometries(out / "geometries.h5")
    assert len(db.matches) == len(matches) == 15
    for (a, b), (m, _) in matches.items():
        got = db.matches.get((a, b))
        if got is None:  # COLMAP stores a pair in image-id order
            got = db.matches[(b, a)][:, ::-1]
        assert {tuple(r) for r in got} == {tuple(r) for r in m}
        g = geometries[(a, b)]
        config, inliers = db.geometries[(a, b)] if (a, b) in db.geometries else db.geometries[(b, a)]
        assert len(inliers) == len(g.inlier_matches)
        assert len(inliers) == 0 or config in (
            "CALIBRATED",
            "UNCALIBRATED",
            "PLANAR",
            "PANORAMIC",
            "PLANAR_OR_PANORAMIC",
        )


def test_keypoint_set_merges_coincident_points():
    s = KeypointSet(np.array([[10.0, 10.0], [10.6, 10.0], [50.0, 50.0]]), merge_px=1.0)
    idx = s.index(np.array([[10.5, 10.1], [9.8, 10.2], [30.0, 30.0], [30.4, 29.8], [50.0, 50.0]]))
    assert list(idx) == [1, 0, 3, 3, 2]  # nearest within 1 px; a new point, then merged with it
    assert len(s) == 4 and s.num_base == 3
    np.testing.assert_allclose(s.keypoints[3], [30.0, 30.0])


def test_level_cache_extracts_each_image_level_once():
    from localscale.matching import match_config

    assert snap_factor(0.5, 2) == 0.5 and snap_factor(0.55, 2) == 0.5 and snap_factor(0.7, 2) == 2**-0.5
    assert snap_factor(1.0) == 1.0
    rng = np.random.default_rng(0)
    img = (rng.random((120, 160, 3)) * 255).astype(np.uint8)
    m = LevelMatcher(match_config("sift", num_features=200), cache_size=8, levels_per_octave=2)
    f1 = m.extract(img, 0.52, "a")
    f2 = m.extract(img, 0.47, "a")  # the same half-octave level: from the cache
    assert f1 is f2 and m.level_count == 1
    m.extract(img, 0.52, "b")  # another image
    m.extract(np.rot90(img).copy(), 0.52, ("a", "turn", 1))  # a turn of the same image
    m.extract(img, 0.25, "a")  # another level
    assert m.level_count == 4 and max(m.extractions.values()) == 1


def test_pairs_exhaustive_retrieval_and_file(run, tmp_path):
    out, _ = run
    names = ["view_%d.png" % i for i in range(6)]
    assert len(pairs_exhaustive(names)) == 15
    near = pairs_from_retrieval(names, out / "features.h5", 2)
    assert all(any(n in p for p in near) for n in names)
    assert len({tuple(sorted(p)) for p in near}) == len(near) <= 12
    f = tmp_path / "pairs.txt"
    f.write_text("# comment\nview_0.png view_1.png\nview_1.png view_0.png\n\n'view_2.png' view_3.png\n")
    assert pairs_from_file(f, names) == [("view_0.png", "view_1.png"), ("view_2.png", "view_3.png")]


def test_find_images_skips_what_is_not_an_image(tmp_path, capsys):
    write_scene(tmp_path, num_views=2, shape=(60, 80))
    (tmp_path / "notes.txt").write_text("x")
    (tmp_path / "broken.jpg").write_bytes(b"\xff\xd8\xff\xe0 not a jpeg")
    images = find_images(tmp_path)
    assert [im.name for im in images] == ["view_0.png", "view_1.png"]
    assert images[0].shape == (60, 80)
    err = capsys.readouterr().err
    assert "warning: skipped 1 file(s) that are not images" in err and "notes.txt" in err
    assert "warning: skipped broken.jpg" in err


def test_extract_features_resumes(tmp_path, scene):
    folder, _ = scene
    images = find_images(folder)
    conf = FeatureConf("sift", 300, 1024)
    path = extract_features(images[:2], tmp_path / "features.h5", conf, show_progress=False)
    before = read_features(path, images[0].name)["keypoints"]
    m = LevelMatcher(conf.match_config())
    extract_features(images[:3], path, conf, matcher=m, show_progress=False)
    assert m.level_count == 1  # only the image not yet in the file
    np.testing.assert_array_equal(read_features(path, images[0].name)["keypoints"], before)


def test_pairs_file_takes_names_tabs_and_paths(scene, tmp_path):
    folder, _ = scene
    names = ["view_%d.png" % i for i in range(6)]
    f = tmp_path / "pairs.txt"
    rel = os.path.relpath(folder / "view_4.png", tmp_path)
    f.write_text(f"view_0.png\tview_1.png\n{rel} view_5.png\n")
    assert pairs_from_file(f, names, folder) == [("view_0.png", "view_1.png"), ("view_4.png", "view_5.png")]
    from localscale.sfm import PairsFileError

    with pytest.raises(PairsFileError, match="not one of the usable images"):
        pairs_from_file(f, names)  # paths need the images folder


def test_interrupted_matching_keeps_its_pairs_and_resumes(scene, tmp_path, monkeypatch):
    from localscale.sfm import pair_runner as match_module

    folder, _ = scene
    real_run = match_module.PairRunner.run
    calls = []

    def run_then_stop(self, a, b):
        if len(calls) == 5:
            raise KeyboardInterrupt
        calls.append((a, b))
        return real_run(self, a, b)

    monkeypatch.setattr(match_module.PairRunner, "run", run_then_stop)
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        reconstruct(folder, out, matcher="sift", num_threads=1, show_progress=False)
    assert len(read_all_matches(out / "matches.h5")) == 5  # flushed on the way out
    assert not (out / "summary.json").exists()
    monkeypatch.setattr(match_module.PairRunner, "run", real_run)
    summary = reconstruct(folder, out, matcher="sift", num_threads=1, show_progress=False)
    assert summary["run"] == "resume"
    assert summary["matching"]["resumed"] == 5 and summary["matching"]["matched"] == 10
    assert summary["registered"] == 6
