"""Hub killed mid-run and restarted: agents stop their wheels, reconnect, and run again; nothing crashes."""
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import yaml

from hub.control import request
from hub.harness import spawn_agent, stop_processes

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_hub(config_path: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    hub = subprocess.Popen([sys.executable, "-m", "khepri_cli.main", "hub", "--config", str(config_path)],
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    listening = []
    while len(listening) < 2:
        line = hub.stdout.readline()
        assert line, "the hub exited before listening"
        if line.startswith("listening "):
            listening.append(line.split()[1])
    assert listening == ["robots", "control"]
    return hub


def status(endpoint):
    return request(endpoint, "status", timeout_s=5.0)["status"]


def wait_status(endpoint, condition, timeout_s=30.0):
    deadline = time.monotonic() + timeout_s
    while True:
        current = status(endpoint)
        if condition(current):
            return current
        assert time.monotonic() < deadline, f"not reached within {timeout_s} s: {current}"
        time.sleep(0.1)


def all_robots(key, value):
    return lambda s: all(r[key] == value for r in s["robots"])


def two_robot_lab(tmp_path: Path):
    """A lab config (sim source, two aggregate robots, insecure, free ports on loopback): its path and the
    robot and control endpoints."""
    (tmp_path / "two.yaml").write_text(yaml.safe_dump({
        "behaviour": "aggregate", "robots": {"count": 2, "spawn": {"x": [-1.0, 1.0], "y": [-1.0, 1.0]}},
        "arena": {"walls": [-2, -2, 2, 2]}, "time_limit_s": 600}))
    robot_port, control_port = free_port(), free_port()
    config = tmp_path / "lab.yaml"
    config.write_text(yaml.safe_dump({
        "source": {"type": "sim", "scenario": str(tmp_path / "two.yaml")},
        "network": {"bind": "127.0.0.1", "robot_port": robot_port, "control_port": control_port},
        "security": {"insecure": True}}))
    return config, f"tcp://127.0.0.1:{robot_port}", f"tcp://127.0.0.1:{control_port}"


def running(control: str) -> None:
    """Wait for both agents to connect, start the run, and wait until both are running it."""
    wait_status(control, all_robots("connected", True))
    request(control, "start")
    wait_status(control, lambda s: all(r["agent_mode"] == "run" and r["state"] not in (None, "init")
                                       for r in s["robots"]))


def test_agents_survive_a_hub_restart(tmp_path):
    config, robots, control = two_robot_lab(tmp_path)
    hub = start_hub(config)
    agents = [spawn_agent(robots, i, tmp_path / f"agent-{i}.log") for i in range(2)]
    try:
        running(control)

        hub.send_signal(signal.SIGKILL)                       # no goodbye: a crash or a pulled cable
        hub.wait()
        time.sleep(1.0)
        assert [a.poll() for a in agents] == [None, None], "an agent died with the hub"
        for i in range(2):
            log = (tmp_path / f"agent-{i}.log").read_text()
            assert "no frame from the hub" in log and "wheels stopped" in log

        hub = start_hub(config)
        fresh = wait_status(control, all_robots("connected", True))
        assert fresh["mode"] == "idle"
        wait_status(control, all_robots("agent_mode", "idle"))   # the new hub has no run: agents drop theirs
        # ... the run itself too, not only its wheels: the hub learns of it from their telemetry (their
        # hellos were lost while they reconnected)
        dropped = wait_status(control, all_robots("run_id", None))
        assert [r["state"] for r in dropped["robots"]] == [None, None]
        assert [r["driver"] for r in dropped["robots"]] == ["sim", "sim"]
        request(control, "start")
        wait_status(control, lambda s: all(r["agent_mode"] == "run" and r["state"] not in (None, "init")
                                           for r in s["robots"]))
        assert [a.poll() for a in agents] == [None, None]
    finally:
        agent_codes = stop_processes(agents)
        hub_code = stop_processes([hub])
        said = hub.stdout.read()
        hub.stdout.close()
    assert agent_codes == [0, 0] and hub_code == [0]
    # The new hub says, once, that its robots were in a run it did not start (its console said only that they
    # connected, and its log had no trace of the run).
    unknown = [line for line in said.splitlines() if "which this hub did not start" in line]
    assert len(unknown) == 1 and unknown[0].startswith("hub: robot "), said


def test_a_hub_stopped_with_sigterm_tells_its_agents_to_stop_their_run(tmp_path):
    """'SIGINT or SIGTERM tells every agent stop': the stops used to be dropped with the socket, so the
    agents kept their runs, held only by their watchdogs. The hub now waits for their acknowledgements."""
    config, robots, control = two_robot_lab(tmp_path)
    hub = start_hub(config)
    agents = [spawn_agent(robots, i, tmp_path / f"agent-{i}.log") for i in range(2)]
    try:
        running(control)
        hub.send_signal(signal.SIGTERM)
        assert hub.wait(timeout=10) == 0
        for i in range(2):
            deadline = time.monotonic() + 5.0
            while "run stopped: hub shutting down" not in (tmp_path / f"agent-{i}.log").read_text():
                assert time.monotonic() < deadline, (tmp_path / f"agent-{i}.log").read_text()
                time.sleep(0.05)
    finally:
        agent_codes = stop_processes(agents)
        stop_processes([hub])
        hub.stdout.close()
    assert agent_codes == [0, 0]
