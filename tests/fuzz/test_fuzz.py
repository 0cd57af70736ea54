"""A brief, reproducible run of every reader fuzz target (``make fuzz`` explores each for 10 minutes).

Each target runs in its own process (``python -m tests.fuzz.run``) under the
runner's memory limit and per-input alarm; any input that ends other than as
a valid cloud or a clean one-line error fails the test, with the input saved.
"""

import os
import re
import subprocess
import sys

import pytest

from tests.conftest import ROOT
from tests.fuzz.targets import TARGETS

SECONDS = float(os.environ.get("FUZZ_BRIEF_SECONDS", 4))


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(TARGETS))
def test_fuzz_target_briefly(name, request, tmp_path):
    data = request.getfixturevalue("shared_data") if not TARGETS[name].config else None
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    argv = [sys.executable, "-m", "tests.fuzz.run", "--seconds", str(SECONDS), "--target", name,
            "--failures", str(tmp_path / "failures"), "--derandomize"]
    if data is not None:
        argv += ["--data", str(data)]
    out = subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    report = out.stdout + out.stderr
    assert out.returncode == 0, report
    runs = re.search(rf"^{name}: (\d+) executions .* (\d+) failures$", out.stdout, re.M)
    assert runs and int(runs.group(1)) >= 20 and runs.group(2) == "0", report
    assert "Traceback" not in report, report
