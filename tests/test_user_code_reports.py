"""What a run says about a bug in the user's own code (behaviour or evaluator) when it comes at an awkward
moment: at the very first step, after another failure, or deep inside khepri's checks."""
import json
import sys

import numpy as np
import pytest

from khepri_cli.main import main

CRASHY = '''
from dataclasses import dataclass

from onboard.behaviour import Behaviour, register


@dataclass
class CrashyParams:
    bug: str = "none"


@register("crashy")
class Crashy(Behaviour):
    Params = CrashyParams

    def step(self):
        self.robot.wheels.set_speeds(0.1, 0.1)
        if self.params.bug == "step_at_0" and self.robot.id == 1:
            raise RuntimeError("deliberate crash")

    def telemetry(self):
        if self.params.bug == "telemetry_at_0":
            return {"seen": {1, 2}}
        return {"state": "ok"}
'''

SCENARIO = """name: crashy
behaviour: crashy
params: {{bug: {bug}}}
robots: {{count: 3, spawn: {{x: [-0.5, 0.5], y: [-0.5, 0.5]}}}}
object: {{shape: polygon, vertices: [[0, 0], [0.4, 0], [0.2, 0.3]], position: [0.8, 0.8], static: true}}
arena: {{walls: [-1.5, -1.5, 1.5, 1.5]}}
time_limit_s: 1
"""


@pytest.fixture
def crashy(tmp_path, monkeypatch):
    (tmp_path / "crashy_behaviour.py").write_text(CRASHY)
    monkeypatch.chdir(tmp_path)

    def scenario(bug: str) -> str:
        (tmp_path / f"{bug}.yaml").write_text(SCENARIO.format(bug=bug))
        return f"{bug}.yaml"

    yield scenario
    sys.modules.pop("crashy_behaviour", None)         # the next test's import registers it again


def run(*args):
    return main(["--import", "crashy_behaviour", *args])


def assert_empty_trajectory(npz) -> None:
    """Every per-sample array keeps its documented shape with T = 0 (object_pose was (0,), not (0, 3))."""
    arrays = np.load(npz)
    assert arrays["t"].shape == (0,) and arrays["robot_pose"].shape == (0, 3, 3)
    assert arrays["robot_alive"].shape == (0, 3) and arrays["robot_alive"].dtype == bool
    assert arrays["object_pose"].shape == (0, 3) and arrays["object_outline"].shape == (3, 2)


@pytest.mark.parametrize("bug, call", [("step_at_0", "robot 1, step(): RuntimeError: deliberate crash at "
                                                      "crashy_behaviour.py:19"),
                                       ("telemetry_at_0", "robot 0, telemetry(): ValueError: the hub could not")])
def test_a_crash_at_the_first_step_is_reported_with_its_plot_and_video(crashy, tmp_path, capsys, bug, call):
    """Plotting the run's zero samples raised IndexError in plots.py, so khepri's own traceback came out
    instead of the summary and the crash report."""
    assert run("sim", "run", crashy(bug), "--out", "out", "--video", "out/run.gif") == 1
    out, err = capsys.readouterr()
    assert "0.0 s simulated" in out and "stopped: crashed" in out and "video: out/run.gif" in out
    assert f"khepri: error: the run crashed: {call}" in err and "(at t = 0.0 s)" in err
    assert "Traceback" not in err
    assert_empty_trajectory(tmp_path / "out" / "trajectory.npz")
    assert (tmp_path / "out" / "trajectory.png").stat().st_size > 0


def test_sil_writes_a_crash_at_the_first_step_as_sim_run_does(crashy, tmp_path, capsys):
    assert run("sil", crashy("step_at_0"), "--no-record", "--out", "sil") == 1
    err = capsys.readouterr().err
    assert "agent 1: behaviour crashed: robot 1, step(): RuntimeError: deliberate crash" in err
    assert "Traceback" not in err
    assert json.loads((tmp_path / "sil" / "result.json").read_text())["stop_reason"] == "crashed"
    assert_empty_trajectory(tmp_path / "sil" / "trajectory.npz")
    assert (tmp_path / "sil" / "trajectory.png").stat().st_size > 0
