"""A user's behaviour with bugs: the simulator and SIL say which robot, which call and which line, keep the
results, stop the wheels, and keep one robot's mistakes from reaching the others outside the radio."""
import json
import math
import re

import numpy as np
import pytest

from khepri_cli.main import main
from onboard.behaviour import _REGISTRY, Behaviour, build_params, register
from onboard.config import ConfigError
from onboard.protocol import ProtocolError, decode
from sim_backend.runner import Simulation

BUGGY = '''
import math
import time
from dataclasses import dataclass, field
from typing import List

import numpy as np

from onboard.behaviour import Behaviour, register


def nested(depth: int) -> list:
    value = [(1,)]                      # a tuple, so that the value must be copied into plain JSON
    for _ in range(depth):
        value = [value]
    return value


@dataclass
class BuggyParams:
    bug: str = "none"
    speed_m_s: float = 0.1
    seen: List[int] = field(default_factory=list)


@register("buggy")
class Buggy(Behaviour):
    Params = BuggyParams

    def __init__(self, robot, params):
        super().__init__(robot, params)
        if params.bug == "init":
            raise RuntimeError("boom in init")

    def step(self):
        self.robot.wheels.set_speeds(self.params.speed_m_s, self.params.speed_m_s)
        late = self.robot.clock.now() > 0.5
        if self.params.bug == "step" and self.robot.id == 2 and late:
            [1, 2][5]
        if self.params.bug == "exit" and self.robot.id == 1 and late:
            raise SystemExit(3)
        if self.params.bug == "nan" and late:
            self.robot.radio.broadcast({"a": math.nan})
        if self.params.bug == "intkey" and late:
            self.robot.radio.broadcast({"bids": {3: 0.5}})
        if self.params.bug == "numpy" and 0.5 < self.robot.clock.now() < 0.65:
            self.robot.radio.broadcast({"xy": np.array([0.25, 1.5]), "n": np.int64(7), "t": (1, 2)})
        if self.params.bug == "numpy":
            self.params.seen.extend(message.payload["n"] for message in self.robot.radio.receive()
                                    if message.payload == {"xy": [0.25, 1.5], "n": 7, "t": [1, 2]})
        if self.params.bug == "nanwheels" and late:
            self.robot.wheels.set_speeds(math.nan, 0.1)
        if self.params.bug == "strwheels" and late:
            self.robot.wheels.set_speeds(0.1, "fast")
        if self.params.bug == "returns":
            return (0.1, 0.1)                # wheel speeds, as a user of another framework might
        if self.params.bug == "slow" and self.robot.id == 1 and 0.45 < self.robot.clock.now() < 0.55:
            time.sleep(0.3)                  # once: past the agent's 0.25 s step watchdog
        if self.params.bug == "set_broadcast" and late:        # a long error: the payload's path to the set
            self.robot.radio.broadcast({"summary": {"neighbours_seen": [{"id": 1, "ids_heard": {1, 2}}]}})
        if self.params.bug == "deep_broadcast" and late:
            self.robot.radio.broadcast({"a": nested(600)})
        if self.params.bug == "columns":
            self.robot.range_and_bearing.neighbours().ids[:] = 0
        if self.params.bug == "hang" and self.robot.id == 1 and late:
            while True:                      # waits for a message that only the next step could bring
                try:
                    self.robot.radio.receive()
                except Exception:
                    pass
        if self.params.bug == "share":
            self.params.seen.append(self.robot.id)
            if self.robot.id == 0:
                self.params.speed_m_s = 0.0

    def telemetry(self):
        if self.params.bug == "telemetry_list":
            return [1, 2]
        if self.params.bug == "deep_telemetry" and self.robot.clock.now() > 0.5:
            return {"a": nested(600)}
        if self.params.bug == "set" and self.robot.clock.now() > 0.5:
            return {"state": "ok", "neighbours": {1, 2}}       # a set: fine in Python, not on the wire
        if self.params.bug == "list_state" and self.robot.clock.now() > 0.5:
            return {"state": ["search", "push"]}                # a list: JSON, but no state the hub shows
        if self.params.bug == "intkey_telemetry":
            return {"state": "ok", "heard": {self.robot.id: 1.5, None: np.int64(2)}}   # JSON writes keys as str
        return {"state": "ok", "seen": len(self.params.seen), "numpy": np.float32(1.5), "x": math.nan}

    @property
    def finished(self):
        if self.params.bug == "finished":
            raise RuntimeError("bug in finished")
        return False

    def stop(self):
        super().stop()
        if self.params.bug == "stop":
            raise RuntimeError("bug in stop")
'''

SCENARIO = """name: buggy
behaviour: buggy
params: {{bug: {bug}}}
robots: {{count: 3, spawn: {{x: [-0.5, 0.5], y: [-0.5, 0.5]}}}}
arena: {{walls: [-2, -2, 2, 2]}}
time_limit_s: 2
"""


@pytest.fixture
def buggy(user_behaviour):
    return user_behaviour("buggy_behaviour", BUGGY, SCENARIO)


def run(*args):
    return main(["--import", "buggy_behaviour", *args])


def test_a_crash_names_the_robot_the_call_and_the_line_and_keeps_the_results(buggy, tmp_path, capsys):
    assert run("sim", "run", buggy("step"), "--no-plot", "--out", "out") == 1
    err = capsys.readouterr().err
    assert "the run crashed: robot 2, step(): IndexError: list index out of range at buggy_behaviour.py:" in err
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    assert result["stop_reason"] == "crashed" and result["sim_time_s"] == pytest.approx(0.6)
    assert result["traceback"][-1] == "IndexError: list index out of range"
    assert (tmp_path / "out" / "trajectory.npz").is_file()


def test_an_init_or_stop_that_raises_is_reported_without_losing_the_run(buggy, tmp_path, capsys):
    assert run("sim", "run", buggy("init"), "--no-plot", "--out", "init") == 1
    assert "the behaviour failed: robot 0, Buggy.__init__: RuntimeError: boom in init" in capsys.readouterr().err
    assert run("sim", "run", buggy("stop"), "--no-plot", "--out", "stop") == 1
    err = capsys.readouterr().err         # the run reached its time limit; then stop() raised
    assert "khepri: error: after the run (time limit): robot 0, stop(): RuntimeError: bug in stop" in err
    assert run("sim", "run", buggy("finished"), "--no-plot", "--out", "finished") == 1     # was "telemetry()"
    assert "the run crashed: robot 0, finished: RuntimeError: bug in finished at buggy_behaviour.py:" in \
        capsys.readouterr().err
    result = json.loads((tmp_path / "stop" / "result.json").read_text())
    assert result["sim_time_s"] == pytest.approx(2.0)           # the whole run, written


def test_a_hung_step_is_stopped_by_the_wall_limit_and_named_with_the_results_kept(buggy, tmp_path, capsys):
    """A step() that never returns used to hold `sim run` (and a study's worker) forever."""
    assert run("sim", "run", buggy("hang"), "--no-plot", "--out", "out", "--wall-limit", "1.5") == 1
    err = capsys.readouterr().err
    assert "the run was stopped: wall-clock limit of 1.5 s reached while robot 1's step() at buggy_behaviour.py:" \
        in err and "(at t = 0.6 s)" in err
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    assert result["stop_reason"] == "wall-clock limit" and result["sim_time_s"] == pytest.approx(0.6)
    assert np.load(tmp_path / "out" / "trajectory.npz")["t"].shape == (6,)


def test_ctrl_c_keeps_what_was_recorded_and_says_which_step_was_running(buggy, tmp_path, capsys):
    import os
    import signal
    import threading

    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "run.gif").write_bytes(b"GIF89a")       # an earlier run's video, not rewritten
    threading.Timer(2.0, os.kill, (os.getpid(), signal.SIGINT)).start()
    # The wall limit is a backstop: should the signal be lost, the test fails instead of hanging the suite.
    assert run("sim", "run", buggy("hang"), "--no-plot", "--out", "out", "--video", "out/run.gif",
               "--wall-limit", "30") == 130
    err = capsys.readouterr().err
    assert "khepri: interrupted (Ctrl-C) while robot 1's step() at buggy_behaviour.py:" in err
    assert "khepri: no video written (interrupted); out/run.gif is from an earlier run" in err
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    assert result["stop_reason"] == "interrupted" and result["sim_time_s"] == pytest.approx(0.6)


def test_a_study_records_a_hung_run_as_failed_and_runs_the_others(buggy, tmp_path, capsys):
    for bug in ("hang", "none"):
        (tmp_path / f"{bug}.yaml").write_text(SCENARIO.format(bug=bug).replace("name: buggy", f"name: {bug}"))
    (tmp_path / "study.yaml").write_text("name: hangs\nscenarios: [hang.yaml, none.yaml]\nseeds: [1]\n")
    assert run("study", "study.yaml", "--out", "st", "--workers", "2", "--wall-limit", "3", "--no-figures") == 1
    hung = json.loads((tmp_path / "st" / "hang" / "seed-1" / "result.json").read_text())
    assert hung["failed"] and hung["stop_reason"] == "wall-clock limit"
    assert "robot 1's step() at buggy_behaviour.py:" in hung["error"]
    fine = json.loads((tmp_path / "st" / "none" / "seed-1" / "result.json").read_text())
    assert not fine["failed"] and fine["stop_reason"] == "time limit"
    assert "wall-clock limit of 3 s reached" in (tmp_path / "st" / "report.md").read_text()


def test_nan_in_a_broadcast_is_refused_as_the_wire_would(buggy, capsys):
    assert run("sim", "run", buggy("nan"), "--no-plot", "--out", "nan") == 1
    assert "step(): RadioPayloadError: radio payload['a'] is nan, which JSON cannot carry" in capsys.readouterr().err
    message = b'{"v": 2, "type": "broadcast", "id": 3, "sent_s": 1.0, "payload": {"a": [1, NaN]}}'
    with pytest.raises(ProtocolError, match="from robot 3: broadcast.payload: radio payload is not JSON: Out of range"):
        decode(message, "robot 3")


def test_an_error_raised_by_the_hal_points_at_the_behaviours_call(buggy, capsys):
    """The line shown was the HAL's check (hal.py), not the behaviour's call that passed the NaN."""
    assert run("sim", "run", buggy("nanwheels"), "--no-plot", "--out", "nanwheels") == 1
    err = capsys.readouterr().err
    assert "step(): ValueError: set_speeds(left_m_s=nan): wheel speeds must be finite numbers (m/s) at " \
           "buggy_behaviour.py:" in err
    # Not Python's "must be real number, not str", which named neither the call nor the wheel.
    assert run("sim", "run", buggy("strwheels"), "--no-plot", "--out", "strwheels") == 1
    assert "step(): ValueError: set_speeds(right_m_s='fast'): wheel speeds must be finite numbers (m/s) at " \
           "buggy_behaviour.py:" in capsys.readouterr().err
    assert run("sim", "run", buggy("nan"), "--no-plot", "--out", "nan") == 1      # a broadcast the wire refuses
    assert "which JSON cannot carry; send None or leave it out at buggy_behaviour.py:" in capsys.readouterr().err


@pytest.mark.parametrize("bug, said", [
    ("deep_broadcast", "step(): RadioPayloadError: radio payload nests lists or mappings hundreds of levels deep"),
    ("deep_telemetry", "telemetry(): TypeError: telemetry nests lists or mappings hundreds of levels deep"),
])
def test_a_payload_nested_hundreds_deep_is_the_behaviours_error_not_a_crash_of_the_run(buggy, capsys, bug, said):
    """Copying it for the wire recursed: RecursionError ended the run as 'the run crashed', naming neither the
    robot nor the call."""
    assert run("sim", "run", buggy(bug), "--no-plot", "--out", bug) == 1
    err = capsys.readouterr().err
    assert said in err and "robot 0" in err, err


def test_a_broadcast_names_the_field_json_would_change_and_takes_numpy(buggy, capsys):
    """An int key arrived as a string (the receiver's payload[3] failed far away); numpy was refused in a
    broadcast while telemetry took it."""
    assert run("sim", "run", buggy("intkey"), "--no-plot", "--out", "intkey") == 1
    assert "radio payload['bids'] has the key 3 (int); JSON keys are strings" in capsys.readouterr().err
    from onboard.plugins import import_user_modules
    from sim_backend.scenario import load_scenario

    import_user_modules(["buggy_behaviour"])
    sim = Simulation(load_scenario(buggy("numpy")))
    sim.run(time_limit_s=1.0)
    assert all(b.params.seen and set(b.params.seen) == {7} for b in sim.behaviours)   # arrived as plain JSON


def test_the_agents_radio_checks_a_payload_as_the_simulators_does():
    from onboard.agent.devices import HubRadio, HubState
    from onboard.hal.payload import RadioPayloadError

    sent = []
    radio = HubRadio(HubState(), type("Clock", (), {"now": lambda self: 1.0})(), sent.append, robot_id=4)
    radio.broadcast({"xy": np.array([0.25, 1.5]), "tags": ("a",), "nested": {"k": [np.float32(0.5)]}})
    assert sent[0]["payload"] == {"xy": [0.25, 1.5], "tags": ["a"], "nested": {"k": [0.5]}}
    for bad, words in [({"a": {1, 2}}, "radio payload['a'] is a set"),
                       ({"a": [0.0, math.inf]}, "radio payload['a'][1] is inf"),
                       ({"a": {2: 1}}, "has the key 2 (int)"),
                       ({"a": object()}, "radio payload['a'] is an object, which")]:
        with pytest.raises(RadioPayloadError, match=words.replace("[", r"\[").replace("(", r"\(").replace(")", r"\)")):
            radio.broadcast(bad)
    with pytest.raises(TypeError, match="^radio payload must be a mapping, got list"):
        radio.broadcast([1, 2])
    assert len(sent) == 1


def test_telemetry_the_wire_cannot_carry_fails_in_simulation_too(buggy, capsys):
    """A set in telemetry ran fine in sim run and study, then stopped every agent at t = 0 in sil."""
    assert run("sim", "run", buggy("set"), "--no-plot", "--out", "set") == 1
    err = capsys.readouterr().err
    assert "robot 0, telemetry(): TypeError: telemetry['neighbours'] is a set, which JSON cannot carry" in err
    assert "onboard/behaviour.py" not in err and " at behaviour.py" not in err    # no line of khepri's own,
    assert "(returned by telemetry() at buggy_behaviour.py:" in err                 # but the user's method
    assert run("sim", "run", buggy("none"), "--no-plot", "--out", "none") == 0   # numpy and NaN are fine


def test_sil_names_the_telemetry_field_the_wire_cannot_carry_as_sim_run_does(buggy, tmp_path, capsys):
    """sil said only `agent 0: telemetry() cannot be sent: cannot encode: Object of type set is not JSON
    serializable`: not which field, and not as the crash `sim run` reported for the same telemetry."""
    assert run("sil", buggy("set"), "--no-plot", "--no-record", "--out", "sil-set") == 1
    err = capsys.readouterr().err
    assert "agent 0: behaviour crashed: robot 0, telemetry(): TypeError: telemetry['neighbours'] is a set, which " \
        "JSON cannot carry: send dicts, lists, strings, numbers, booleans or None (returned by telemetry() at " \
        "buggy_behaviour.py:" in err and ") (at t = " in err                                      # whole, not cut
    assert json.loads((tmp_path / "sil-set" / "result.json").read_text())["stop_reason"] == "crashed"


def test_a_state_the_hub_would_drop_is_named_in_sim_run_and_by_the_agent_in_sil(buggy, tmp_path, capsys):
    """The hub drops telemetry whose state is a list (docs/protocol.md): the agent sent it anyway, and the robot
    went silent at the hub, while sim run took it. Both now name the field, as for a set."""
    assert run("sim", "run", buggy("list_state"), "--no-plot", "--out", "list") == 1
    said = "telemetry['state'] must be a string of at most 200 characters, a number or null (got ['search', 'push'])"
    assert f"robot 0, telemetry(): ValueError: the hub could not be sent this telemetry, so every agent in a lab " \
        f"would stop on it: {said}" in capsys.readouterr().err
    assert run("sil", buggy("list_state"), "--no-plot", "--no-record", "--out", "sil-list") == 1
    err = capsys.readouterr().err
    assert "telemetry() cannot be sent: behaviour.state: must be a string of at most 200 characters" in err, err
    assert json.loads((tmp_path / "sil-list" / "result.json").read_text())["stop_reason"] == "crashed"


def test_a_step_slower_than_the_agents_watchdog_is_said_once_in_sim_run(buggy, tmp_path, capsys):
    """`time.sleep(0.5)` in step() ran at 0.05x real time without a word in sim run; the agent on a robot stops
    the wheels after 0.25 s of one step()."""
    assert run("sim", "run", buggy("slow"), "--no-plot", "--out", "slow") == 0
    said = [line for line in capsys.readouterr().err.splitlines() if "step() took" in line]
    assert len(said) == 1 and said[0].startswith("khepri: warning: robot 1's step() took 0.3")
    assert "at t = 0.5 s (said once a run): on a robot the agent's step watchdog stops the wheels" in said[0]
    warnings = json.loads((tmp_path / "slow" / "result.json").read_text())["warnings"]
    assert said[0].removeprefix("khepri: warning: ") in warnings


def test_a_step_that_returns_something_is_told_its_return_value_is_ignored(buggy, tmp_path, capsys):
    """A step() returning wheel speeds instead of calling set_speeds ran with the robots standing still, without
    a word; said once a run, in sim run and by each agent."""
    told = "step() returned (0.1, 0.1) (said once a run): its return value is ignored; drive the wheels with " \
           "self.robot.wheels.set_speeds(left_m_s, right_m_s)"
    assert run("sim", "run", buggy("returns"), "--no-plot", "--out", "returns") == 0
    assert [line for line in capsys.readouterr().err.splitlines() if "returned" in line] == [
        f"khepri: warning: robot 0's {told}"]
    assert run("sil", buggy("returns"), "--no-plot", "--no-record", "--time-limit", "0.5", "--out", "sil") == 0
    logged = (tmp_path / "sil" / "agents" / "agent-2.log").read_text().splitlines()
    assert [line for line in logged if "returned" in line] == [f"agent 2: warning: {told}"]


def test_sil_tells_a_long_crash_whole_with_its_file_and_time(buggy, capsys):
    """The agent's telemetry cuts its error to the protocol's 200 characters: sil said `... send dicts with
    string keys, lists, strings, numbe` and lost where and when; it takes the whole line from the agent's log."""
    assert run("sil", buggy("set_broadcast"), "--no-plot", "--no-record", "--out", "sil-set-broadcast") == 1
    err = capsys.readouterr().err
    assert "step(): RadioPayloadError: radio payload['summary']['neighbours_seen'][0]['ids_heard'] is a set, " \
        "which JSON cannot carry; send dicts with string keys, lists, strings, numbers, booleans or None at " \
        "buggy_behaviour.py:" in err, err


def test_an_evaluator_gets_telemetry_keys_as_the_strings_sil_delivers(buggy):
    """`{robot_id: x}` in telemetry reached `sim run`'s evaluator with int keys and sil's (over JSON) with
    str keys, so an evaluator that worked in one raised KeyError in the other."""
    from onboard.behaviour import is_plain_json
    from onboard.plugins import import_user_modules
    from sim_backend.scenario import load_scenario

    assert not is_plain_json({1: "a"}) and not is_plain_json({"a": {None: 1}})
    import_user_modules(["buggy_behaviour"])
    sim = Simulation(load_scenario(buggy("intkey_telemetry")))
    sim.run(time_limit_s=0.3)
    assert [t["heard"] for t in sim.telemetry] == [{"0": 1.5, "null": 2}, {"1": 1.5, "null": 2},
                                                  {"2": 1.5, "null": 2}]
    assert json.loads(json.dumps(sim.telemetry)) == sim.telemetry          # what the wire would deliver


def test_a_behaviour_cannot_reach_other_robots_through_its_params_or_sensor_columns(buggy, capsys):
    from onboard.plugins import import_user_modules
    from sim_backend.scenario import load_scenario

    import_user_modules(["buggy_behaviour"])
    sim = Simulation(load_scenario(buggy("share")))
    sim.run(time_limit_s=1.0)
    assert [b.params.speed_m_s for b in sim.behaviours] == [0.0, 0.1, 0.1]   # robot 0 changed only its own
    assert [len(b.params.seen) for b in sim.behaviours] == [10, 10, 10]
    assert run("sim", "run", buggy("columns"), "--no-plot", "--out", "columns") == 1
    assert "ValueError: assignment destination is read-only" in capsys.readouterr().err


def test_sil_reports_a_stop_that_raises_as_sim_run_does(buggy, tmp_path, capsys):
    """The agent logged it and stopped the wheels, and sil exited 0 without a word."""
    assert run("sil", buggy("stop"), "--no-plot", "--no-record", "--out", "sil-stop") == 1
    assert "khepri: error: after the run: agent 0: robot 0, stop(): RuntimeError: bug in stop" in \
        capsys.readouterr().err
    result = json.loads((tmp_path / "sil-stop" / "result.json").read_text())
    assert result["stop_reason"] == "time limit" and "stop(): RuntimeError: bug in stop" in result["error"]


def test_sil_reports_the_crashed_agent_and_stops(buggy, tmp_path, capsys):
    assert run("sil", buggy("step"), "--no-plot", "--no-record", "--out", "sil") == 1
    err = capsys.readouterr().err
    assert "agent 2: behaviour crashed: robot 2, step(): IndexError: list index out of range" in err
    result = json.loads((tmp_path / "sil" / "result.json").read_text())
    assert result["stop_reason"] == "crashed" and result["sim_time_s"] < 1.0
    assert result["sil"]["agent_exit_codes"][2] == 1          # as lab.md says: it was listed as -15 (SIGTERM)
    log = (tmp_path / "sil" / "agents" / "agent-2.log").read_text()
    assert "[1, 2][5]" in log                                     # the traceback is in the agent's log


def test_sys_exit_in_step_is_a_crash_named_like_any_other_in_sim_and_sil(buggy, tmp_path, capsys):
    """It ended `sim run` silently with the exit's code and no result, and `sil` said the run went to its time
    limit."""
    assert run("sim", "run", buggy("exit"), "--no-plot", "--out", "out") == 1
    assert "the run crashed: robot 1, step(): SystemExit: 3 at buggy_behaviour.py:" in capsys.readouterr().err
    assert json.loads((tmp_path / "out" / "result.json").read_text())["stop_reason"] == "crashed"
    assert run("sil", buggy("exit"), "--no-plot", "--no-record", "--out", "sil") == 1
    assert "agent 1: behaviour crashed: robot 1, step(): SystemExit: 3" in capsys.readouterr().err
    assert json.loads((tmp_path / "sil" / "result.json").read_text())["stop_reason"] == "crashed"


def test_telemetry_that_is_not_a_dict_is_said_so(buggy, tmp_path, capsys):
    assert run("sim", "run", buggy("telemetry_list"), "--no-plot", "--out", "tl") == 1
    said = capsys.readouterr().err
    # Where: a value found wrong after telemetry() returned has no traceback leading to the user's line.
    assert "robot 0, telemetry(): TypeError: telemetry() must return a dict (got list) (returned by telemetry() at " \
        "buggy_behaviour.py:" in said, said


PLAIN_TELEMETRY = {"state": "ok", "seen": 0, "numpy": 1.5, "x": None, "finished": False}   # the buggy one's


def test_the_simulators_evaluator_gets_telemetry_as_plain_json_as_sils_does(buggy):
    """`sim run`'s evaluator got the behaviour's NaN and numpy values, sil's the None and floats its agents
    sent: an evaluator reading a NaN field worked in one and failed in the other."""
    from onboard.plugins import import_user_modules
    from sim_backend.scenario import load_scenario

    import_user_modules(["buggy_behaviour"])
    sim = Simulation(load_scenario(buggy("none")))
    sim.run(time_limit_s=0.5)
    assert sim.telemetry == [PLAIN_TELEMETRY] * 3                 # what evaluator.on_step was given
    assert type(sim.telemetry[0]["numpy"]) is float


def test_only_plain_json_telemetry_skips_the_copy():
    from onboard.behaviour import is_plain_json

    assert is_plain_json({"a": 1, "b": [0.5, "x", None, True], "c": {"d": -2.0}})
    for odd in (math.inf, -math.inf, [math.nan], {"d": [1.0, math.nan]}, np.float64(0.5), (1, 2), {1, 2}):
        assert not is_plain_json({"a": odd}), odd


def test_sil_agents_send_numpy_and_nan_telemetry_as_plain_json(buggy, tmp_path, capsys):
    assert run("sil", buggy("none"), "--no-plot", "--no-record", "--out", "sil-ok") == 0
    result = json.loads((tmp_path / "sil-ok" / "result.json").read_text())
    assert result["telemetry"] == [PLAIN_TELEMETRY] * 3
    assert result["stop_reason"] == "time limit" and result["sil"]["step_timeouts"] == 0
    moved = np.load(tmp_path / "sil-ok" / "trajectory.npz")["robot_pose"]
    assert np.hypot(*(moved[-1, :, :2] - moved[0, :, :2]).T).min() > 0.1


def test_params_mistakes_and_name_clashes_are_config_errors():
    class NotADataclass(Behaviour):
        Params = dict

    with pytest.raises(ConfigError, match="NotADataclass.Params must be a dataclass"):
        build_params(NotADataclass, {})
    from dataclasses import dataclass

    @dataclass
    class Checked:
        speed: float = 0.1

        def validate(self, where):
            if self.speed > 1:
                raise ValueError("too fast")

    class Fussy(Behaviour):
        Params = Checked

        def step(self):
            pass

    with pytest.raises(ConfigError, match="params: too fast"):
        build_params(Fussy, {"speed": 2.0})
    with pytest.raises(ConfigError, match="the behaviour name 'transport' is taken by"):
        register("transport")(Fussy)

    class Lazy(Behaviour):
        def step(self):
            yield

    with pytest.raises(ConfigError, match=r"Lazy.step contains `yield`: it would never run"):
        register("lazy")(Lazy)

    class Idle(Behaviour):
        pass

    with pytest.raises(ConfigError, match=r"Idle has no step\(self\): define it"):
        register("idle")(Idle)
    assert math.isfinite(build_params(Fussy, {}).speed)


def test_register_refuses_what_would_fail_only_once_a_run_started():
    """Each of these registered, then crashed every robot at t = 0 (a signature), ran with the robots standing
    still and only Python's `never awaited` warning (async), or failed in the scenario check naming khepri's
    code (`type object 'A' has no attribute 'Params' at behaviour.py`)."""
    class Eager(Behaviour):
        async def step(self):
            pass

    class Ported(Behaviour):
        def step(self, robot, dt):
            pass

    class Narrow(Behaviour):
        def __init__(self, robot):
            super().__init__(robot)

        def step(self):
            pass

    class Plain:
        def step(self):
            pass

    refusals = {Eager: r"Eager.step is `async def`: it would never run",
                Ported: r"Ported.step must be step\(self\); it is step\(self, robot, dt\) \(at test_behaviour_errors",
                Narrow: r"Narrow.__init__ must be __init__\(self, robot, params=None\), calling super\(\).__init__\("
                        r"robot, params\); it is __init__\(self, robot\)",
                Plain: r"Plain is not a Behaviour: write `class Plain\(Behaviour\):`"}
    for cls, refusal in refusals.items():
        with pytest.raises(ConfigError, match=refusal):
            register("test-refused")(cls)
    assert "test-refused" not in _REGISTRY

    class Flexible(Behaviour):             # any signature a call with (robot, params) fits is fine
        def __init__(self, robot, *args, **kwargs):
            super().__init__(robot, *args, **kwargs)

        def step(self, *unused):
            pass

    try:
        assert register("test-flexible")(Flexible) is Flexible
    finally:
        _REGISTRY.pop("test-flexible", None)


RANDOM_WALK = '''
import random

from onboard.behaviour import Behaviour, register


@register("random-walk")
class RandomWalk(Behaviour):
    def step(self):
        self.robot.wheels.set_speeds(random.uniform(0.0, 0.2), random.uniform(0.0, 0.2))
'''


def test_sil_runs_of_a_behaviour_that_uses_random_repeat(tmp_path, monkeypatch):
    (tmp_path / "random_walk.py").write_text(RANDOM_WALK)
    (tmp_path / "walk.yaml").write_text(SCENARIO.replace("buggy", "random-walk").format(bug="none")
                                        .replace("params: {bug: none}\n", ""))
    monkeypatch.chdir(tmp_path)
    ends = []
    for out in ("a", "b"):
        assert main(["--import", "random_walk", "sil", "walk.yaml", "--no-plot", "--no-record", "--out", out]) == 0
        ends.append(np.load(tmp_path / out / "trajectory.npz")["robot_pose"][-1])
    assert np.array_equal(ends[0], ends[1])


SLEEPY = '''
import time

from onboard.behaviour import Behaviour, register


@register("sleepy")
class Sleepy(Behaviour):
    def step(self):
        if self.robot.id == 0 and abs(self.robot.clock.now() - 0.3) < 0.05:
            time.sleep(0.4)
        self.robot.wheels.set_speeds(0.1, 0.1)
'''


def test_a_step_slower_than_the_watchdog_is_named_as_the_cause(tmp_path, monkeypatch):
    (tmp_path / "sleepy.py").write_text(SLEEPY)
    scenario = SCENARIO.replace("buggy", "sleepy").format(bug="none").replace("params: {bug: none}\n", "")
    (tmp_path / "sleepy.yaml").write_text(scenario.replace("time_limit_s: 2", "time_limit_s: 1"))
    monkeypatch.chdir(tmp_path)
    assert main(["--import", "sleepy", "sil", "sleepy.yaml", "--no-plot", "--no-record", "--out", "out"]) == 0
    log = (tmp_path / "out" / "agents" / "agent-0.log").read_text()
    # The step sleeps 0.4 s; on a loaded machine it takes longer (0.5 s or more once in a full suite), never less.
    took = re.search(r"the behaviour's step took (\d+\.\d+) s, longer than the 0\.25 s watchdog", log)
    assert took and float(took.group(1)) >= 0.4, log
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    # The step held its frames, not what the agent sends: nothing was left unsent (a count held only once the hub
    # has spoken, so the hellos before the connection are not in it either). `>= 0` held for any count.
    assert result["sil"]["dropped"]["unsent_at_agents"] == 0, result["sil"]["dropped"]


def test_a_wheel_speed_too_large_for_a_float_is_refused_as_a_nan_is():
    """10 ** 400 raised OverflowError from math.isfinite, not the ValueError that names the wheel."""
    from onboard.hal.devices import commanded_wheel_speeds

    with pytest.raises(ValueError, match=r"set_speeds\(right_m_s=1000+\): wheel speeds must be finite numbers"):
        commanded_wheel_speeds(0.1, 10 ** 400, 0.8)
