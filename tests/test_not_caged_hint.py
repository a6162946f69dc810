"""A run whose cage did not close says how far the cage got, and whether the time limit cut it short
(sim_backend/transport_metrics.py: _not_caged_hint): a 60 s limit on lab-6 read "cage did not close", the same
words as a cage that could not close."""
import dataclasses

import numpy as np

from sim_backend.scenario import load_scenario
from sim_backend.world import World


def _evaluator(time_limit_s: float):
    # Imported here: importing it registers the transport evaluator, which a test module must not do as it is
    # collected (tests/test_suite_isolation.py).
    from sim_backend.transport_metrics import TransportEvaluator

    scenario = dataclasses.replace(load_scenario("lab-6"), time_limit_s=time_limit_s)
    return TransportEvaluator(scenario, World(scenario, np.random.default_rng(1)))


def _run(evaluator, states_at: dict, until_s: float) -> None:
    """Telemetry every 0.1 s: the robots' states from each time in ``states_at`` on (member: caged)."""
    states = None
    for step in range(int(round(until_s * 10)) + 1):
        t = step / 10
        states = states_at.get(t, states)
        evaluator.on_step(t, [{"state": s, "member": s == "caged"} for s in states])


def test_a_cage_still_forming_at_the_time_limit_asks_for_a_longer_one():
    evaluator = _evaluator(60.0)
    _run(evaluator, {0.0: ["idle"] * 6, 8.0: ["travel"] + ["idle"] * 5, 20.0: ["caged", "travel"] + ["idle"] * 4,
                     40.0: ["caged", "caged", "attach", "travel", "idle", "idle"]}, 60.0)
    assert evaluator.result()["failures"] == [
        "cage did not close", "by its 60 s time limit 2 robots had joined the cage, the last 20 s before the end, "
        "and 2 were on the way to the object or attaching: the cage was still forming, give it a longer time limit "
        "(time_limit_s, --time-limit)"]


def test_a_cage_that_stopped_growing_long_before_the_limit_is_not_blamed_on_it():
    evaluator = _evaluator(600.0)
    _run(evaluator, {0.0: ["idle"] * 6, 20.0: ["caged", "attach"] + ["idle"] * 4}, 600.0)
    failures = evaluator.result()["failures"]
    assert failures == ["cage did not close", "by its 600 s time limit 1 robot had joined the cage, the last 580 s "
                        "before the end, and 1 was on the way to the object or attaching"]
