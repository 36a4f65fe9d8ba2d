"""tools/gpu_check.sh, the script a lent GPU machine runs (docs/GPU.md): it must stay runnable.

No GPU here: the script's syntax, its documented steps against the ones it runs, and one step
run through its step runner (a failed step is recorded and the next still runs).
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys

import pytest

from tests.helpers.paths import REPO

SCRIPT = REPO / "tools" / "gpu_check.sh"
pytestmark = pytest.mark.skipif(shutil.which("bash") is None, reason="no bash")


def test_the_script_parses_and_documents_every_step_it_runs():
    subprocess.run(["bash", "-n", str(SCRIPT)], check=True)
    text = SCRIPT.read_text()
    documented = set(re.findall(r"^#   (\w+)\s", text, flags=re.M))
    run = set(re.findall(r"^\s+(\w+)\)\s", text, flags=re.M)) - {"export"}
    assert documented == run, (documented, run)


def test_a_step_runs_under_its_limit_and_a_failure_does_not_stop_the_next(tmp_path):
    env = dict(os.environ, OUT=str(tmp_path / "out"), PYTHON=sys.executable,
               GPU_CHECK_WORK=str(tmp_path / "work"), GPU_CHECK_BACKEND="cpu",
               GPU_CHECK_DEADLINE="60")
    p = subprocess.run(["bash", str(SCRIPT), "env", "nosuchstep", "env"], cwd=REPO, env=env,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    lines = (tmp_path / "out" / "summary.txt").read_text().splitlines()
    assert [ln.split()[0] for ln in lines] == ["env", "unknown", "env"]
    assert "torch" in (tmp_path / "out" / "log.txt").read_text()
