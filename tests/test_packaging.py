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
