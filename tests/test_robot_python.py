"""The agents on the robots' Python: `khepri sil --agent-python` runs them with another interpreter, and `make
test` builds .venv-robot (Python 3.9 with the lowest package versions pyproject.toml allows) where it finds a
Python 3.9. The syntax check in test_architecture.py reads onboard/ as 3.9 would parse it; this runs it."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ROBOT_PYTHON = ROOT / ".venv-robot" / "bin" / "python"
# What the Makefile's ROBOT_PACKAGES pin: the lowest versions pyproject.toml allows.
LOWEST = {"numpy": "1.22.4", "zmq": "25.0.0", "yaml": "6.0", "filterpy": "2.0.0"}


def khepri(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "khepri_cli.main", *args], capture_output=True, text=True,
                          timeout=timeout, env=dict(os.environ, PYTHONPATH=str(ROOT)))


@pytest.mark.skipif(not ROBOT_PYTHON.exists(), reason="no .venv-robot: `make test` builds it where it finds a "
                                                       "Python 3.9 (or ROBOT_PYTHON names one)")
def test_the_payload_demo_completes_with_its_agents_on_python_39_and_the_lowest_packages(tmp_path):
    versions = subprocess.run(
        [str(ROBOT_PYTHON), "-c", "import sys, numpy, zmq, yaml, filterpy; print(sys.version_info[:2] == (3, 9), "
         "numpy.__version__, zmq.__version__, yaml.__version__, filterpy.__version__)"],
        capture_output=True, text=True, timeout=120)
    assert versions.stdout.split() == ["True", *LOWEST.values()], versions.stdout + versions.stderr
    out = tmp_path / "sil"
    run = khepri("sil", "lab-6-payload", "--agent-python", str(ROBOT_PYTHON), "--no-plot", "--no-record",
                 "--out", str(out))
    assert run.returncode == 0, run.stderr[-2000:]
    result = json.loads((out / "result.json").read_text())
    assert result["completed"] and result["final_position_error_m"] <= 0.05, result.get("failures")
    assert re.fullmatch(rf"3\.9\.\d+ \({re.escape(str(ROBOT_PYTHON))}\)", result["sil"]["agent_python"])
    assert result["sil"]["agent_exit_codes"] == [0] * 6


def test_an_interpreter_that_cannot_run_an_agent_is_refused_before_anything_starts(tmp_path):
    """Six agents crashing on `import numpy` said nothing of why; a file that is no program neither."""
    bare = tmp_path / "bare-python"       # this Python without its site-packages: no numpy, no zmq
    bare.write_text(f"#!/bin/sh\nexec {sys.executable} -S \"$@\"\n")
    bare.chmod(0o755)
    out = tmp_path / "sil"
    run = khepri("sil", "lab-6", "--agent-python", str(bare), "--out", str(out))
    assert run.returncode == 2
    assert run.stderr.startswith(f"khepri: error: --agent-python: {bare} cannot import numpy (ModuleNotFoundError: "
                                 "No module named 'numpy'); zmq ("), run.stderr
    assert run.stderr.rstrip().endswith(": install numpy, pyzmq, pyyaml and filterpy into it")
    assert not out.exists()          # said before --out was made
    text = tmp_path / "notes.txt"
    text.write_text("not a program\n")
    run = khepri("sil", "lab-6", "--agent-python", str(text), "--out", str(out))
    assert run.returncode == 2 and run.stderr == f"khepri: error: --agent-python: {text} is not an executable file\n"
    silent = tmp_path / "silent"          # runs, says nothing, exits 0: no version, so no Python
    silent.write_text("#!/bin/sh\nexit 0\n")
    silent.chmod(0o755)
    run = khepri("sil", "lab-6", "--agent-python", str(silent), "--out", str(out))
    assert run.returncode == 2 and run.stderr == (f"khepri: error: --agent-python: {silent} does not run as a Python "
                                                  "interpreter (exit code 0)\n")
