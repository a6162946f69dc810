"""Each `ctl start` on the sim source begins at the scenario's start, as a new `khepri sim run` does: the hub's world
is rebuilt for the run (robots, object, faults, the run's evaluator), unless the lab asks to go on in the same world
(`source.reset_each_run: false`). A real hub with real agent processes on loopback, two runs."""
import time

import numpy as np
import pytest

from hub.config import parse_config
from hub.harness import HubThread, spawn_agent, stop_processes
from hub.recording import read_log
from hub.sim_source import SimSource

ROBOTS = 3
MOVED_M = 0.05          # run 1 takes at least one robot this far from its start (else the test proves nothing)
SAME_M = 2e-3           # the frames carry poses to 0.1 mm; the idle world settles by less than this


@pytest.fixture
def gathering(make_scenario):
    """Three aggregating robots spread over the floor (they drive towards each other at once) and a box well away
    from them (so `ctl status` has an object); no pose noise, so each frame carries the robot's true pose."""
    return make_scenario(robots={"count": ROBOTS, "spawn": {"x": [-1.5, 1.5], "y": [-1.5, -0.5]}},
                         object={"shape": "box", "size": [0.3, 0.3], "position": [0.0, 1.2]},
                         sensors={"pose_noise_m": 0.0, "pose_noise_rad": 0.0},
                         arena={"walls": [-2.0, -2.0, 2.0, 2.0]}, time_limit_s=60)


def two_runs(scenario, tmp_path, reset_each_run):
    """start, let the robots move, stop, start again: the status right after the second start, and the log."""
    log = tmp_path / "hub.mcap"
    source = {"type": "sim"} if reset_each_run is None else {"type": "sim", "reset_each_run": reset_each_run}
    config = parse_config({"source": source, "network": {"bind": "127.0.0.1", "robot_port": 0, "control_port": 0},
                           "security": {"insecure": True}, "record": str(log)})
    with HubThread(config, scenario=scenario) as hub:
        agents = [spawn_agent(hub.endpoints["robots"], i, tmp_path / f"agent-{i}.log") for i in range(ROBOTS)]
        try:
            hub.wait_until(lambda s: all(r["connected"] for r in s["robots"]))
            hub.request("start")
            hub.wait_until(lambda s: all(r["agent_mode"] == "run" and r["state"] == "gathering" for r in s["robots"]))
            time.sleep(1.5)
            hub.request("stop")
            hub.wait_until(lambda s: all(r["agent_mode"] == "idle" for r in s["robots"]))
            time.sleep(0.3)           # idle frames: where the robots are when the second run starts
            hub.request("start")
            second = hub.status()
            hub.wait_until(lambda s: all(r["agent_mode"] == "run" and r["run_id"] == second["run_id"]
                                         for r in s["robots"]))
            hub.request("stop")
        finally:
            codes = stop_processes(agents)
    assert codes == [0] * ROBOTS
    return second, log


def frames_by_run(log, robot):
    """Robot ``robot``'s downlink poses, one list per run (the frames whose mode is run, split where it was not)."""
    runs, running = [], False
    last_idle = []
    for record in read_log(log, topics=[f"/robot/{robot}/frame"]):
        frame = record.payload
        if frame["mode"] == "run":
            if not running:
                runs.append({"before": list(last_idle), "poses": []})
            runs[-1]["poses"].append(frame["pose"])
        elif frame["pose"] is not None:
            last_idle = frame["pose"]
        running = frame["mode"] == "run"
    return runs


def scenario_start(scenario):
    """The robots' and the object's poses at the scenario's start, from a world built afresh for its seed."""
    world = SimSource(scenario).world
    return world.robot_poses(), world.object_pose()


def moved(a, b):
    return float(np.hypot(a[0] - b[0], a[1] - b[1]))


@pytest.mark.parametrize("reset_each_run", [None, True])
def test_a_second_start_begins_at_the_scenarios_start(gathering, tmp_path, reset_each_run):
    """The world was built once when the hub started: the second run began where the first had left the robots,
    while its mission (waypoints, the behaviours' fresh start) assumed the scenario's start."""
    second, log = two_runs(gathering, tmp_path, reset_each_run)
    robots, box = scenario_start(gathering)
    assert second["object"]["pose"] == pytest.approx(box.round(4).tolist(), abs=SAME_M)
    travelled = []
    for rid in range(ROBOTS):
        runs = frames_by_run(log, rid)
        assert len(runs) == 2, runs
        first, again = runs
        assert moved(first["poses"][0], robots[rid]) < SAME_M          # the first run starts at the start too
        travelled.append(moved(first["poses"][-1], robots[rid]))
        assert moved(again["poses"][0], robots[rid]) < SAME_M, (rid, again["poses"][0], robots[rid])
        assert abs(again["poses"][0][2] - robots[rid][2]) < 1e-2
    assert max(travelled) > MOVED_M, travelled


def test_reset_each_run_false_goes_on_where_the_last_run_left_the_world(gathering, tmp_path):
    """A lab that wants to continue in the same world says so, and gets today's behaviour."""
    second, log = two_runs(gathering, tmp_path, False)
    robots, _ = scenario_start(gathering)
    away = []
    for rid in range(ROBOTS):
        first, again = frames_by_run(log, rid)
        assert moved(again["poses"][0], again["before"]) < SAME_M, (rid, again["poses"][0], again["before"])
        away.append(moved(again["poses"][0], robots[rid]))
    assert max(away) > MOVED_M, away


def lab_with_a_fault():
    from sim_backend.scenario import Fault, load_scenario

    return load_scenario("lab-6").with_overrides(faults=[Fault(robot=4, at_s=0.5)])


def lab_hub(lines, reset_each_run=True):
    from hub.factory import build_hub

    config = parse_config({"source": {"type": "sim", "reset_each_run": reset_each_run},
                           "network": {"bind": "127.0.0.1", "robot_port": 0, "control_port": 0},
                           "security": {"insecure": True}})
    return build_hub(config, log=lines.append, scenario=lab_with_a_fault())


def first_run_moves_everything(hub):
    """Run 1, driven by hand (as `khepri sil` starts its one run, before physics steps: the world is not rebuilt
    then): robot 4's fault fires, the box is pushed onto the first waypoint and still slides,
    the evaluator counts the waypoint reached, and a message waits in the relay for a robot out of reach."""
    source, box = hub.source, hub.source.world.object_body
    hub.control.execute("start")
    assert source.world.object_body is box          # physics has not stepped yet: the world is used as built
    for waypoint in (0, 1):
        source.advance(source.substeps_per_control * 3)
        box.position, box.velocity = (0.0, 0.3), (0.0, 0.2)
        hub.on_pose_frame(source.snapshot(time.monotonic()))
        for robot in hub.robots.values():
            robot.run_id = hub.run_id
            robot.telemetry = {"mode": "run", "run_id": hub.run_id, "behaviour": {
                "state": "push", "member": True, "closed": True, "waypoint": waypoint, "finished": False}}
        hub.housekeeping(time.monotonic())
    hub.relay.submit(0, 1.0, {"cage": "closed"}, 20, [3])
    status = hub.control.status(time.monotonic())
    assert status["object"]["reached"] == 1 and status["object"]["pose"][:2] == pytest.approx([0.0, 0.3], abs=0.05)
    assert hub.killed == {4} and not source.world.alive()[4]
    hub.control.execute("stop")


def test_a_new_run_rebuilds_the_object_faults_and_evaluator_and_drops_the_last_runs_messages():
    lines = []
    hub = lab_hub(lines)
    try:
        source = hub.source
        start_robots, start_box = scenario_start(lab_with_a_fault())
        first_run_moves_everything(hub)
        hub.control.execute("start")
        world = source.world
        status = hub.control.status(time.monotonic())
        assert status["object"]["pose"] == pytest.approx(start_box.round(4).tolist(), abs=1e-4)
        assert (status["object"]["reached"], status["object"]["target"]) == (0, 0)
        assert tuple(world.object_body.velocity) == (0.0, 0.0) and not world.odometry().any()
        assert np.abs(world.robot_poses() - start_robots).max() == 0.0
        assert np.abs(hub.poses - start_robots).max() < 1e-9       # what the next frames carry
        assert world.alive().all() and hub.killed == set() and not hub.relay.pending(3)
        assert hub.progress.world is world and hub.progress.evaluator.world is world
        assert any(line.endswith("the world is back at the scenario's start") for line in lines), lines
        # The clock runs on; the fault is due 0.5 s into this run again, as in `khepri sim run`.
        began = source.time_s
        assert began > 0.5
        source.advance(source.substeps_per_control * 4)
        hub.on_pose_frame(source.snapshot(time.monotonic()))
        assert source.time_s - began < 0.5 and hub.killed == set()
        source.advance(source.substeps_per_control)
        hub.on_pose_frame(source.snapshot(time.monotonic()))
        assert hub.killed == {4}
    finally:
        hub.close()


def first_frames(hub):
    """Every robot's noisy neighbours, as the next frames would carry them (draws the noise)."""
    return hub.sensors.frames(hub.ids).records.tolist()


def test_a_new_run_restarts_the_hubs_noise_with_its_world():
    """The world was rebuilt for the scenario's seed, but the hub's range-and-bearing noise ran on from the last run,
    so a second lockstep run could not repeat the first. Now the new run's first frames are a fresh hub's."""
    fresh = lab_hub([])
    try:
        fresh.on_pose_frame(fresh.source.snapshot(time.monotonic()))      # the world as built, before any step
        expected = first_frames(fresh)
    finally:
        fresh.close()
    assert len(expected) > 6       # every robot hears some others: the noise is in the test
    hub = lab_hub([])
    try:
        first_run_moves_everything(hub)
        assert first_frames(hub) != expected            # the run moved the world and drew noise
        hub.control.execute("start")
        assert first_frames(hub) == expected
    finally:
        hub.close()


def test_reset_each_run_false_keeps_the_last_runs_world():
    """The world, box and dead robot as the last run left them; the evaluator counts afresh, as it did."""
    lines = []
    hub = lab_hub(lines, reset_each_run=False)
    try:
        world = hub.source.world
        first_run_moves_everything(hub)
        assert hub.source.world is world and not [line for line in lines if "back at the scenario's start" in line]
        hub.control.execute("start")
        status = hub.control.status(time.monotonic())
        assert hub.source.world is world and status["object"]["pose"][:2] == pytest.approx([0.0, 0.3], abs=0.05)
        assert hub.killed == {4} and status["object"]["reached"] == 0      # a fresh count, as before
        assert not hub.relay.pending(3)          # the last run's messages go either way: the agents drop theirs
    finally:
        hub.close()


def test_the_encoders_in_the_frames_count_on_across_a_new_run(gathering):
    """The world is built again for a new run, but a real robot's encoders do not go back to 0 when it is carried
    to its start: the frames' `odo` counts on, and the new world's wheels add to it."""
    source = SimSource(gathering)
    source.command(0, 0.1, 0.1)
    source.advance(source.substeps_per_control * 5)
    rolled = source.snapshot(time.monotonic()).extras[0]["odo"]
    assert min(rolled) > 0.04
    assert source.restart(time.monotonic()).extras[0]["odo"] == rolled
    assert not source.world.odometry().any()
    source.command(0, 0.1, 0.1)
    source.advance(source.substeps_per_control * 5)
    assert source.snapshot(time.monotonic()).extras[0]["odo"] == pytest.approx([2 * rolled[0], 2 * rolled[1]])
