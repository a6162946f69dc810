"""``khepri bench hub``: a hub process fed by the motioncapture library's mock backend (N rigid bodies at R Hz)
serves N light agents: DEALER sockets in this process, one connection each, that say hello and then only
receive (no telemetry unless ``telemetry_hz`` is given), all polled by one thread.

Latency is measured for every frame, from its pose frame's arrival at the hub (``hub_t``, stamped by the
hub's reader thread right after ``waitForNextFrame`` returns, before the bodies are converted) to the moment
this process takes it off an agent socket (stamped right after ``recv``, before anything is parsed); both
read the same monotonic clock, as they run on one machine. Once the window is over, each frame is decoded and
validated with ``onboard.protocol.decode``, as an agent would; a frame without a pose (whose ``hub_t`` is
its send time) does not count, nor a heartbeat that repeats a pose a robot already had. With ``downlink_hz`` 20 and
120 mocap frames a second, each pose frame is due for about a sixth of the robots, so the p99 is that of
the last robots of each burst. Hub CPU is the hub process's ``process_time`` (all its threads, ZeroMQ's
included) over the window.
"""
from __future__ import annotations

import math
import os
import re
import selectors
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Dict, Iterable, List, Tuple

import numpy as np
import yaml
import zmq

from onboard.agent.link import use_ipv6
from onboard.protocol import DOWNLINK_TYPES, ProtocolError, decode, encode

from .control import request

ROOT = Path(__file__).resolve().parents[1]
LISTENING = re.compile(r"^listening (robots|control) (\S+)$", re.MULTILINE)


def bench_hub(robots: int, rate_hz: float, seconds: float, warmup_s: float = 1.0,
              telemetry_hz: float = 0.0, record: bool = False) -> Dict[str, Any]:
    """``telemetry_hz`` > 0: every agent also sends a small telemetry message at that rate (a real agent's
    load on the hub is 10 Hz), from the same thread, between receives. ``record``: the hub records
    everything to an MCAP log in a temporary folder, as ``khepri hub --record`` does."""
    with tempfile.TemporaryDirectory(prefix="khepri-bench-hub-") as tmp:
        config = Path(tmp) / "bench.yaml"
        settings = bench_config(robots, rate_hz, 0, 0)     # port 0: the hub picks free ones
        if record:
            settings["record"] = str(Path(tmp) / "bench.mcap")
        config.write_text(yaml.safe_dump(settings))
        hub, endpoints = _start_hub(config)
        control = endpoints["control"]
        try:
            sockets = _connect_agents(endpoints["robots"], robots)
            with _ReadySockets(sockets) as ready:
                _collect(sockets, ready, warmup_s, telemetry_hz)
                before = request(control, "status", timeout_s=5.0)["status"]
                started = time.monotonic()
                latencies, last = _collect(sockets, ready, seconds, telemetry_hz, since=started)
                after = request(control, "status", timeout_s=5.0)["status"]
                wall = time.monotonic() - started
            for sock in sockets:
                sock.close(0)
        finally:
            hub.terminate()
            hub.wait(timeout=10.0)
    if not latencies:
        raise RuntimeError("the hub sent no frames during the benchmark")
    values = np.asarray(latencies) * 1000.0
    bursts = np.asarray(list(last.values())) * 1000.0
    return {"latency_p50_ms": round(float(np.percentile(values, 50)), 4),
            "latency_p99_ms": round(float(np.percentile(values, 99)), 4),
            "hub_cpu_percent": round(100.0 * (after["cpu_s"] - before["cpu_s"]) / wall, 2),
            "frames_received": len(latencies), "mocap_hz": after["mocap_hz"],
            "last_robot_p50_ms": round(float(np.percentile(bursts, 50)), 4),    # per pose frame, the slowest robot
            "last_robot_p99_ms": round(float(np.percentile(bursts, 99)), 4),
            "hub_drops": sum(after["drops"].values()) - sum(before["drops"].values()),
            "frames_dropped": sum(r["frames_dropped"] for r in after["robots"])
            - sum(r["frames_dropped"] for r in before["robots"])}


def bench_config(robots: int, rate_hz: float, robot_port: int, control_port: int) -> Dict[str, Any]:
    """Robots on a 0.5 m grid (a crowded 5 x 5 m lab floor for 100): d_C = 3 m gives each dozens of neighbours."""
    side = int(np.ceil(np.sqrt(robots)))
    bodies = [f"kh{i}({(i % side) * 0.5:.2f},{(i // side) * 0.5:.2f},0.05,1,0,0,0)" for i in range(robots)]
    return {
        "source": {"type": "motioncapture", "system": "mock",
                   "options": {"frequency": str(int(round(rate_hz))), "rigid_bodies": ";".join(bodies)},
                   "bodies": {f"kh{i}": i for i in range(robots)}, "up_axis": "z"},
        "network": {"bind": "127.0.0.1", "robot_port": robot_port, "control_port": control_port},
        "security": {"insecure": True},
        "run": {"behaviour": "aggregate"},
    }


def _start_hub(config: Path) -> Tuple[subprocess.Popen, Dict[str, str]]:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    log_path = config.with_suffix(".log")
    with open(log_path, "w", encoding="utf-8") as log:     # a file, not a pipe: nobody has to keep reading it
        hub = subprocess.Popen([sys.executable, "-m", "khepri_cli.main", "hub", "--config", str(config)],
                               stdout=log, stderr=subprocess.STDOUT, env=env)
    deadline = time.monotonic() + 30.0
    try:
        while log_path.read_text(encoding="utf-8").count("listening ") < 2:
            if hub.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the hub did not start: {log_path.read_text(encoding='utf-8')[-500:]}")
            time.sleep(0.05)
    except BaseException:       # also Ctrl-C or a kill while it starts: the hub process must not outlive us
        hub.kill()
        hub.wait(timeout=10.0)
        raise
    return hub, dict(LISTENING.findall(log_path.read_text(encoding="utf-8")))


def _connect_agents(endpoint: str, robots: int) -> List[zmq.Socket]:
    context = zmq.Context.instance()
    sockets = []
    for _ in range(robots):
        sock = context.socket(zmq.DEALER)
        sock.linger = 0
        sock.rcvhwm = 16
        use_ipv6(sock, endpoint)
        sock.connect(endpoint)
        sockets.append(sock)
    time.sleep(0.2)
    for i, sock in enumerate(sockets):
        sock.send(encode({"type": "hello", "id": i, "driver": "bench"}))
    return sockets


class _ReadySockets:
    """Which of the light agents' sockets may have something to read: epoll over their ZeroMQ descriptors.

    A real agent waits on its one socket. ``zmq.Poller`` would rebuild its list of 100 sockets on every call
    (about 20 µs here), and a burst of frames takes several calls, so the last robots' latency would include
    this process's bookkeeping. An epoll registration is kept, so a wait costs the same for 1 socket or 100.
    A ZeroMQ descriptor only signals that the socket's state may have changed: whoever is told about a socket
    reads it until ``zmq.Again``, and a socket that was sent on is read right after (a send may take the
    signal of a message that came in meanwhile)."""

    def __init__(self, sockets: List[zmq.Socket]):
        self.selector = selectors.DefaultSelector()
        for sock in sockets:
            self.selector.register(sock.getsockopt(zmq.FD), selectors.EVENT_READ, sock)

    def wait(self, timeout_s: float) -> List[zmq.Socket]:
        return [key.data for key, _ in self.selector.select(timeout_s)]

    def __enter__(self) -> _ReadySockets:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.selector.close()


def _drain(sock: zmq.Socket, arrived: List[Tuple[zmq.Socket, bytes, float]]) -> None:
    while True:
        try:
            data = sock.recv(zmq.NOBLOCK)
        except zmq.Again:
            return
        arrived.append((sock, data, time.monotonic()))      # stamped before anything is parsed


def _collect(sockets: List[zmq.Socket], ready: _ReadySockets, seconds: float, telemetry_hz: float = 0.0,
             since: float = -math.inf):
    """Receive for ``seconds``: the latency of every frame that carries a pose (from its hub stamp to its
    arrival here), and per pose frame (``hub_t``) the latency of the last robot to get it. Only pose frames
    that reached the hub at ``since`` or later count: frames of earlier ones waited in the sockets while this
    process asked the hub for its status, which is the benchmark's delay, not the hub's."""
    latencies: List[float] = []
    last: Dict[float, float] = {}
    period = 1.0 / telemetry_hz if telemetry_hz > 0 else 1.0
    next_telemetry = [time.monotonic() + period * i / len(sockets) for i in range(len(sockets))]
    steps = [0] * len(sockets)
    arrived: List[Tuple[zmq.Socket, bytes, float]] = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        # Only receive and stamp here: decoding waits until the window is over, so that this thread stays as
        # light as a real agent's and no frame waits for another's decoding.
        woken = ready.wait(0.005 if telemetry_hz > 0 else 0.05)
        for sock in woken:
            _drain(sock, arrived)
        if not woken:       # a quiet spell: make sure no socket holds a frame whose signal was missed
            for sock in sockets:
                if sock.getsockopt(zmq.EVENTS) & zmq.POLLIN:
                    _drain(sock, arrived)
        now = time.monotonic()
        for i, sock in enumerate(sockets if telemetry_hz > 0 else ()):
            if now >= next_telemetry[i]:
                next_telemetry[i] += period
                steps[i] += 1
                sock.send(encode({"type": "telemetry", "id": i, "step": steps[i], "mode": "idle",
                                  "loop": {"hz": 10.0, "steps": steps[i], "misses": 0}}), zmq.NOBLOCK)
                _drain(sock, arrived)
    _account(arrived, since, latencies, last)
    return latencies, last


def _account(arrived: Iterable[Tuple[zmq.Socket, bytes, float]], since: float, latencies: List[float],
             last: Dict[float, float]) -> None:
    """Decode and validate what arrived (as an agent would) and add each pose frame's latency: once per robot
    and pose frame. With motion capture slower than the downlink (``--rate 5``), the hub sends a robot the
    same pose again to keep its watchdog fed; such a frame's age since ``hub_t`` is not latency."""
    seen = set()
    for sock, data, at in arrived:
        try:
            message = decode(data, "hub", accept=DOWNLINK_TYPES)
        except ProtocolError as err:
            raise RuntimeError(f"the hub sent a bad message: {err}") from None
        if message["type"] == "frame" and message["pose"] is not None and message["hub_t"] >= since:
            if (sock, message["hub_t"]) in seen:
                continue
            seen.add((sock, message["hub_t"]))
            latency = at - message["hub_t"]
            latencies.append(latency)
            last[message["hub_t"]] = max(latency, last.get(message["hub_t"], 0.0))
