"""``khepri bench hub``: a hub process fed by the motioncapture library's mock backend (N rigid bodies at R Hz)
serves N light agents (DEALER sockets in this process that only timestamp what arrives).

Latency is measured from a frame's arrival at the hub (its ``hub_t`` stamp, taken by the reader thread right
after ``waitForNextFrame`` returns) to its arrival at an agent socket; both sides read the same monotonic
clock, as they run on one machine. Hub CPU comes from the hub's own ``process_time`` over the window.
"""
from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Dict, List

import numpy as np
import yaml
import zmq

from onboard.protocol import encode

from .control import request

ROOT = Path(__file__).resolve().parents[1]
HUB_T = re.compile(rb'"hub_t":([0-9.eE+-]+)')


def bench_hub(robots: int, rate_hz: float, seconds: float, warmup_s: float = 1.0) -> Dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="khepri-bench-hub-") as tmp:
        robot_port, control_port = _free_port(), _free_port()
        config = Path(tmp) / "bench.yaml"
        config.write_text(yaml.safe_dump(bench_config(robots, rate_hz, robot_port, control_port)))
        hub = _start_hub(config)
        control = f"tcp://127.0.0.1:{control_port}"
        try:
            sockets = _connect_agents(f"tcp://127.0.0.1:{robot_port}", robots)
            _collect(sockets, warmup_s)
            before = request(control, "status", timeout_s=5.0)["status"]
            started = time.monotonic()
            latencies = _collect(sockets, seconds)
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
    return {"latency_p50_ms": round(float(np.percentile(values, 50)), 4),
            "latency_p99_ms": round(float(np.percentile(values, 99)), 4),
            "hub_cpu_percent": round(100.0 * (after["cpu_s"] - before["cpu_s"]) / wall, 2),
            "frames_received": len(latencies), "mocap_hz": after["mocap_hz"]}


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


def _start_hub(config: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    log_path = config.with_suffix(".log")
    with open(log_path, "w", encoding="utf-8") as log:     # a file, not a pipe: nobody has to keep reading it
        hub = subprocess.Popen([sys.executable, "-m", "khepri_cli.main", "hub", "--config", str(config)],
                               stdout=log, stderr=subprocess.STDOUT, env=env)
    deadline = time.monotonic() + 30.0
    while log_path.read_text(encoding="utf-8").count("listening ") < 2:
        if hub.poll() is not None or time.monotonic() > deadline:
            hub.kill()
            raise RuntimeError(f"the hub did not start: {log_path.read_text(encoding='utf-8')[-500:]}")
        time.sleep(0.05)
    return hub


def _connect_agents(endpoint: str, robots: int) -> List[zmq.Socket]:
    context = zmq.Context.instance()
    sockets = []
    for _ in range(robots):
        sock = context.socket(zmq.DEALER)
        sock.linger = 0
        sock.rcvhwm = 16
        sock.connect(endpoint)
        sockets.append(sock)
    time.sleep(0.2)
    for i, sock in enumerate(sockets):
        sock.send(encode({"type": "hello", "id": i, "driver": "bench"}))
    return sockets


def _collect(sockets: List[zmq.Socket], seconds: float) -> List[float]:
    """Receive for ``seconds``; the latency of every frame, from its hub stamp to its arrival here."""
    poller = zmq.Poller()
    for sock in sockets:
        poller.register(sock, zmq.POLLIN)
    latencies: List[float] = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for sock, _ in poller.poll(50):
            while True:
                try:
                    data = sock.recv(zmq.NOBLOCK)
                except zmq.Again:
                    break
                arrived = time.monotonic()
                match = HUB_T.search(data)
                if match and data.startswith(b'{"type":"frame"'):
                    latencies.append(arrived - float(match.group(1)))
    return latencies


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
