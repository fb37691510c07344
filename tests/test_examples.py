"""The plug-in examples run on the bundled pair and show what they claim."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def _run(script, *args):
    env = dict(os.environ, OMP_NUM_THREADS="1", MPLBACKEND="Agg")
    res = subprocess.run(
        [sys.executable, str(EXAMPLES / script), *args], capture_output=True, text=True, env=env, timeout=300
    )
    assert res.returncode == 0, res.stderr
    return res.stdout


@pytest.mark.parametrize("detector", ["orb", "sift"])
def test_keypoint_scales_opencv_example_corrects_more_matches(detector):
    out = _run("keypoint_scales_opencv.py", "--detector", detector)
    correct = {name: int(n) for name, n in re.findall(r"(uncorrected|rescaled): .* (\d+) correct", out)}
    assert set(correct) == {"uncorrected", "rescaled"}, out
    assert correct["rescaled"] > correct["uncorrected"], out


def test_batched_maps_example():
    out = _run("batched_maps.py", "--device", "cpu")
    assert "(2, 427, 640) scale maps" in out
    diff = float(re.search(r"max \|predict_batch - predict\| on \(A, B\): (\S+)", out).group(1))
    assert diff < 1e-4
    errors = [float(e) for e in re.findall(r"mean scale-ratio error (\S+)", out)]
    assert len(errors) == 2 and max(errors) < 1.5, out
