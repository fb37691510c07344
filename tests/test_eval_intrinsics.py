"""``eval/reconstruct_collections.py --intrinsics``: known PINHOLE cameras read from a collection's
``name w h fx fy cx cy`` table (:mod:`localscale.evaluation.reconstruction`)."""

import pytest

from localscale.evaluation import reconstruction


def test_intrinsics_table_is_read_per_image(tmp_path):
    table = tmp_path / "intrinsics.txt"
    lines = [
        "# name w h fx fy cx cy",
        "a.jpg 1024 683 819.2 819.6 512 341.5",
        "",
        "b.jpg 683 1024 819.6 819.2 341.5 512",
    ]
    table.write_text("\n".join(lines) + "\n")
    cams = reconstruction.read_intrinsics(table)
    assert cams == {"a.jpg": "819.2,819.6,512.0,341.5", "b.jpg": "819.6,819.2,341.5,512.0"}
    # the mapper keeps them: no focal length, principal point or distortion refinement
    assert set(reconstruction.FIXED_INTRINSICS.values()) == {False} and len(reconstruction.FIXED_INTRINSICS) == 3


def test_bad_intrinsics_are_refused_before_anything_runs(tmp_path, capsys, repo_script):
    rc = repo_script("eval/reconstruct_collections.py")
    bad = tmp_path / "bad.txt"
    bad.write_text("a.jpg 1024 683 819.2\n")
    with pytest.raises(ValueError, match="name w h fx fy cx cy"):
        reconstruction.read_intrinsics(bad)
    out = tmp_path / "out"
    for arg in ("cyprus_dim", f"cyprus_dim={bad}", f"cyprus_dim={tmp_path / 'missing.txt'}"):
        with pytest.raises(SystemExit) as e:
            rc.main(["--root", str(tmp_path), "--intrinsics", arg, "-o", str(out)])
        assert e.value.code == 2 and "--intrinsics" in capsys.readouterr().err
    assert not out.exists()


def test_rows_name_the_pairs_and_the_ray_cluster(tmp_path, capsys, repo_script):
    run = reconstruction.ReconstructionRun
    assert reconstruction.row_name(run(), "aliked-lg-auto") == "aliked-lg-auto"
    cfg = run(pairs="auto", ray_workers=2, mapper="global")
    assert reconstruction.row_name(cfg, "aliked-lg-auto") == "aliked-lg-auto+global+pairs-auto+ray2"
    # COLMAP's SIFT pipeline always runs in this process on its exhaustive pairs
    assert reconstruction.row_name(cfg, "colmap-sift") == "colmap-sift+global"
    rc = repo_script("eval/reconstruct_collections.py")
    with pytest.raises(SystemExit) as e:
        rc.main(["--root", str(tmp_path), "--ray-workers", "-1", "-o", str(tmp_path / "out")])
    assert e.value.code == 2 and "--ray-workers" in capsys.readouterr().err
