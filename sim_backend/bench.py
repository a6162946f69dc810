"""``khepri bench sim``: how fast the simulator runs the paper's boxes with 25, 50 and 100 robots.

Besides the real-time factor, each case says where the time went: milliseconds of wall time per simulated
second in each phase of the control loop (``runner.PHASES``), so a slow case points at its cause.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Any, Dict, List

from onboard.config import ConfigError

from .runner import Simulation
from .scenario import load_scenario

PAPER_SCENARIO = {25: "paper-25-straight", 50: "paper-50-straight", 100: "paper-100-straight"}


def bench_sim(counts: List[int], seconds: float, behaviour: str) -> List[Dict[str, Any]]:
    return [bench_case(count, seconds, behaviour) for count in counts]


def bench_case(count: int, seconds: float, behaviour: str) -> Dict[str, Any]:
    base = load_scenario(PAPER_SCENARIO.get(count, "paper-100-straight"))
    robots = base.robots if count in PAPER_SCENARIO else dataclasses.replace(base.robots, count=count)
    scenario = base.with_overrides(behaviour=behaviour, params={}, robots=robots)
    try:
        sim = Simulation(scenario)
    except ConfigError as err:       # name the option the user typed, not a scenario field they cannot set
        if err.field == "behaviour":
            raise ConfigError("--behaviour", err.problem) from None
        if err.field.startswith("robots"):
            raise ConfigError("--robots", f"{count} robots do not fit where {base.name} starts its robots "
                                          f"({err.field}: {err.problem.split(': make')[0]})") from None
        raise
    started, cpu_started = time.perf_counter(), time.process_time()
    result = sim.run(time_limit_s=seconds)
    wall, cpu = time.perf_counter() - started, time.process_time() - cpu_started
    sim_seconds = round(sim.step_index * sim.period, 6)
    per_sim_second = 1000.0 / sim_seconds if sim_seconds > 0 else 0.0
    # A crashed behaviour ends the run early: its speed is not the behaviour's, and the crash must be seen.
    crash = {"stop_reason": result["stop_reason"], "error": result["error"]} if result.get("error") else {}
    return {
        **crash, "robots": count, "behaviour": behaviour, "scenario": base.name, "sim_seconds": sim_seconds,
        "wall_seconds": wall, "cpu_seconds": cpu,
        "physics_steps_per_s": sim.step_index * sim.substeps / wall,
        "real_time_factor": sim_seconds / wall,
        # CPU time of this process: the same figure on a busy machine, where other processes steal wall time.
        "cpu_real_time_factor": sim_seconds / cpu if cpu > 0 else None,
        "phase_ms_per_sim_s": {name: round(spent * per_sim_second, 2) for name, spent in sim.phase_times().items()},
    }
