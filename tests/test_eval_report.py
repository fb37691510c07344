"""Result files record the commit of the code that made them."""

import json
import re
import subprocess

import numpy as np

from localscale.evaluation.report import git_commit, write_outputs


def test_commit_of_this_checkout_or_unknown(tmp_path):
    here = git_commit()
    assert here == "unknown" or re.fullmatch(r"[0-9a-f]{40}", here)
    package = tmp_path / "repo" / "localscale"
    package.mkdir(parents=True)
    assert git_commit(package) == "unknown"  # no checkout around it
    git = ["git", "-C", str(tmp_path / "repo"), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], check=True)
    assert git_commit(package) == "unknown"  # a checkout without a commit
    (package / "x.py").write_text("")
    subprocess.run([*git, "add", "."], check=True)
    subprocess.run([*git, "commit", "-qm", "x"], check=True)
    head = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    assert git_commit(package) == head
    inner = tmp_path / "repo" / "sub" / "localscale"  # a package deeper inside another checkout
    inner.mkdir(parents=True)
    assert git_commit(inner) == "unknown"


def test_evaluation_outputs_record_the_commit(tmp_path):
    summary = {"all": {"num_pairs": 0}}
    write_outputs({"summary": summary, "records": []}, [], ["none"], tmp_path, thresholds=(1, 3, 5, 10))
    doc = json.loads((tmp_path / "results.json").read_text())
    assert doc["commit"] == git_commit()
    assert np.isscalar(doc["commit"])
