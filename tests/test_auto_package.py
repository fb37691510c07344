"""``auto`` in one package: the old modules and names still work for a release, with a warning."""

import importlib
import sys

import pytest

OLD_MODULES = {
    "localscale.matching.hypotheses": ("localscale.matching.auto.hypotheses", ("Hypothesis", "propose")),
    "localscale.matching.localization": ("localscale.matching.auto.localization", ("locate_window", "locate_turn")),
    "localscale.matching.turns": ("localscale.matching.auto.turns", ("match_turned", "unturn_points")),
    "localscale.sfm.pair_graph": ("localscale.matching.auto.graph", ("PairGraph", "Relation")),
}


@pytest.mark.parametrize("old", sorted(OLD_MODULES))
def test_an_old_module_warns_and_gives_the_packages_names(old):
    new, names = OLD_MODULES[old]
    sys.modules.pop(old, None)
    with pytest.warns(DeprecationWarning, match="next release"):
        module = importlib.import_module(old)
    target = importlib.import_module(new)
    for name in names:
        assert getattr(module, name) is getattr(target, name)


@pytest.mark.parametrize(
    "old, new",
    [("auto_match", "try_hypotheses"), ("refine_match", "match_refined_pair"), ("refine_matching", "refine_passes")],
)
def test_an_old_name_warns_and_gives_the_new_function(old, new):
    import localscale.matching as matching

    with pytest.warns(DeprecationWarning, match=new):
        f = getattr(matching, old)
    assert f is getattr(matching, new)
    assert old not in matching.__all__ and new in matching.__all__


def test_the_package_drives_a_collection_without_the_sfm_package():
    """The steps of ``auto`` on a collection are the matching package's: importing them loads no sfm module."""
    import subprocess

    code = (
        "import sys, localscale.matching.auto.collection, localscale.matching.auto.loop;"
        "print(sorted(m for m in sys.modules if m.startswith('localscale.sfm')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_the_sfm_runner_holds_the_correction_object():
    from localscale.matching import get_correction
    from localscale.matching.matcher import Matcher
    from localscale.sfm.pair_runner import PairRunner

    runner = PairRunner({}, None, None, "none", "cpu", Matcher("sift"), None, None, 2)
    assert runner.correction is get_correction("none") and runner.correction.as_is
    assert not get_correction("auto").as_is and not get_correction("gt").as_is and not get_correction("local").as_is
