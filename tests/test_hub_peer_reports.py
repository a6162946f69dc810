"""What an agent reports is checked where it arrives and shown safely: the hub drops telemetry whose values are
not what docs/protocol.md says (naming the field and the sender), and `khepri ctl status` prints whatever a
hub reports without failing. Real sockets on loopback."""
import json
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Optional

import pytest
import zmq

from hub.config import parse_config
from hub.control import status_table
from hub.harness import HubThread
from hub.recording import read_log
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
            line = hub.wait_for_lines("dropped bad message", timeout_s=5.0)[0]
        finally:
            sock.close(0)
        status = hub.status()
    assert line.startswith(f"hub: dropped bad message: from peer at 127.0.0.1: {said}"), line
    assert status["drops"] == {"bad message": 1}
    row = status["robots"][0]
    assert row["state"] is None and row["finished"] is None and row["battery_v"] is None
    assert row["loop_misses"] is None and row["frames_lost"] is None


class Peer(threading.Thread):
    """A hand-made agent for robot 0 that says hello, acknowledges every command and sends ``report(run_id)`` as
    its telemetry every 0.1 s (``run_id``: the run the hub last started, None before), until ``stop()``."""

    def __init__(self, endpoint: str, report: Callable[[Optional[str]], dict], hello: Optional[dict] = None):
        super().__init__(daemon=True)
        self.endpoint, self.report, self.hello = endpoint, report, hello or {"driver": "sim"}
        self.run_id: Optional[str] = None
        self.done = threading.Event()

    def run(self) -> None:
        sock = peer(self.endpoint)
        try:
            sock.send(raw({"type": "hello", "id": 0, **self.hello}))
            step = 0
            while not self.done.is_set():
                while sock.poll(0):
                    message = sock.recv()
                    if message.startswith(b"{"):
                        command = json.loads(message)
                        self.run_id = (command.get("run") or {}).get("run_id", self.run_id)
                        sock.send(encode({"type": "ack", "id": 0, "cmd": command["cmd"]}))
                step += 1
                sock.send(telemetry(step, **self.report(self.run_id)))
                time.sleep(0.1)
        finally:
            sock.close(0)

    def stop(self) -> None:
        self.done.set()
        self.join(5.0)


def test_a_finished_that_is_not_true_or_false_does_not_end_a_run_for_the_hub():
    """`"finished": "no"` made the hub say that every connected robot reports its job finished."""
    with HubThread(parse_config(SIM)) as hub:
        agent = Peer(hub.endpoints["robots"], lambda run_id: {
            "mode": "run" if run_id else "idle", "run_id": run_id, "driver": "sim",
            "behaviour": {"state": "pushing", "finished": "no"}})
        agent.start()
        try:
            hub.request("start")
            time.sleep(2.0)
            status = hub.status()
        finally:
            agent.stop()
    assert agent.run_id is not None, "the hub never sent start"
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
            hub.wait_for_lines("telemetry.loop.hz", timeout_s=5.0)
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


# A robot's text that tries to be read as the hub's: a line of its own (newline, carriage return), colours
# (ESC, and C1's CSI), a Unicode line separator.
EVIL = "\x1b[31mRED\x1b[0m\nhub: run 123 completed (FAKE LINE)\r\u2028\x9b2J"
SHOWN = "\\x1b[31mRED\\x1b[0m\\x0ahub: run 123 completed (FAKE LINE)\\x0d\\u2028\\x9b2J"
CONTROL = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029]")


def khepri(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "khepri_cli.main", *args], capture_output=True, text=True,
                          env=ENV, timeout=60)


def test_a_robots_text_makes_no_line_of_its_own_on_the_hubs_console_in_its_log_or_in_ctl_status(tmp_path):
    """The hub escaped ESC but not newline or carriage return: a robot's error, driver or run id put a line of its
    own making on the console and in the recorded /hub/log, and `ctl status` printed the raw ANSI and newline."""
    log = tmp_path / "run.mcap"
    with HubThread(parse_config({**SIM, "record": str(log)})) as hub:
        agent = Peer(hub.endpoints["robots"], lambda run_id: {"driver": EVIL, "error": EVIL, "mode": EVIL,
                                                              "behaviour": {"state": EVIL}},
                     hello={"driver": EVIL, "run_id": EVIL})
        agent.start()
        try:
            hub.wait_for_lines("hub: robot 0: ", timeout_s=5.0)
            hub.wait_for_lines("which this hub did not start", timeout_s=5.0)
            status = khepri("ctl", "status", "--hub", hub.endpoints["control"])
        finally:
            agent.stop()
    assert f"hub: robot 0: {SHOWN}" in hub.lines
    assert f"hub: robot 0 was in run {SHOWN}, which" in "\n".join(hub.lines)
    assert not [line for line in hub.lines if CONTROL.search(line)], hub.lines
    recorded = [record.payload["message"] for record in read_log(log, topics=["/hub/log"])]
    assert f"hub: robot 0: {SHOWN}" in recorded and not [line for line in recorded if CONTROL.search(line)]
    printed = khepri("log", "console", str(log)).stdout.splitlines()
    assert printed and all(re.match(r"\d{4}-\d\d-\d\d ", line) for line in printed), printed
    assert status.returncode == 0, status.stderr
    row = next(line for line in status.stdout.splitlines() if line.lstrip().startswith("0 "))
    assert not CONTROL.search(status.stdout.replace("\n", "")), status.stdout
    assert "\\x1b[31mRED" in row and row.endswith(SHOWN), row


def test_log_console_escapes_a_line_an_older_hub_recorded_as_it_came(tmp_path):
    from hub.console import console_record
    from hub.recording import Recorder

    log = tmp_path / "old.mcap"
    with Recorder(log) as recorder:
        recorder.write("/hub/log", console_record(f"hub: robot 0: {EVIL}", time.time()))
    shown = khepri("log", "console", str(log))
    assert shown.returncode == 0 and shown.stdout.count("\n") == 1 and shown.stdout.rstrip().endswith(SHOWN), shown


def test_ctl_start_prints_a_robots_refusal_on_one_line():
    """`khepri ctl start` printed a robot's error as it came: its newline made a line of the robot's making."""
    with HubThread(parse_config(SIM)) as hub:
        agent = Peer(hub.endpoints["robots"], lambda run_id: {"error": EVIL, "refused_run_id": run_id} if run_id
                     else {})
        agent.start()
        try:
            hub.wait_until(lambda s: s["robots"][0]["connected"])
            started = khepri("ctl", "start", "--hub", hub.endpoints["control"])
        finally:
            agent.stop()
    assert started.returncode == 1, started
    assert f"khepri: error: robot 0: {SHOWN}\n" in started.stderr and "\x1b" not in started.stderr, started.stderr


def test_the_status_table_shows_a_robots_text_escaped_and_its_columns_stay_in_line():
    rows = [{"id": 0, "connected": True, "last_seen_s": 0.1, "mode": "run", "state": "push", "loop_hz": 10.0},
            {"id": 1, "connected": True, "last_seen_s": 0.1, "mode": "run", "state": "a\tb\nc", "loop_hz": 10.0,
             "error": EVIL}]
    header, first, second = status_table({"mode": "run", "source": "sim", "mocap_hz": 50.0, "robots": rows,
                                          "run_id": "r\n1"}).splitlines()[1:]
    assert second.split()[5] == "a\\x09b\\x0ac" and second.endswith(SHOWN)
    assert first.index("10.0") == second.index("10.0")
    assert status_table({"mode": "idle", "source": "sim", "mocap_hz": 0.0, "robots": [],
                         "run_id": "r\n1"}).startswith("hub: idle  run: r\\x0a1  ")


def test_the_agent_does_not_send_telemetry_the_hub_would_drop():
    """The agent checks its messages with the hub's rules: a behaviour's list as its state would have had every
    telemetry dropped, the robot silent at the hub; now encode refuses it, naming the field."""
    with pytest.raises(ProtocolError, match=r"from self: telemetry.behaviour.state: must be a string"):
        encode({"type": "telemetry", "id": 0, "step": 1, "mode": "run", "behaviour": {"state": ["a", "b"]}})
    encode({"type": "telemetry", "id": 0, "step": 1, "mode": "run", "behaviour": {"state": 3, "finished": False}})
