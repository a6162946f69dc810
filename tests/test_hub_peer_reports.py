"""What an agent reports is checked where it arrives and shown safely: the hub drops telemetry whose values are
not what docs/protocol.md says (naming the field and the sender), and `khepri ctl status` prints whatever a
hub reports without failing. Real sockets on loopback."""
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zmq

from hub.config import parse_config
from hub.control import status_table
from hub.harness import HubThread
from onboard.protocol import PROTOCOL_VERSION, ProtocolError, encode

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=str(ROOT))
SIM = {"source": {"type": "sim"}, "security": {"insecure": True},
       "network": {"bind": "127.0.0.1", "robot_port": 0, "control_port": 0}}


def peer(endpoint: str) -> zmq.Socket:
    """A hand-made agent: a DEALER that sends what it is given, checked or not."""
    sock = zmq.Context.instance().socket(zmq.DEALER)
    sock.linger = 0
    sock.connect(endpoint)
    return sock


def raw(message: dict) -> bytes:
    """A message as a peer may send it: not through ``encode``, which refuses what the hub would drop."""
    return json.dumps({"v": PROTOCOL_VERSION, **message}).encode()


def telemetry(step: int, **fields) -> bytes:
    return raw({"type": "telemetry", "id": 0, "step": step, "mode": "idle", **fields})


def wait_for_line(hub: HubThread, fragment: str, timeout_s: float = 5.0) -> str:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for line in list(hub.lines):
            if fragment in line:
                return line
        time.sleep(0.02)
    raise AssertionError(f"no line with {fragment!r} in {hub.lines}")


def ctl_status(hub: HubThread) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "khepri_cli.main", "ctl", "status", "--hub",
                           hub.endpoints["control"]], capture_output=True, text=True, env=ENV, timeout=60)


@pytest.mark.parametrize("field, value, said", [
    ("loop", {"hz": "fast"}, "telemetry.loop.hz: must be a finite number"),
    ("loop", {"hz": 1e308}, "telemetry.loop.hz: must be from 0 to 1e+06"),
    ("loop", {"hz": 10.0, "misses": -5}, "telemetry.loop.misses: must be a count"),
    ("loop", {"steps": "many"}, "telemetry.loop.steps: must be an integer"),
    ("behaviour", {"state": "push", "finished": "no"}, "telemetry.behaviour.finished: must be true or false"),
    ("behaviour", {"state": {"a": [1, 2]}}, "telemetry.behaviour.state: must be a string of at most 200"),
    ("behaviour", {"state": "S" * 5000}, "telemetry.behaviour.state: must be a string of at most 200"),
    ("battery_v", 1e300, "telemetry.battery_v: must be from 0 to 1000"),
    ("frames_lost", -3, "telemetry.frames_lost: must be a count"),
])
def test_telemetry_the_protocol_does_not_allow_is_dropped_naming_the_field_and_the_sender(field, value, said):
    """The hub took `loop` and `behaviour` unchecked: `"hz": "fast"` ended `ctl status` in a traceback, a
    battery of 1e300 V printed 300 digits, a dict state was printed raw."""
    with HubThread(parse_config(SIM)) as hub:
        sock = peer(hub.endpoints["robots"])
        try:
            sock.send(encode({"type": "hello", "id": 0, "driver": "sim"}))
            sock.send(telemetry(1, **{field: value}))
            line = wait_for_line(hub, "dropped bad message")
        finally:
            sock.close(0)
        status = hub.status()
    assert line.startswith(f"hub: dropped bad message: from peer at 127.0.0.1: {said}"), line
    assert status["drops"] == {"bad message": 1}
    row = status["robots"][0]
    assert row["state"] is None and row["finished"] is None and row["battery_v"] is None
    assert row["loop_misses"] is None and row["frames_lost"] is None


def test_a_finished_that_is_not_true_or_false_does_not_end_a_run_for_the_hub():
    """`"finished": "no"` made the hub say that every connected robot reports its job finished."""
    with HubThread(parse_config(SIM)) as hub:
        sock = peer(hub.endpoints["robots"])
        try:
            sock.send(encode({"type": "hello", "id": 0, "driver": "sim"}))
            hub.request("start")
            run_id, deadline = None, time.monotonic() + 3.0
            step = 0
            while time.monotonic() < deadline:
                while sock.poll(0):
                    message = sock.recv()
                    if message.startswith(b"{"):
                        command = json.loads(message)
                        run_id = (command.get("run") or {}).get("run_id", run_id)
                        sock.send(encode({"type": "ack", "id": 0, "cmd": command["cmd"]}))
                step += 1
                sock.send(telemetry(step, mode="run" if run_id else "idle", run_id=run_id, driver="sim",
                                    behaviour={"state": "pushing", "finished": "no"}))
                time.sleep(0.1)
            status = hub.status()
        finally:
            sock.close(0)
    assert run_id is not None, "the hub never sent start"
    assert not [line for line in hub.lines if "reports its job finished" in line], hub.lines
    assert status["robots"][0]["finished"] is None and status["drops"]["bad message"] >= 10


def test_ctl_status_prints_a_hub_whose_peer_sent_a_loop_rate_that_is_text():
    """The audit's case, end to end: a peer's `"loop": {"hz": "fast"}`, then `khepri ctl status`."""
    with HubThread(parse_config(SIM)) as hub:
        sock = peer(hub.endpoints["robots"])
        try:
            sock.send(encode({"type": "hello", "id": 0, "driver": "sim"}))
            for step in range(1, 6):
                sock.send(telemetry(step, loop={"hz": "fast"}))
                time.sleep(0.05)
            wait_for_line(hub, "telemetry.loop.hz")
            run = ctl_status(hub)
        finally:
            sock.close(0)
    assert run.returncode == 0 and "Traceback" not in run.stderr, run.stderr
    assert "dropped since the hub started: bad message 5" in run.stdout, run.stdout


def test_the_status_table_prints_any_values_a_hub_reports():
    """An older hub passes a peer's values on unchecked, and a newer one may add or change fields: no value in a
    reply makes `ctl status` fail, and none makes a column hundreds of characters wide."""
    odd = {"id": 0, "connected": "yes", "last_seen_s": "a while", "mode": None, "state": {"a": [1, 2]},
           "finished": "no", "loop_hz": "fast", "loop_misses": 1e300, "battery_v": float("nan"),
           "estop_ack_ms": [1], "reason": 5, "error": ["x"]}
    status = {"mode": "run", "mocap_hz": "fast", "robots": [odd, {"id": 1}, "not a row"],
              "object": {"pose": "here"}, "replay": {"played_s": None}, "recording": "yes", "drops": []}
    text = status_table(status)
    assert max(len(line) for line in text.splitlines()) < 200, text
    rows = text.splitlines()
    assert rows[0].startswith("hub: run  run: -  behaviour: None  source: None  mocap: ? Hz")
    assert rows[2].split()[:3] == ["0", "yes", "?"] and "finished" not in rows[2]
    assert "object: the hub's report of it cannot be read" in text
    assert "replay: the hub's report of it cannot be read" in text


def test_the_agent_does_not_send_telemetry_the_hub_would_drop():
    """The agent checks its messages with the hub's rules: a behaviour's list as its state would have had every
    telemetry dropped, the robot silent at the hub; now encode refuses it, naming the field."""
    with pytest.raises(ProtocolError, match=r"from self: telemetry.behaviour.state: must be a string"):
        encode({"type": "telemetry", "id": 0, "step": 1, "mode": "run", "behaviour": {"state": ["a", "b"]}})
    encode({"type": "telemetry", "id": 0, "step": 1, "mode": "run", "behaviour": {"state": 3, "finished": False}})
