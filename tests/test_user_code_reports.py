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
        if self.params.bug == "tuple_key":
            self.robot.radio.broadcast({"v": {(1, 2): 3}})

    def telemetry(self):
        if self.params.bug == "telemetry_at_0":
            return {"seen": {1, 2}}
        return {"state": "ok"}


@register("crashy-at-once")
class CrashyAtOnce(Behaviour):
    def step(self):
        raise RuntimeError("deliberate crash")
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
def crashy(user_behaviour):
    return user_behaviour("crashy_behaviour", CRASHY, SCENARIO)


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
                                       ("telemetry_at_0", "robot 0, telemetry(): TypeError: telemetry['seen'] "
                                                          "is a set")])     # and where telemetry() is: below
def test_a_crash_at_the_first_step_is_reported_with_its_plot_and_video(crashy, tmp_path, capsys, bug, call):
    """Plotting the run's zero samples raised IndexError in plots.py, so khepri's own traceback came out
    instead of the summary and the crash report."""
    assert run("sim", "run", crashy(bug), "--out", "out", "--video", "out/run.gif") == 1
    out, err = capsys.readouterr()
    assert "0.0 s simulated" in out and "stopped: crashed" in out and "video: out/run.gif" in out
    assert f"khepri: error: the run crashed: {call}" in err and "(at t = 0.0 s)" in err
    assert "Traceback" not in err
    if bug == "telemetry_at_0":     # found after it returned, so no traceback points at the user's file: it did not
        assert "(returned by telemetry() at crashy_behaviour.py:23)" in err, err
    assert_empty_trajectory(tmp_path / "out" / "trajectory.npz")
    assert (tmp_path / "out" / "trajectory.png").stat().st_size > 0


def test_sil_writes_a_crash_at_the_first_step_as_sim_run_does(crashy, tmp_path, capsys):
    assert run("sil", crashy("step_at_0"), "--no-record", "--out", "sil") == 1
    err = capsys.readouterr().err
    assert "agent 1: behaviour crashed: robot 1, step(): RuntimeError: deliberate crash" in err
    assert "Traceback" not in err
    result = json.loads((tmp_path / "sil" / "result.json").read_text())
    assert result["stop_reason"] == "crashed"
    assert_empty_trajectory(tmp_path / "sil" / "trajectory.npz")
    assert (tmp_path / "sil" / "trajectory.png").stat().st_size > 0
    # The traceback, as `sim run` keeps it (from the agent's log: sil's result.json had none)
    assert run("sim", "run", crashy("step_at_0"), "--no-plot", "--out", "sim") == 1
    assert result["traceback"] == json.loads((tmp_path / "sim" / "result.json").read_text())["traceback"]
    assert result["traceback"][-1].startswith("RuntimeError: deliberate crash")


def test_the_traceback_shows_the_behaviours_own_line_under_khepris_checks(crashy, tmp_path, capsys):
    """A nested dict with a tuple key is refused six calls deep in the payload check: the traceback showed
    only sim_backend/hal.py and onboard/hal/payload.py, not the behaviour's broadcast; then both, khepri's
    frames a dozen lines of noise under the user's. Now the user's line, and a note for khepri's."""
    assert run("sim", "run", crashy("tuple_key"), "--no-plot", "--out", "out") == 1
    trace = json.loads((tmp_path / "out" / "result.json").read_text())["traceback"]
    assert 'crashy_behaviour.py", line 21, in step' in trace[0]
    assert 'self.robot.radio.broadcast({"v": {(1, 2): 3}})' in trace[0]
    assert trace[1] == "  (raised in khepri's code for that call, 7 frames further in, left out)", trace
    assert not [line for line in trace if "hal.py" in line or "payload.py" in line], trace
    assert trace[-1].startswith("onboard.hal.payload.RadioPayloadError: radio payload['v'] has the key (1, 2)")
    assert "\n".join(trace) in capsys.readouterr().err


@pytest.mark.parametrize("json_flag", [[], ["--json"]])
def test_bench_sim_says_a_crashed_behaviour_and_exits_1(crashy, capsys, json_flag):
    """It printed the figures of the short run as if it had run its time, exit code 0."""
    assert run("bench", "sim", "--robots", "4", "--seconds", "2", "--behaviour", "crashy-at-once", *json_flag) == 1
    out, err = capsys.readouterr()
    assert "khepri: error: 4 robots: the run crashed after 0 of the 2 simulated seconds: robot 0, step(): " \
           "RuntimeError: deliberate crash at crashy_behaviour.py:" in err
    if json_flag:
        [result] = json.loads(out)["results"]
        assert result["stop_reason"] == "crashed" and result["sim_seconds"] == 0


EVALUATOR = '''
from sim_backend.metrics import Evaluator, register_evaluator


@register_evaluator("crashy")
class CrashyEvaluator(Evaluator):
    steps = 0

    def __init__(self, scenario, world):
        super().__init__(scenario, world)
        if scenario.params.get("bug") == "evaluator_init":
            self.steps = int("many")

    def warnings(self, params):
        if params.bug == "evaluator_warnings":
            return [params.unknown]
        return []

    def on_step(self, time_s, telemetry):
        self.steps += 1
        if self.scenario.params.get("bug") == "on_step" and time_s > 0.25:
            1 / 0

    def result(self):
        return ODD_RESULTS.get(self.scenario.params.get("bug")) or {"per_step": 1 / self.steps}   # 0 steps: 1 / 0


ODD_RESULTS = {"result_seed": {"stop_reason": "great", "seed": 99}, "result_set": {"seen": {1, 2}},
               "result_list": [1, 2]}
'''


@pytest.fixture
def judged(crashy, tmp_path, monkeypatch):
    """The crashy behaviour with its evaluator, registered for this test only."""
    from sim_backend import metrics

    (tmp_path / "crashy_eval.py").write_text(EVALUATOR)
    monkeypatch.setattr(metrics, "_EVALUATORS", dict(metrics._EVALUATORS))
    yield crashy
    sys.modules.pop("crashy_eval", None)


def run_judged(*args):
    return run("--import", "crashy_eval", *args)


def test_an_evaluator_bug_names_the_evaluator_its_call_and_its_line(judged, tmp_path, capsys):
    """It read `the run crashed: ZeroDivisionError: division by zero (at t = 0.3 s)`: no evaluator, no line."""
    assert run_judged("sim", "run", judged("on_step"), "--no-plot", "--out", "out") == 1
    err = capsys.readouterr().err
    assert "khepri: error: the run crashed: evaluator CrashyEvaluator.on_step(): ZeroDivisionError: division " \
           "by zero at crashy_eval.py:22 (at t = 0.3 s)" in err
    assert "    1 / 0" in err
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    assert result["stop_reason"] == "crashed" and result["traceback"][-1] == "ZeroDivisionError: division by zero"


def test_an_evaluator_failing_after_a_behaviour_crash_is_kept_beside_it(judged, tmp_path, capsys):
    """The evaluator's result() failing after the behaviour's crash was dropped without a word."""
    assert run_judged("sim", "run", judged("step_at_0"), "--no-plot", "--out", "out") == 1
    err = capsys.readouterr().err
    assert "khepri: error: the run crashed: robot 1, step(): RuntimeError: deliberate crash" in err
    failure = "evaluator CrashyEvaluator.result(): ZeroDivisionError: division by zero at crashy_eval.py:25"
    assert f"khepri: error: the evaluator failed too: {failure}" in err
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    assert result["error"].startswith("robot 1, step(): ") and result["evaluation_error"] == failure


@pytest.mark.parametrize("bug, said", [
    ("result_seed", "'seed' is a result.json field the simulator writes"),
    ("result_set", "result()['seen'] is a set, which JSON cannot carry"),
    ("result_list", "returned a list, not a dict of result.json fields")])
def test_an_evaluator_result_that_result_json_cannot_hold_is_refused_by_its_field(judged, tmp_path, capsys,
                                                                                bug, said):
    """An evaluator's own `seed` replaced the run's (a study then failed with KeyError and later counted the
    run as finished), and a set in its result ended `sim run` in khepri's traceback with no result.json."""
    assert run_judged("sim", "run", judged(bug), "--no-plot", "--out", "out", "--time-limit", "0.5") == 1
    err = capsys.readouterr().err
    assert f"khepri: error: after the run (time limit): evaluator CrashyEvaluator.result(): TypeError: {said}" in err
    assert "Traceback" not in err
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    assert result["seed"] == 1 and result["stop_reason"] == "time limit" and said in result["error"]


def test_sil_names_an_evaluator_bug_as_sim_run_does(judged, tmp_path, capsys):
    assert run_judged("sil", judged("on_step"), "--no-plot", "--no-record", "--out", "sil") == 1
    assert "khepri: error: evaluator CrashyEvaluator.on_step(): ZeroDivisionError: division by zero at " \
           "crashy_eval.py:22 (at t = 0.3 s)" in capsys.readouterr().err
    assert json.loads((tmp_path / "sil" / "result.json").read_text())["stop_reason"] == "crashed"


@pytest.mark.parametrize("command", [["sim", "run"], ["sil"]])
@pytest.mark.parametrize("bug, call, line", [("evaluator_init", "__init__()", 12),
                                             ("evaluator_warnings", "warnings()", 16)])
def test_an_evaluator_bug_before_the_run_names_its_call_and_line(judged, capsys, command, bug, call, line):
    """An evaluator raising in __init__ or warnings(), before any step, ended in a bare Python traceback."""
    assert run_judged(*command, judged(bug), "--no-plot", "--out", "out") == 1
    err = capsys.readouterr().err
    assert f"khepri: error: the evaluator failed: evaluator CrashyEvaluator.{call}: " in err
    assert f"at crashy_eval.py:{line}" in err and "Traceback" not in err


@pytest.mark.parametrize("message, said", [
    ("{where}.speed_m_s: must be > 0", "params.speed_m_s: must be > 0"),      # was params: params.speed_m_s: ...
    ("{where}: speeds must add up", "params: speeds must add up"),
    ("too fast", "params: too fast"),
    ("params_speed: not a field of this record", "params: params_speed: not a field of this record"),
])
def test_a_validate_message_that_names_its_field_is_not_prefixed_again(message, said):
    from dataclasses import dataclass

    from onboard.behaviour import Behaviour, build_params
    from onboard.config import ConfigError

    @dataclass
    class Checked:
        speed_m_s: float = 0.1

        def validate(self, where):
            if self.speed_m_s <= 0:
                raise ValueError(message.format(where=where))

    class Checking(Behaviour):
        Params = Checked

        def step(self):
            pass

    with pytest.raises(ConfigError) as raised:
        build_params(Checking, {"speed_m_s": -1.0})
    assert str(raised.value) == said
