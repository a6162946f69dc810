"""``khepri bench sim``: how fast the simulator runs the paper's boxes with 25, 50 and 100 robots."""
from __future__ import annotations

import time
from typing import Any, Dict, List

from .runner import Simulation
from .scenario import load_scenario

PAPER_SCENARIO = {25: "paper-25-straight", 50: "paper-50-straight", 100: "paper-100-straight"}


def bench_sim(counts: List[int], seconds: float, behaviour: str) -> List[Dict[str, Any]]:
    results = []
    for count in counts:
        base = load_scenario(PAPER_SCENARIO.get(count, "paper-100-straight"))
        robots = base.robots if count in PAPER_SCENARIO else _resized(base.robots, count)
        scenario = base.with_overrides(behaviour=behaviour, params={}, robots=robots)
        sim = Simulation(scenario)
        started = time.perf_counter()
        sim.run(time_limit_s=seconds)
        wall = time.perf_counter() - started
        sim_seconds = sim.step_index * sim.period
        results.append({
            "robots": count, "behaviour": behaviour, "scenario": base.name, "sim_seconds": sim_seconds,
            "wall_seconds": wall, "physics_steps_per_s": sim.step_index * sim.substeps / wall,
            "real_time_factor": sim_seconds / wall,
        })
    return results


def _resized(robots, count):
    import dataclasses

    return dataclasses.replace(robots, count=count)
