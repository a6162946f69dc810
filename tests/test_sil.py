"""Software in the loop, end to end: the hub's sim source and one real agent process per robot over loopback
CURVE sockets run lab-6 and lab-6-payload in lockstep; evaluated like `khepri sim run`, with the MCAP log beside it."""
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hub.log_summary import summarise
from hub.recording import read_log
from hub.sil import SilOptions, run_sil
from sim_backend.scenario import load_scenario


@pytest.mark.parametrize("name", ["lab-6", "lab-6-payload"])
def test_sil_lab6_cages_and_reaches_every_waypoint(tmp_path, name):
    scenario = load_scenario(name)
    result = run_sil(scenario, tmp_path, SilOptions(plot=False))
    print(json.dumps({k: v for k, v in result.items() if k != "waypoints"}, indent=1))
    assert "error" not in result
    assert result["caged"] is True and result["completed"] is True, result["failures"]
    assert [w["index"] for w in result["waypoints"]] == list(range(len(scenario.path)))
    assert result["final_position_error_m"] <= 0.05
    sil = result["sil"]
    assert sil["lockstep"] and sil["agents"] == 6 and sil["agent_exit_codes"] == [0] * 6
    assert sil["step_timeouts"] == 0 and sil["missing_answers"] == 0
    assert sil["dropped"]["hub_rejected"] == {} and sil["dropped"]["frames_lost_at_agents"] == 0
    assert result["radio"]["delivered"] > 0

    saved = json.loads((tmp_path / "result.json").read_text())
    assert saved["caged"] is True and saved["sil"]["latency_ms"]["p50"] > 0
    arrays = np.load(tmp_path / "trajectory.npz")
    assert arrays["robot_pose"].shape == (len(arrays["t"]), 6, 3)
    topics = {record.topic for record in read_log(tmp_path / "hub.mcap")}
    assert {"/mocap/poses", "/robot/0/frame", "/robot/5/telemetry", "/robot/3/broadcast", "/robot/1/command",
            "/control"} <= topics
    # The hub tells the run's outcome from sil's own evaluator, in its log and on its console (hub.log).
    runs = summarise(tmp_path / "hub.mcap").runs
    assert [(r["outcome"], r["end_cause"], r["ended_by"]) for r in runs] == [("completed", "stop", "sil")]
    assert runs[0]["arrived_s"] is not None and runs[0]["object"]["reached"] == len(scenario.path)
    assert f"hub: run {runs[0]['run_id']} stopped by sil: completed; object at (" in (tmp_path / "hub.log").read_text()


def test_a_clean_short_run_reports_no_drop(tmp_path):
    """Every clean run reported a few messages the agents could not send: the hellos an agent says at once,
    before its connection is up. Those lose nothing, so a clean run now says `dropped: nothing`."""
    from hub.sil_report import sil_summary_lines

    result = run_sil(load_scenario("lab-6"), tmp_path, SilOptions(plot=False, record=False, time_limit_s=2.0))
    dropped = result["sil"]["dropped"]
    assert dropped["unsent_at_agents"] == 0 and dropped["hub_rejected"] == {}
    assert sil_summary_lines(result["sil"])[1] == "  dropped: nothing"


def test_the_warnings_go_by_the_time_limit_the_run_gets(tmp_path):
    """`khepri sil x.yaml --time-limit 2` with a fault at 100 s and the scenario's 60 s warned that the fault was
    not before the time limit (60 s), and with --time-limit 120 warned that it never fires, although it does:
    the preflight read the scenario's own limit. `sim run` goes by --time-limit."""
    from sim_backend.scenario import Fault

    lab6 = load_scenario("lab-6")
    scenario = lab6.with_overrides(robots=dataclasses.replace(lab6.robots, count=3), time_limit_s=60.0,
                                   faults=[Fault(robot=1, at_s=100.0)],
                                   comm=dataclasses.replace(lab6.comm, latency_s=0.3),
                                   sensors=dataclasses.replace(lab6.sensors, pose_dropout=0.6))
    result = run_sil(scenario, tmp_path, SilOptions(plot=False, record=False, time_limit_s=1.0))
    assert [w for w in result.get("warnings", []) if w.startswith("faults")] == [
        "faults[0].at_s: 100 s is not before the time limit (1 s): robot 1 never fails"]
    # The hub relays with the next frame: a radio delay the scenario asks for was ignored without a word.
    assert [w for w in result["warnings"] if w.startswith("comm.latency_s (0.3 s) is not simulated by the hub's")]
    # Nor were lost poses: a behaviour's code for a missing pose never ran in sil, and nothing said so.
    (dropout,) = [w for w in result["warnings"] if w.startswith("sensors.pose_dropout (0.6) is not simulated")]
    assert "source.stale_s" in dropout and "held" in dropout
    hub_log = (tmp_path / "hub.log").read_text()
    assert hub_log.count("sensors.pose_dropout (0.6) is not simulated") == 1, hub_log     # was said twice


def test_a_transport_scenario_without_an_object_is_refused_naming_the_scenarios_object(tmp_path):
    """It was refused naming `run.params.object_estimate`, a key of a lab config the user of sil never wrote."""
    from onboard.config import ConfigError

    lab6 = load_scenario("lab-6")
    scenario = lab6.with_overrides(object=None, path=[])
    (tmp_path / "result.json").write_text('{"stop_reason": "behaviour finished"}')     # the last run's
    with pytest.raises(ConfigError) as info:
        run_sil(scenario, tmp_path, SilOptions(plot=False, record=False, time_limit_s=1.0))
    # Refused before anything in the folder was touched: the last run's results were cleared away first.
    assert (tmp_path / "result.json").read_text() == '{"stop_reason": "behaviour finished"}'
    assert not (tmp_path / "hub.log").exists()
    assert info.value.field == "object" and info.value.problem.startswith(
        "lab-6 has none, and the transport behaviour needs to know where one starts to run through a hub "
        "(`khepri hub` or `khepri sil`): give the scenario an object")


def test_a_realtime_run_stops_at_its_time_limit_as_lockstep_does(tmp_path):
    """`khepri sil ... --realtime --time-limit 2` wrote sim_time_s 2.1 and a 21st sample at t = 2.0: the step
    that began at the limit was observed. Lockstep and `sim run` give 2.0 s and 20 samples (t = 0 .. 1.9)."""
    lab6 = load_scenario("lab-6")
    scenario = lab6.with_overrides(robots=dataclasses.replace(lab6.robots, count=3))
    result = run_sil(scenario, tmp_path, SilOptions(plot=False, record=False, realtime=True, time_limit_s=2.0))
    assert "error" not in result and result["stop_reason"] == "time limit"
    assert result["sim_time_s"] == pytest.approx(2.0)
    t = np.load(tmp_path / "trajectory.npz")["t"]
    assert len(t) == 20 and t[-1] == pytest.approx(1.9)
    # Physics starts once the agents are there: the hub used to warn of no frame while they started.
    assert "no motion-capture frame yet" not in (tmp_path / "hub.log").read_text()


def test_a_slow_scenario_gets_a_hub_watchdog_its_telemetry_can_feed(tmp_path):
    """At 5 Hz an agent speaks every 0.2 s, and the default watchdog_s (0.3 s) is refused for that: sil, whose
    config the user does not write, stopped with that error before it sets the watchdog from the scenario."""
    lab6 = load_scenario("lab-6")
    scenario = lab6.with_overrides(physics=dataclasses.replace(lab6.physics, control_hz=5.0))
    result = run_sil(scenario, tmp_path, SilOptions(plot=False, record=False, time_limit_s=2.0))
    assert "error" not in result and result["sil"]["agent_exit_codes"] == [0] * 6
    assert result["sil"]["step_timeouts"] == 0 and result["sil"]["missing_answers"] == 0


def test_a_robot_killed_by_a_fault_has_null_telemetry_as_in_sim_run(tmp_path):
    """`sim run` wrote `null` for a dead robot's telemetry, sil what the hub last heard from its agent."""
    from sim_backend.scenario import Fault

    scenario = load_scenario("lab-6").with_overrides(faults=[Fault(robot=0, at_s=0.5)])
    result = run_sil(scenario, tmp_path, SilOptions(plot=False, record=False, time_limit_s=1.5))
    assert "error" not in result
    assert result["telemetry"][0] is None and all(tel is not None for tel in result["telemetry"][1:])
    assert json.loads((tmp_path / "result.json").read_text())["telemetry"][0] is None


def test_an_earlier_runs_agent_logs_do_not_stay_beside_this_runs(tmp_path):
    """A 6-robot run's agents/agent-4.log and agent-5.log stayed in the folder of a later 4-robot run."""
    (tmp_path / "agents").mkdir()
    for i in range(6):
        (tmp_path / "agents" / f"agent-{i}.log").write_text("an earlier run's agent\n")
    lab6 = load_scenario("lab-6")
    scenario = lab6.with_overrides(robots=dataclasses.replace(lab6.robots, count=4))
    run_sil(scenario, tmp_path, SilOptions(plot=False, record=False, time_limit_s=2.0))
    logs = sorted(path.name for path in (tmp_path / "agents").iterdir())
    assert logs == [f"agent-{i}.log" for i in range(4)]
    assert all("an earlier run" not in (tmp_path / "agents" / name).read_text() for name in logs)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_kill_ends_sil_as_ctrl_c_does_with_its_log_closed(tmp_path, sig):
    """`kill` (SIGTERM) used to end sil at once: no message, and an MCAP log without its footer; the terminal or
    ssh session closing (SIGHUP) too, leaving its secret keys in /tmp as well."""
    root = Path(__file__).resolve().parents[1]
    out = tmp_path / "sil"
    out.mkdir()
    (out / "result.json").write_text('{"stop_reason": "behaviour finished"}')     # an earlier run's
    sil = subprocess.Popen([sys.executable, "-m", "khepri_cli.main", "sil", "lab-6", "--realtime", "--time-limit",
                            "60", "--no-plot", "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           text=True, env=dict(os.environ, PYTHONPATH=str(root)))
    try:
        deadline = time.monotonic() + 30
        while "started by sil" not in read_or_empty(out / "hub.log") and time.monotonic() < deadline:
            time.sleep(0.2)
        time.sleep(2.0)                                 # the run is under way
        sil.send_signal(sig)
        _, err = sil.communicate(timeout=30)
    finally:
        sil.kill()
    assert sil.returncode == 130
    assert f"khepri: interrupted ({sig.name}) (at t = " in err and "Traceback" not in err    # was "(Ctrl-C)"
    summary = summarise(out / "hub.mcap")
    assert not summary.truncated
    # The log says why the run ended: `log info` said only "stopped by sil".
    run, = summary.runs
    assert run["end_note"].startswith(f"interrupted ({sig.name}) (at t = "), run
    # What was recorded is written, as `sim run` does, in place of the earlier run's result.
    result = json.loads((out / "result.json").read_text())
    assert result["stop_reason"] == "interrupted" and result["sim_time_s"] > 1.0
    assert (out / "trajectory.npz").is_file()


def test_a_ctrl_c_to_the_whole_group_leaves_every_agent_exiting_by_itself(tmp_path):
    """A terminal's Ctrl-C reaches sil and its agents together: every agent stopped its wheels and was leaving
    when sil's SIGTERM caught it on its way out, and agent_exit_codes read -15 for all, as if killed."""
    root = Path(__file__).resolve().parents[1]
    out = tmp_path / "sil"
    sil = subprocess.Popen([sys.executable, "-m", "khepri_cli.main", "sil", "lab-6", "--realtime", "--time-limit",
                            "60", "--no-plot", "--no-record", "--out", str(out)], stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True, env=dict(os.environ, PYTHONPATH=str(root)),
                           start_new_session=True)
    try:
        deadline = time.monotonic() + 30
        while "started by sil" not in read_or_empty(out / "hub.log") and time.monotonic() < deadline:
            time.sleep(0.2)
        time.sleep(1.0)
        os.killpg(sil.pid, signal.SIGINT)
        sil.communicate(timeout=30)
    finally:
        sil.kill()
    assert sil.returncode == 130
    codes = json.loads((out / "result.json").read_text())["sil"]["agent_exit_codes"]
    assert codes == [0] * 6, codes


def read_or_empty(path: Path) -> str:
    try:
        return path.read_text()
    except OSError:
        return ""


def test_the_traceback_is_read_from_the_agents_log_as_sim_run_keeps_it(tmp_path):
    """A message of several lines comes before the trace in the log: the parser stopped there, and sil wrote
    no traceback at all."""
    from hub.sil_agents import agent_traceback

    (tmp_path / "agents").mkdir()
    (tmp_path / "agents" / "agent-7.log").write_text(
        "agent 7: run r1: crashy\n"
        "agent 7: behaviour crashed: robot 7, step(): ValueError: first line\n"
        "second line\n"
        "agent 7 said ünïcödé ✓ at crashy.py:8 (at t = 0.6 s)\n"
        "agent 7:     File \"crashy.py\", line 8, in step\n"
        "    raise ValueError(text)\n"
        "agent 7:   ValueError: first line\n"
        "second line\n"
        "agent 7 said ünïcödé ✓\n"
        "agent: error: the behaviour crashed: robot 7, step(): ValueError: first line\n", encoding="utf-8")
    assert agent_traceback(tmp_path, 7) == ['  File "crashy.py", line 8, in step\n    raise ValueError(text)',
                                            "ValueError: first line\nsecond line\nagent 7 said ünïcödé ✓"]
    assert agent_traceback(tmp_path, 3) is None


def test_the_sil_summary_says_its_figures_and_drops_in_words():
    """It printed the raw dict of drops, and 'latency p99 None ms' with --realtime."""
    from hub.sil_report import sil_summary_lines

    realtime = {"agents": 6, "lockstep": False, "latency_ms": {"p99": None}, "loop_misses": 2,
                "dropped": {"hub_rejected": {}, "frames_lost_at_agents": 0,
                            "relay": {"sent": 50, "refused": 7, "dropped_random": 0}}}
    assert sil_summary_lines(realtime) == [
        "  6 agents, real time, frame-to-answer latency not measured (--realtime: the agents run on their own "
        "clocks), loop misses 2",
        "  dropped: 7 broadcasts the relay refused (over relay.max_bytes, or sent outside a run) (hub.log says more)"]
    lockstep = {"agents": 3, "lockstep": True, "latency_ms": {"p99": 1.25}, "loop_misses": 0,
                "dropped": {"hub_rejected": {"bad message": 2}, "relay": {}}}
    assert sil_summary_lines(lockstep) == [
        "  3 agents, lockstep, frame-to-answer latency p99 1.25 ms, loop misses 0",
        "  dropped: 2 messages the hub refused: bad message (hub.log says more)"]
    assert sil_summary_lines({"agents": 1, "lockstep": True, "dropped": {}})[1] == "  dropped: nothing"
    # The scenario's comm.drop, which hub.log only counts: named by the scenario's key, not the hub config's.
    lossy = {"agents": 10, "lockstep": True, "dropped": {"relay": {"dropped_random": 5377, "refused": 0}}}
    assert sil_summary_lines(lossy)[1] == "  dropped: 5377 radio messages lost by chance (the scenario's comm.drop)"


def test_a_lockstep_run_without_latency_does_not_blame_realtime():
    """A behaviour whose __init__ raised ended a lockstep `khepri sil` at t = 0, and the summary said the
    latency was not measured because of `--realtime`, which was never given."""
    from hub.sil_report import sil_summary_lines

    line = sil_summary_lines({"agents": 3, "lockstep": True, "latency_ms": {"p99": None}, "dropped": {}})[0]
    assert line == "  3 agents, lockstep, frame-to-answer latency not measured (no frame was answered), loop misses 0"


COURSE_HOLDER = '''
import random
import time
from dataclasses import dataclass

from onboard.behaviour import Behaviour, register


@dataclass
class Params:
    slow_s: float = 0.0


@register("course-holder")
class CourseHolder(Behaviour):
    """Sets random wheel speeds at t = 0 and 1 s only, as a behaviour holding a course does; robot 0's step at
    t = 0.5 s takes slow_s longer."""
    Params = Params

    def step(self):
        t = self.robot.clock.now()
        if self.robot.id == 0 and abs(t - 0.5) < 0.05:
            time.sleep(self.params.slow_s)
        if abs(t) < 0.05 or abs(t - 1.0) < 0.05:
            self.robot.wheels.set_speeds(random.uniform(0.05, 0.2), random.uniform(0.05, 0.2))
'''

COURSE_SCENARIO = """name: course
behaviour: course-holder
params: {{slow_s: {bug}}}
robots: {{count: 3, spawn: {{x: [-0.5, 0.5], y: [-0.5, 0.5]}}}}
arena: {{walls: [-2, -2, 2, 2]}}
time_limit_s: 2
"""


def test_a_lockstep_run_does_not_depend_on_how_long_an_agent_takes(user_behaviour, tmp_path):
    """One agent's step taking 0.7 s, as on a loaded machine, changed a lockstep run: the other agents' watchdogs
    and the hub's silence check stopped their wheels in the step the hub was waiting on, and the slow agent's
    own step watchdog dropped its wheel command. Physics waits for every answer, so nothing may change."""
    from khepri_cli.main import main

    scenario = user_behaviour("course_holder", COURSE_HOLDER, COURSE_SCENARIO)
    poses, warnings = {}, {}
    for slow in ("0", "0.7"):
        out = f"slow-{slow}"
        assert main(["--import", "course_holder", "sil", scenario(slow), "--no-plot", "--no-record", "--out", out]) == 0
        result = json.loads((tmp_path / out / "result.json").read_text())
        assert result["sil"]["step_timeouts"] == 0 and result["sil"]["dropped"]["frames_lost_at_agents"] == 0
        poses[slow] = np.load(tmp_path / out / "trajectory.npz")["robot_pose"]
        warnings[slow] = result.get("warnings", [])
    assert "the behaviour's step took 0.7" in (tmp_path / "slow-0.7" / "agents" / "agent-0.log").read_text()
    # Said in result.json, as `sim run` says a slow step(): a robot's wheels would stop (it was in the log alone).
    assert warnings["0"] == [] and len(warnings["0.7"]) == 1
    said = warnings["0.7"][0]
    assert said.startswith("agent 0: the behaviour's step") and said.endswith("(agents/agent-0.log)")
    assert np.abs(poses["0"][-1, :, :2] - poses["0"][0, :, :2]).max() > 0.1      # they drove
    assert np.array_equal(poses["0"], poses["0.7"])
