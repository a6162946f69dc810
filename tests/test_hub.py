"""The hub with the sim source and real agent processes: operator control, e-stop latch, geofence, status."""
import time

import numpy as np
import pytest

from hub.config import parse_config
from hub.control import ControlError, status_table
from hub.harness import HubThread, spawn_agent, stop_processes


def lab_config(**extra):
    data = {"source": {"type": "sim"}, "network": {"bind": "127.0.0.1", "robot_port": 0, "control_port": 0},
            "security": {"insecure": True}}
    data.update(extra)
    return parse_config(data)


@pytest.fixture
def three_robots(make_scenario):
    return make_scenario(robots={"count": 3, "spawn": {"x": [-1.2, -0.6], "y": [-1.2, -0.6]}},
                         arena={"walls": [-2.0, -2.0, 2.0, 2.0]}, time_limit_s=60)


def start_agents(hub, count, tmp_path):
    agents = [spawn_agent(hub.endpoints["robots"], i, tmp_path / f"agent-{i}.log") for i in range(count)]
    hub.wait_until(lambda s: all(r["connected"] for r in s["robots"]))
    return agents


def robots_say(status, key, value):
    return all(r[key] == value for r in status["robots"])


def test_operator_start_estop_clear_resume_stop(three_robots, tmp_path):
    with HubThread(lab_config(), scenario=three_robots) as hub:
        agents = start_agents(hub, 3, tmp_path)
        try:
            status = hub.status()
            assert status["mode"] == "idle" and status["mocap_hz"] > 20
            hub.request("start")
            status = hub.wait_until(lambda s: robots_say(s, "agent_mode", "run")
                                    and all(r["state"] not in (None, "init") for r in s["robots"]))
            run_id = status["run_id"]

            hub.request("estop")
            status = hub.wait_until(lambda s: robots_say(s, "agent_mode", "estop"))
            assert robots_say(status, "mode", "estop")
            assert all(r["estop_ack_ms"] is not None for r in status["robots"])
            for refused in ("start", "stop"):
                with pytest.raises(ControlError, match="latched"):
                    hub.request(refused)

            hub.request("clear")
            status = hub.wait_until(lambda s: robots_say(s, "agent_mode", "hold"))
            assert status["mode"] == "hold" and status["run_id"] == run_id
            # Cleared: the acknowledgement times are history. They stayed in `ctl status` ("e-stop acknowledged
            # in 1.6 ms") through the resumed run, where they read as if the robots were still e-stopped.
            assert all(r["estop_ack_ms"] is None for r in status["robots"])

            hub.request("start")                 # resumes the same run
            status = hub.wait_until(lambda s: robots_say(s, "agent_mode", "run"))
            assert status["run_id"] == run_id

            hub.request("stop")
            status = hub.wait_until(lambda s: robots_say(s, "agent_mode", "idle"))
            assert status["run_id"] is None
            table = status_table(status)
            assert "connected" in table and len(table.splitlines()) == 2 + 3

            hub.request("start")                 # a new run
            status = hub.wait_until(lambda s: robots_say(s, "agent_mode", "run"))
            assert status["run_id"] not in (None, run_id)
            assert all(r["estop_ack_ms"] is None for r in status["robots"])
        finally:
            codes = stop_processes(agents)
    assert codes == [0, 0, 0]


def test_robots_outside_the_geofence_are_held(three_robots, tmp_path):
    config = lab_config(geofence=[-0.5, -2.0, 2.0, 2.0])       # every robot spawns at x < -0.6: outside
    with HubThread(config, scenario=three_robots) as hub:
        # Before any run, the status says so already: it showed a plain `idle` until `start`. And a robot never
        # connected shows no mode: `run` in its row read as if it ran.
        idle = hub.wait_until(lambda s: robots_say(s, "reason", "outside the geofence: held when a run starts"))
        assert [line.split()[3] for line in status_table(idle).splitlines()[2:]] == ["-", "-", "-"]
        agents = start_agents(hub, 3, tmp_path)
        try:
            reply = hub.request("start")
            # The operator hears at once that the run starts without them (it said `ok` alone).
            assert "; HELD, not running: robot 0 (outside the geofence), robot 1 (outside the geofence)" in \
                reply["note"], reply
            # Waited for, not read once: on a loaded machine a late simulated frame briefly holds a robot as
            # "not tracked by motion capture" instead (a failed fresh-clone run).
            hub.wait_until(lambda s: robots_say(s, "agent_mode", "hold")
                           and robots_say(s, "reason", "outside the geofence"))
            before = hub.hub.source.world.robot_poses()
            time.sleep(1.0)
            after = hub.hub.source.world.robot_poses()
            assert np.abs(after - before).max() < 1e-3, "a fenced robot moved"
            # It never was inside; nor was any robot: one line, with the likely cause, not one per robot.
            (fenced,) = [line for line in hub.lines if "outside the geofence" in line]
            assert fenced.startswith("hub: every robot is outside the geofence [-0.5, -2.0, 2.0, 2.0] (robot 0 "
                                     "at (") and "is the geofence in the motion capture's frame" in fenced, fenced
        finally:
            stop_processes(agents)


def test_status_before_any_agent_shows_robots_never_seen(three_robots):
    with HubThread(lab_config(), scenario=three_robots) as hub:
        status = hub.status()
        assert [r["id"] for r in status["robots"]] == [0, 1, 2]
        assert not any(r["connected"] for r in status["robots"])
        assert all(r["last_seen_s"] is None for r in status["robots"])
        assert "never" in status_table(status)
        assert hub.lines[0].startswith("hub: source sim ")           # said first: which robots these are
        assert hub.lines[1:3] == [f"listening robots {hub.endpoints['robots']}",
                                  f"listening control {hub.endpoints['control']}"]


def test_the_status_tables_columns_stay_in_line_for_long_ids_and_counts():
    """Widths were fixed: a 6-digit id or a robot silent for hours pushed its row's columns out of line."""
    base = {"connected": True, "mode": "run", "state": "push", "loop_hz": 10.0, "loop_misses": 0, "battery_v": 7.4}
    rows = [{**base, "id": 7, "last_seen_s": 0.1},
            {**base, "id": 123456, "connected": False, "last_seen_s": 98765.4, "loop_hz": None, "loop_misses": 1234567}]
    status = {"mode": "run", "source": "sim", "mocap_hz": 120.0, "robots": rows}
    header, *lines = status_table(status).splitlines()[1:]
    # Every column starts (left-aligned) or ends (right-aligned) at the same place in every line.
    assert lines[0].index("yes") == lines[1].index("no ") == header.index("connected")
    assert lines[0].index("run") == lines[1].index("run") == header.index("mode")
    assert lines[0].index("7.40 V") + 6 == lines[1].index("7.40 V") + 6 == header.index("battery") + 7
    assert lines[1].split()[0] == "123456" and "1234567" in lines[1]


def test_the_status_table_says_where_the_hub_records_and_that_its_drop_counts_are_since_it_started():
    """Plain status showed the recording only once it had failed, and its `dropped:` line, counted over the
    hub's lifetime, read as the current run's."""
    status = {"mode": "run", "source": "sim", "mocap_hz": 50.0, "robots": [],
              "recording": {"path": "logs/run-1.mcap", "error": None}, "drops": {"bad message": 2}}
    lines = status_table(status).splitlines()
    assert lines[1] == "recording: logs/run-1.mcap"
    assert lines[-1] == "dropped since the hub started: bad message 2"
    status["recording"]["error"] = "disk full"
    assert status_table(status).splitlines()[1] == "RECORDING STOPPED (logs/run-1.mcap): disk full"
    status["recording"] = {"path": "logs/run-1.mcap", "error": None, "left_out": 812}    # a stalled disk
    assert status_table(status).splitlines()[1:3] == [
        "recording: logs/run-1.mcap", "RECORDING FELL BEHIND: 812 messages left out (the disk was too slow)"]
    status["recording"] = None
    assert not [line for line in status_table(status).splitlines() if "record" in line.lower()]


def test_a_crashed_robots_row_does_not_speak_of_a_state_it_does_not_show():
    """Its last report, the crash, had no behaviour: the row showed `-` and said `state is its last report`."""
    from hub.control import robot_table

    row = {"id": 2, "connected": False, "last_seen_s": 3.0, "mode": "run", "state": None, "loop_hz": None,
           "loop_misses": 4, "battery_v": None, "error": "behaviour crashed: robot 2, step(): ..."}
    assert robot_table([row])[1].endswith("silent for 3.0 s; behaviour crashed: robot 2, step(): ...")


def test_a_killed_agent_shows_no_loop_rate_and_says_its_state_is_old(three_robots, tmp_path):
    """A SIGKILLed agent's row kept `loop Hz 10.0`, mode `run` and its last state with no note: a dead robot
    read as one still running its behaviour."""
    with HubThread(lab_config(), scenario=three_robots) as hub:
        agents = start_agents(hub, 3, tmp_path)
        try:
            hub.request("start")
            hub.wait_until(lambda s: all(r["loop_hz"] for r in s["robots"]))
            agents[1].kill()
            status = hub.wait_until(lambda s: not s["robots"][1]["connected"])
            assert status["robots"][1]["loop_hz"] is None
            assert all(r["loop_hz"] for r in status["robots"] if r["id"] != 1)
            row = status_table(status).splitlines()[2 + 1]
            assert row.split()[6] == "-" and "state is its last report" in row, row
        finally:
            stop_processes(agents)


def test_wheel_commands_an_agent_sends_outside_run_do_not_move_the_simulated_robots(three_robots):
    """The sim hub is the physics: a robot the hub holds (e-stop, hold, idle) stays put whatever its agent sends,
    as a wheel command from a behaviour's own thread or a rogue agent would. Real agents close their wheel gate
    in those modes, so the tests with them never sent one: the hub's own check went untested."""
    from hub.factory import build_hub

    hub = build_hub(lab_config(), log=lambda line: None, scenario=three_robots)
    source = hub.source

    def moved_by(left, right):
        before = source.world.robot_poses().copy()
        for _ in range(5):                     # commands as an agent sends them, between physics steps
            for robot in hub.robots.values():
                hub._on_wheels(robot, {"type": "wheels", "id": robot.id, "left": left, "right": right}, 0.0)
            source.advance(source.substeps_per_control)
        return float(np.abs(source.world.robot_poses() - before)[:, :2].max())

    try:
        hub.on_pose_frame(source.snapshot(time.monotonic()))
        assert moved_by(0.3, 0.3) < 1e-6                       # idle
        hub.control.execute("start")
        hub.control.execute("estop")
        assert moved_by(0.3, 0.3) < 1e-6                       # e-stop
        hub.control.execute("clear")
        assert moved_by(0.3, -0.3) < 1e-6                      # hold, after the clear
        hub.control.execute("start")
        assert moved_by(0.3, 0.3) > 0.05                       # run: the same commands drive them
        # ... and no faster than a KheperaIV can, whatever a bad agent asks for (the agent's HAL clamps too).
        top = 5 * source.substeps_per_control * source.world.dt * source.world.spec.max_wheel_speed_m_s
        assert 0.5 * top < moved_by(50.0, 50.0) < 1.05 * top
    finally:
        hub.close()


def test_the_geofence_holds_a_robot_past_any_of_its_four_sides_and_frees_one_back_inside(three_robots):
    """The geofence test above has every robot start beyond xmin: a fence that checked x only, or one side of each
    axis, passed it. Here robots leave (and come back) through every side during a run."""
    from hub.factory import build_hub
    from hub.sources import PoseFrame

    hub = build_hub(lab_config(geofence=[-1.0, -1.0, 1.0, 1.0]), log=lambda line: None, scenario=three_robots)

    def modes_at(*xy):
        poses = np.array([[x, y, 0.0] for x, y in xy])
        hub.on_pose_frame(PoseFrame(time.monotonic(), [0, 1, 2], poses))
        return [hub.mode_for(hub.robots[rid]) for rid in (0, 1, 2)]

    held = ("hold", "outside the geofence")
    try:
        hub.control.execute("start")
        assert modes_at((0.0, 0.0), (0.5, -0.5), (-0.9, 0.9)) == [("run", "")] * 3
        assert modes_at((0.0, 0.0), (0.0, 1.2), (1.2, 0.0)) == [("run", ""), held, held]       # past ymax, xmax
        assert modes_at((0.0, -1.2), (0.0, 0.5), (-1.2, 0.0)) == [held, ("run", ""), held]     # ymin, back, xmin
    finally:
        hub.close()


def test_a_simulated_robot_whose_agent_falls_silent_is_stopped_by_the_hub(three_robots):
    """The sim hub's side of the watchdog: an agent that says nothing for watchdog_s (dead, frozen, cut off)
    cannot stop its own wheels, so the hub holds its simulated ones; the robots whose agents speak drive on. The
    tests with real agents killed one and looked at its status row only, never at where its robot went."""
    from hub.factory import build_hub

    hub = build_hub(lab_config(), log=lambda line: None, scenario=three_robots)
    source = hub.source

    def travelled(now):
        hub.on_pose_frame(source.snapshot(now))              # each pose frame holds the wheels the hub must
        before = source.world.robot_poses().copy()
        source.advance(5 * source.substeps_per_control)
        return np.hypot(*(source.world.robot_poses() - before)[:, :2].T)

    try:
        hub.control.execute("start")
        now = time.monotonic()
        hub.on_pose_frame(source.snapshot(now))              # tracked: they may run
        for robot in hub.robots.values():                    # three agents, all heard from just now
            robot.routing, robot.last_uplink = b"agent-%d" % robot.id, now
            hub._on_wheels(robot, {"type": "wheels", "id": robot.id, "left": 0.3, "right": 0.3}, now)
        assert (travelled(now) > 0.05).all()
        hub.robots[1].last_uplink = now - 2 * hub.config.watchdog_s     # robot 1's agent fell silent
        moved = travelled(now)
        assert moved[1] < 0.02 and (moved[[0, 2]] > 0.1).all(), moved     # it coasts a few mm
    finally:
        hub.close()


def test_an_estop_cleared_before_any_run_leaves_the_hub_idle_and_start_begins_a_run(three_robots):
    """Clear goes back to hold only when a run was going (start then resumes it). An e-stop pressed with no run
    cleared to hold all the same, and `start` then "resumed" run None: no agent was ever told to start. The
    tests cleared e-stops of running runs only."""
    from hub.factory import build_hub

    hub = build_hub(lab_config(), log=lambda line: None, scenario=three_robots)
    try:
        hub.control.execute("estop")
        assert hub.control.execute("clear")[0] and (hub.mode, hub.run_id) == ("idle", None)
        hub.control.execute("start")
        run_id = hub.run_id
        assert hub.mode == "run" and run_id is not None
        hub.control.execute("estop")
        hub.control.execute("clear")
        assert (hub.mode, hub.run_id) == ("hold", run_id)             # a run was going: held, to resume
    finally:
        hub.close()
