"""Packaging: dependency ranges (no exact pins), one version everywhere, ``localscale --version``."""

import re
import sys
from pathlib import Path

import pytest

import localscale
from localscale.cli import main

ROOT = Path(__file__).resolve().parent.parent


def test_version_flag(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"localscale {localscale.__version__}"
    assert re.fullmatch(r"\d+\.\d+\.\d+\S*", localscale.__version__)


@pytest.mark.skipif(sys.version_info < (3, 11), reason="tomllib")
def test_dependencies_are_ranges_and_the_version_has_one_source():
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    deps = project["dependencies"] + [d for ds in project["optional-dependencies"].values() for d in ds]
    assert not [d for d in deps if "==" in d or "===" in d], deps
    assert "torch>=2.1" in project["dependencies"]
    assert "version" in project.get("dynamic", []) and "version" not in project


@pytest.mark.skipif(sys.version_info < (3, 11), reason="tomllib")
def test_the_readme_test_command_installs_what_the_whole_suite_needs():
    """A newcomer's command runs every test: the sfm extra (test_sfm*.py skip without pycolmap
    and h5py) and the ray extra (the engine's Ray tests skip without it) are installed with the
    test extra; the README stays a short guide."""
    import tomllib

    readme = (ROOT / "README.md").read_text()
    assert len(readme.encode()) <= 8192
    command = next(line for line in readme.splitlines() if "python -m pytest" in line)
    installed = re.search(r'pip install -e "\.\[([a-z,]+)\]"', command)
    assert installed, command
    extras = set(installed.group(1).split(","))
    known = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert extras <= set(known) and {"test", "sfm", "ray"} <= extras, extras
