"""``khepri bench estop``: how long after ``khepri ctl estop`` every one of N real agent processes has stopped
its wheels.

The hub runs in a thread of this process with the ``sim`` source (physics as the robots), and each robot is a
real agent process (``python -m onboard.agent --driver sim``) running the ``aggregate`` behaviour. Once all
agents run, the e-stop is requested over the hub's real control socket, as ``khepri ctl estop`` does; then it
is cleared and the run resumed, ``repeats`` times.

What is timed, on the one monotonic clock this process and its hub thread share:

- ``transit``: from the request leaving here to the hub latching the e-stop (its ``estop_at``);
- ``ack``: per agent, from the latch to the agent's acknowledgement arriving at the hub. An agent sends it
  after it has closed its wheel gate, so it includes the agent's stop and the way back.

``transit + the slowest ack`` bounds the operator-to-wheels time of the slowest agent from above. On one PC all
the agents share its cores, as they never do on a fleet (each robot has its own CPU): a loaded machine shows
in these figures, which is why they are a benchmark and not a test.
"""
from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional

import numpy as np

from sim_backend.scenario import parse_scenario  # the sim source's world: this benchmark needs it anyway

from .config import parse_config
from .harness import HubThread, spawn_agent, stop_processes

RUNNING_BEFORE_ESTOP_S = 0.5     # the agents step their behaviour for this long before each e-stop


@dataclass
class EstopTrial:
    """One e-stop: the request's transit to the latch and each agent's acknowledgement (ms)."""

    transit_ms: float
    acks_ms: List[float]
    note: str

    @property
    def worst_ms(self) -> float:
        return self.transit_ms + max(self.acks_ms)


@dataclass
class EstopBench:
    robots: int
    trials: List[EstopTrial] = field(default_factory=list)
    exit_codes: List[int] = field(default_factory=list)

    def summary(self) -> Dict[str, Any]:
        worst = [trial.worst_ms for trial in self.trials]
        acks = np.concatenate([trial.acks_ms for trial in self.trials])
        return {"robots": self.robots, "repeats": len(self.trials),
                "worst_ms_p50": round(float(np.percentile(worst, 50)), 2),
                "worst_ms_max": round(float(max(worst)), 2),
                "transit_ms_max": round(max(trial.transit_ms for trial in self.trials), 2),
                "ack_ms_p50": round(float(np.percentile(acks, 50)), 2),
                "ack_ms_max": round(float(acks.max()), 2)}


def bench_scenario(robots: int):
    """``robots`` KheperaIVs scattered on a floor big enough for them, running ``aggregate``."""
    half = max(1.0, 0.35 * np.sqrt(robots))
    return parse_scenario({"name": "bench-estop", "behaviour": "aggregate", "time_limit_s": 3600,
                           "robots": {"count": robots, "spawn": {"x": [-half, half], "y": [-half, half]}},
                           "arena": {"walls": [-half - 1.0, -half - 1.0, half + 1.0, half + 1.0]}})


def bench_estop(robots: int, repeats: int = 3, connect_timeout_s: Optional[float] = None) -> EstopBench:
    """``connect_timeout_s`` (default: 30 s plus 1 s per agent, as each starts an interpreter on this PC's
    cores): how long the agents may take to connect; RuntimeError says how many did."""
    if connect_timeout_s is None:
        connect_timeout_s = 30.0 + 1.0 * robots
    config = parse_config({"source": {"type": "sim", "frame_hz": 20},
                           "network": {"bind": "127.0.0.1", "robot_port": 0, "control_port": 0},
                           "security": {"insecure": True}})
    result = EstopBench(robots)
    with tempfile.TemporaryDirectory(prefix="khepri-bench-estop-") as tmp, \
            HubThread(config, scenario=bench_scenario(robots)) as hub:
        agents: List = []
        try:       # spawned inside: a Ctrl-C or a kill while they start stops those already started
            for i in range(robots):
                agents.append(spawn_agent(hub.endpoints["robots"], i, Path(tmp) / f"agent-{i}.log", extra=["--quiet"]))
            _wait_for_all(hub, "connected", lambda r: r["connected"], connect_timeout_s)
            for _ in range(repeats):
                result.trials.append(_one_estop(hub))
        finally:
            result.exit_codes = stop_processes(agents)
    return result


def _one_estop(hub: HubThread) -> EstopTrial:
    hub.request("start")           # the first time a new run; after a clear, the run resumes
    _wait_for_all(hub, "running the behaviour", lambda r: r["agent_mode"] == "run", 30.0)
    time.sleep(RUNNING_BEFORE_ESTOP_S)                 # running behaviours, not idle agents
    sent = time.monotonic()
    reply = hub.request("estop")
    transit_ms = (hub.hub.estop_at - sent) * 1000.0
    status = _wait_for_all(hub, "acknowledged the e-stop", lambda r: r["estop_ack_ms"] is not None, 10.0)
    _wait_for_all(hub, "in e-stop", lambda r: r["agent_mode"] == "estop", 5.0)
    trial = EstopTrial(transit_ms, sorted(r["estop_ack_ms"] for r in status["robots"]), reply.get("note", ""))
    hub.request("clear")
    return trial


def _wait_for_all(hub: HubThread, what: str, condition: Callable[[Dict[str, Any]], bool],
                  timeout_s: float) -> Dict[str, Any]:
    """The status once every robot's row meets ``condition``; else RuntimeError: how many did, and which not."""
    try:
        return hub.wait_until(lambda s: all(condition(r) for r in s["robots"]), timeout_s=timeout_s)
    except TimeoutError:
        rows = hub.status()["robots"]
        late = [str(r["id"]) for r in rows if not condition(r)]
        named = ", ".join(late[:10]) + (", ..." if len(late) > 10 else "")
        raise RuntimeError(f"only {len(rows) - len(late)} of {len(rows)} agents {what} within {timeout_s:g} s "
                           f"(not: robots {named})") from None
