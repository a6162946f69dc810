"""How a run is going and how it ended, as a hub with the sim source tells the operator: `ctl status` shows the
object, the waypoint it heads for and the distance to it; a stop, and the arrival at the last waypoint, say the
outcome on the hub's console and in its log (/hub/run, `khepri log info`). The same evaluator as result.json's."""
import json
import re
import time
from pathlib import Path

import pytest
import yaml
from test_hub_cli import hub_ports, khepri, spawn, wait_until_connected

from hub.config import parse_config
from hub.control import status_table
from hub.factory import build_hub
from hub.harness import stop_processes
from hub.recording import HUB_RUN, read_log

NETWORK = {"bind": "127.0.0.1", "robot_port": 0, "control_port": 0}
OBJECT_AT = r"object at \(-?\d+\.\d\d, -?\d+\.\d\d\) m, yaw -?\d+\.\d°"


def test_ctl_status_shows_the_objects_progress_and_ctl_stop_says_how_the_run_ended(tmp_path):
    """`khepri hub` on lab-6 with an agent joined by hand: the object's pose, waypoint and distance only
    appeared in `khepri sil`'s result.json; the hub never said how its run went or how it ended."""
    log = tmp_path / "run.mcap"
    config = tmp_path / "lab.yaml"
    config.write_text(yaml.safe_dump({"source": {"type": "sim", "scenario": "lab-6"}, "network": NETWORK,
                                      "record": str(log)}))
    hub_log = open(tmp_path / "hub.log", "w")
    hub = spawn("hub", "--config", str(config), "--insecure", log=hub_log)
    agent = None
    try:
        ports = hub_ports(tmp_path / "hub.log", hub)
        control, robots = ports["control"], ports["robots"]
        agent = spawn("agent", "--id", "0", "--driver", "sim", "--port", robots, log=open(tmp_path / "agent.log", "w"))
        wait_until_connected(0, control)
        assert khepri("ctl", "start", "--port", control).returncode == 0
        time.sleep(1.0)           # a few control steps of robot 0's telemetry reach the evaluator
        table = khepri("ctl", "status", "--port", control).stdout.splitlines()
        assert re.fullmatch(OBJECT_AT + r", waypoint 1 of 3 is 0\.\d\d m and \d+\.\d° away \(0 reached\)",
                            table[-1]), table
        status = json.loads(khepri("ctl", "status", "--json", "--port", control).stdout)
        thing = status["object"]
        assert (thing["waypoints"], thing["reached"], thing["target"]) == (3, 0, 0), thing
        assert thing["distance_m"] == pytest.approx(0.3, abs=0.05) and len(thing["pose"]) == 3
        # An older hub's reply has no such field: ctl prints the table without its line.
        older = {key: value for key, value in status.items() if key != "object"}
        assert not [line for line in status_table(older).splitlines() if line.startswith("object")]
        stop = khepri("ctl", "stop", "--port", control)
        assert stop.returncode == 0, stop.stderr
    finally:
        codes = stop_processes([p for p in (agent, hub) if p is not None])
        hub_log.close()
    assert codes == [0] * len(codes)
    lines = (tmp_path / "hub.log").read_text().splitlines()
    run_id = status["run_id"]
    said = [line for line in lines if line.startswith(f"hub: run {run_id} stopped by ")]
    assert len(said) == 1 and re.fullmatch(
        rf"hub: run {run_id} stopped by operator at 127\.0\.0\.1: not completed \(cage did not close\); "
        + OBJECT_AT + r", waypoint 1 of 3 is .* away \(0 reached\)", said[0]), lines
    info = khepri("log", "info", str(log), "--json")
    runs = json.loads(info.stdout)["runs"]
    assert [(r["run_id"], r["end_cause"], r["ended_by"], r["outcome"]) for r in runs] == \
        [(run_id, "stop", "operator at 127.0.0.1", "not completed")]
    assert runs[0]["failures"][0] == "cage did not close" and runs[0]["object"]["waypoints"] == 3
    text = khepri("log", "info", str(log)).stdout
    assert re.search(rf"^run: +{run_id} \(transport\): started \d\d:\d\d:\d\d by operator at 127\.0\.0\.1; "
                     r"stopped \d\d:\d\d:\d\d by operator at 127\.0\.0\.1: not completed \(cage did not close\); "
                     + OBJECT_AT, text, re.M), text


def test_the_arrival_at_the_last_waypoint_is_said_once_with_the_outcome(tmp_path):
    """The swarm's telemetry (as the agents send it) takes the evaluator through the three waypoints while the
    object is put on each: the hub says the run completed, once, and records it."""
    log = tmp_path / "run.mcap"
    lines = []
    hub = build_hub(parse_config({"source": {"type": "sim"}, "network": NETWORK, "security": {"insecure": True},
                                  "record": str(log)}), log=lines.append)
    try:
        hub.control.execute("start")

        def step(state, waypoint, closed=False, at=None):
            report_step(hub, state, waypoint, closed, at)

        step("caged", 0, closed=True)
        step("push", 1, at=(0.0, 0.3))
        assert hub.control.status(time.monotonic())["object"]["reached"] == 1
        assert status_table(hub.control.status(time.monotonic())).splitlines()[-1] == \
            "object at (0.00, 0.30) m, yaw 0.0°, waypoint 2 of 3 is 0.30 m and 0.0° away (1 reached)"
        step("push", 2, at=(0.0, 0.6))
        assert not [line for line in lines if "waypoints reached" in line]
        step("done", 2, at=(-0.001, 0.9))       # shown as 0.00, not -0.00
        step("done", 2)
        said = [line for line in lines if "waypoints reached" in line]
        assert said == [f"hub: run {hub.run_id}: all 3 waypoints reached: completed; object at (0.00, 0.90) m, "
                        "yaw 0.0°, all 3 waypoints reached, 0.00 m and 0.0° from the last; `khepri ctl stop` ends "
                        "the run"], lines
        assert hub.mode == "run"          # said, not acted on: ending a lab run is the operator's
    finally:
        hub.close()
    events = [(r.payload["event"], r.payload.get("outcome")) for r in read_log(Path(log), topics=[HUB_RUN])]
    assert events == [("started", None), ("all waypoints reached", "completed")]


def test_an_arrival_that_is_not_a_completion_leads_with_the_outcome():
    """`all 3 waypoints reached: not completed (...)` read as a contradiction to an operator at a demo."""
    from types import SimpleNamespace

    from hub.run_events import follow_progress

    class Progress:
        scenario = SimpleNamespace(path=[(0, 0.3, 0), (0, 0.6, 0), (0, 0.9, 0)])

        def follow(self, hub):
            return True

        def reached(self):
            return 3

        def status(self):
            return None

        def verdict(self):
            return {"outcome": "not completed",
                    "failures": ["waypoint 1 was passed with the object 0.101 m from it (tolerance 0.100 m)"]}

    lines = []
    hub = SimpleNamespace(progress=Progress(), mode="run", run_id="r1", arrival_said=None, recorder=None,
                          run=SimpleNamespace(behaviour="transport", lockstep=False), log=lines.append)
    follow_progress(hub)
    assert lines == ["hub: run r1: NOT completed, although the object passed all 3 waypoints: waypoint 1 was "
                     "passed with the object 0.101 m from it (tolerance 0.100 m); `khepri ctl stop` ends the run"]
    # `khepri sil` (its hub runs the lockstep) ends the run itself: no word of `ctl stop` in its log.
    lines.clear()
    hub.arrival_said, hub.run.lockstep = None, True
    follow_progress(hub)
    assert lines and not [line for line in lines if "ctl stop" in line], lines


def test_a_push_that_stalls_is_said_once_on_the_hubs_console():
    """A cage that lost a pusher stood still for minutes, every robot reporting `push`, and the hub said nothing."""
    from types import SimpleNamespace

    import numpy as np

    from hub.progress import STALL_SAY_S, RunProgress
    from sim_backend.scenario import load_scenario

    scenario = load_scenario("lab-6-payload")
    world = SimpleNamespace(object_pose=lambda: np.array([0.0, 0.59, 0.0]))
    lines = []
    progress = RunProgress("transport", scenario, world, lines.append)
    progress.evaluator = SimpleNamespace(progress_at=80.0, waypoints_reached=lambda: 2)
    hub = SimpleNamespace(mode="run", run_id="3dd9336fcb0a", source=SimpleNamespace(time_s=80.0 + STALL_SAY_S - 1))
    progress._say_a_stall(hub)
    assert lines == []
    hub.source.time_s = 80.0 + STALL_SAY_S + 1
    progress._say_a_stall(hub)
    progress._say_a_stall(hub)                     # once per stall
    assert lines == ["hub: run 3dd9336fcb0a: the object has come no nearer its next waypoint for 61 s of simulated "
                     "time, 0.31 m from waypoint 3: the push may have stalled (`ctl status` shows each robot; "
                     "`ctl stop` ends the run)"], lines
    progress.evaluator.progress_at, hub.mode = 200.0, "estop"      # a new stall, while e-stopped: not said
    hub.source.time_s = 200.0 + 2 * STALL_SAY_S
    progress._say_a_stall(hub)
    hub.mode = "run"
    progress._say_a_stall(hub)
    assert len(lines) == 1


def test_a_waypoint_passed_beyond_its_tolerance_is_no_completion():
    """The swarm passes every waypoint, but the object went by the first 0.15 m off it (push_tolerance_m is
    0.1 m): the run is not completed. The test above puts the object on each waypoint, and the one after fakes
    the evaluator's verdict, so an evaluator that took any pass for a completion passed them both."""
    lines = []
    hub = build_hub(parse_config({"source": {"type": "sim"}, "network": NETWORK, "security": {"insecure": True}}),
                    log=lines.append)
    try:
        hub.control.execute("start")
        for state, waypoint, at in (("caged", 0, None), ("push", 1, (0.15, 0.3)), ("push", 2, (0.0, 0.6)),
                                    ("done", 2, (0.0, 0.9)), ("done", 2, None)):
            report_step(hub, state, waypoint, True, at)
        said = [line for line in lines if "waypoints" in line]
        assert len(said) == 1 and said[0].startswith(
            f"hub: run {hub.run_id}: NOT completed, although the object passed all 3 waypoints: "), lines
        verdict = hub.progress.verdict()       # the line names its first failure: the hand-made cage's shape
        assert verdict["outcome"] == "not completed" and \
            "waypoint 1 was passed with the object 0.15 m from it (tolerance 0.10 m)" in verdict["failures"], verdict
    finally:
        hub.close()


def report_step(hub, state: str, waypoint: int, closed: bool, at=None) -> None:
    """One control step of a sim-source hub whose robots all report ``state`` at ``waypoint`` (as cage members),
    with the object put at ``at`` first (unless None); then the hub's housekeeping judges the progress."""
    source, box = hub.source, hub.source.world.object_body
    source.advance(source.substeps_per_control)
    if at is not None:
        box.position, box.angle = at, 0.0
    for robot in hub.robots.values():
        robot.run_id = hub.run_id
        robot.telemetry = {"mode": "run", "run_id": hub.run_id, "behaviour": {
            "state": state, "member": True, "closed": closed, "waypoint": waypoint, "finished": False}}
    hub.housekeeping(time.monotonic())
