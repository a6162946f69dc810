"""Running a hub in a background thread and agents as child processes: for benchmarks, tests and scripts.

The hub thread owns its sockets (ZeroMQ sockets stay in the thread that made them); other threads talk to
it over its real control socket, as ``khepri ctl`` does.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Dict, List, Optional

from onboard.agent.parent import PARENT_ENV

from .config import LabConfig
from .control import request
from .factory import build_hub

ROOT = Path(__file__).resolve().parents[1]


class HubThread:
    """``with HubThread(config) as hub:`` binds on free ports; ``hub.endpoints``, ``hub.request(cmd)``."""

    def __init__(self, config: LabConfig, scenario=None, operator_keys: Optional[Dict[str, bytes]] = None,
                 hub_factory=build_hub):
        self.config, self.scenario, self.operator_keys = config, scenario, operator_keys
        self.hub_factory = hub_factory
        self.lines: List[str] = []
        self.endpoints: Dict[str, str] = {}
        self.hub = None
        self.error: Optional[BaseException] = None
        self._ready = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="hub", daemon=True)

    def __enter__(self) -> HubThread:
        self._thread.start()
        if not self._ready.wait(30.0):
            raise RuntimeError("the hub did not start within 30 s")
        if self.error is not None:
            raise self.error
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.stop()

    def _run(self) -> None:
        try:
            self.hub = self.hub_factory(self.config, log=self.lines.append, scenario=self.scenario)
            self.endpoints = self.hub.bind()
        except BaseException as err:      # hand the failure to the starting thread
            if self.hub is not None:
                self.hub.close()          # a socket that did bind, the source's thread, the log
            self.error = err
            self._ready.set()
            return
        self._ready.set()
        try:
            self.hub.serve(self._stop.is_set)
        finally:
            self.hub.close()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10.0)

    def request(self, cmd: str, timeout_s: float = 3.0) -> Dict[str, Any]:
        return request(self.endpoints["control"], cmd, keys=self.operator_keys, timeout_s=timeout_s)

    def status(self) -> Dict[str, Any]:
        return self.request("status")["status"]

    def wait_for_lines(self, fragment: str, count: int = 1, timeout_s: float = 10.0) -> List[str]:
        """The hub's log lines holding ``fragment`` once there are ``count`` of them; TimeoutError naming every
        line logged, should they not come within ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            found = [line for line in list(self.lines) if fragment in line]
            if len(found) >= count:
                return found
            if time.monotonic() > deadline:
                raise TimeoutError(f"no {count} line(s) with {fragment!r} within {timeout_s} s: {self.lines}")
            time.sleep(0.02)

    def wait_until(self, condition, timeout_s: float = 20.0, poll_s: float = 0.05) -> Dict[str, Any]:
        """Poll status until ``condition(status)``; the last status, or TimeoutError naming what it saw."""
        deadline = time.monotonic() + timeout_s
        status = self.status()
        while not condition(status):
            if time.monotonic() > deadline:
                raise TimeoutError(f"condition not met within {timeout_s} s; last status: {status}")
            time.sleep(poll_s)
            status = self.status()
        return status


def khepri_env() -> Dict[str, str]:
    """This environment with this khepri's root first on PYTHONPATH: a child Python (an agent, a hub, another
    interpreter's check) imports the same onboard/ and hub/ as this process."""
    return dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))


def spawn_agent(endpoint: str, robot_id: int, log_path: Path, keys: Optional[Path] = None,
                driver: str = "sim", extra: Optional[List[str]] = None,
                python: Optional[str] = None) -> subprocess.Popen:
    """A real agent process (``python -m onboard.agent``, with ``python`` or else this interpreter) writing its
    log to ``log_path``. It ends (SIGTERM: wheels stopped) when the thread that started it does, even if this
    process is killed with SIGKILL (``onboard/agent/parent.py``), so start agents from a thread that outlives
    them."""
    env = khepri_env()
    env[PARENT_ENV] = str(os.getpid())
    command = [python or sys.executable, "-m", "onboard.agent", "--id", str(robot_id), "--hub", endpoint,
               "--driver", driver]
    if keys is not None:
        command += ["--keys", str(keys)]
    command += extra or []
    with open(log_path, "w", encoding="utf-8") as log:
        return subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=env)


def stop_processes(processes: List[subprocess.Popen], timeout_s: float = 20.0) -> List[int]:
    """SIGTERM each, wait (all together, up to ``timeout_s``: a loaded PC is slow to end 25 interpreters),
    SIGKILL stragglers; the exit codes (-9 for a killed straggler)."""
    for process in processes:
        if process.poll() is None:
            process.terminate()
            _continue(process)     # a stopped one (SIGSTOP, Ctrl-Z) handles SIGTERM only once it runs again
    codes = []
    deadline = time.monotonic() + timeout_s
    for process in processes:
        try:
            codes.append(process.wait(timeout=max(0.1, deadline - time.monotonic())))
        except subprocess.TimeoutExpired:
            process.kill()
            codes.append(process.wait())
    return codes


def _continue(process: subprocess.Popen) -> None:
    if hasattr(signal, "SIGCONT"):
        try:
            os.kill(process.pid, signal.SIGCONT)
        except OSError:        # gone meanwhile
            pass


class ScriptedHub:
    """A hub socket driven by a script instead of a source: send exactly the frames and commands you want to
    one agent and see everything it sends back, with arrival times. For agent tests and debugging."""

    def __init__(self, context=None):
        import zmq

        from onboard.protocol import UPLINK_TYPES, decode, encode

        self._zmq, self._decode, self._encode, self._uplink = zmq, decode, encode, UPLINK_TYPES
        self.context = context or zmq.Context.instance()
        self.socket = self.context.socket(zmq.ROUTER)
        self.socket.linger = 0
        self.socket.bind("tcp://127.0.0.1:*")
        self.endpoint = self.socket.getsockopt_string(zmq.LAST_ENDPOINT)
        self.routing: Optional[bytes] = None
        self.received: List[Dict[str, Any]] = []     # each with "_at": monotonic arrival time
        self.seq = 0

    def pump(self, timeout_s: float = 0.0) -> None:
        if not self.socket.poll(timeout_s * 1000.0):
            return
        while True:
            try:
                routing, data = self.socket.recv_multipart(self._zmq.NOBLOCK)
            except self._zmq.Again:
                return
            message = self._decode(data, "agent", accept=self._uplink)
            message["_at"] = time.monotonic()
            self.routing = routing
            self.received.append(message)

    def wait_for(self, predicate, timeout_s: float = 15.0) -> Dict[str, Any]:
        """The first received message (old or new) matching ``predicate``."""
        deadline = time.monotonic() + timeout_s
        checked = 0
        while True:
            for message in self.received[checked:]:
                if predicate(message):
                    return message
            checked = len(self.received)
            if time.monotonic() > deadline:
                raise TimeoutError(f"no matching message within {timeout_s} s (got {len(self.received)})")
            self.pump(0.02)

    def send(self, message: Dict[str, Any]) -> None:
        self.socket.send_multipart([self.routing, self._encode(message)])

    def send_raw(self, data: bytes) -> None:
        self.socket.send_multipart([self.routing, data])

    def frame(self, mode: str = "run", **fields: Any) -> Dict[str, Any]:
        """Send a valid frame (defaults: pose at the origin, no neighbours, quiet IR); returns it."""
        self.seq += 1
        frame = {"type": "frame", "seq": self.seq, "mode": mode, "hub_t": time.monotonic(), "pose": [0.0, 0.0, 0.0],
                 "pose_age_s": 0.0, "neighbours": [], "messages": [], "sim": {"ir": [0.0] * 8, "odo": [0.0, 0.0]}}
        frame.update(fields)
        self.send(frame)
        return frame

    def close(self) -> None:
        self.socket.close(0)
