"""A peer's tuple-space entries are input from the network. The transport refuses, where they arrive, the ones
of a shape its readers cannot take (onboard/behaviours/transport/entries.py): one peer's `{"bid": "soon"}` used
to raise in the step of every robot that merged it, and a robot whose step raises stops."""
import math

import pytest

from onboard.behaviours.transport.entries import entry_problem
from onboard.behaviours.transport.tasks import new_space
from sim_backend.runner import Simulation
from sim_backend.scenario import load_scenario

WINS = 10 ** 6      # a timestamp newer than any the swarm writes: the entry would replace what is held
TASK = {"x": 0.5, "y": 0.5, "branch": "L", "index": 1, "pred": 3, "epoch": 0, "cancelled": False}

HOSTILE = [       # (key, value) from robot 99, and what the refusal says
    ("bid/S/0", {"robot": 99, "bid": "soon"}, "bid is not a finite number (got 'soon')"),
    ("bid/S/0", {"robot": 99, "bid": math.nan}, "the value holds NaN or an infinity, which JSON cannot carry"),
    ("owner/S", {"robot": [1], "bid": 0.1, "epoch": 0}, "robot is not a whole number >= 0 (got [1])"),
    ("grow", {"level": "x"}, 'must be {"level": 0 .. 200}'),
    ("member/98", [1, 2], "must be a mapping"),
    ("member/98", {"tid": "L1", "branch": "L", "index": 1, "dead": "yes"}, "dead must be true or false"),
    ("pos/98", ["a", 0.0, None, None], "x and y must be finite numbers"),
    ("pos/98", [0.0, 0.0, None, [1.0]], "surface must be [x, y] or null"),
    ("path", [[1.0]], "every waypoint must be [x, y, yaw_deg], finite numbers"),
    ("task/S", dict(TASK, x="nan", branch="S", index=0), "x is not a finite number (got 'nan')"),
    ("task/Q1", dict(TASK, branch="Q"), "branch is not S, L or R (got 'Q')"),
    ("task/L2", TASK, "task id 'L2' does not match its branch and index ('L1')"),
    ("task/L1", dict(TASK, epoch=True), "epoch is not a whole number >= 0 (got True)"),
    ("arrive/0/p/\u00b2", 1, "the key is not arrive/<waypoint>/<p|r|c>/<robot id>"),
    ("arrive/0/p/" + "9" * 5000, 1, "the key is not arrive/<waypoint>/<p|r|c>/<robot id>"),   # int() refuses it
    ("member/" + "9" * 5000, {"tid": "L1", "branch": "L", "index": 1}, "the key is not member/<robot id>"),
    ("closed", {"pair": [1]}, 'must be {"pair": [robot id, robot id]}'),
    ("done", True, "must be 1"),
]


@pytest.mark.parametrize("key, value, problem", HOSTILE, ids=[f"{k[:24]}:{p[:20]}" for k, _, p in HOSTILE])
def test_a_peers_entry_of_the_wrong_shape_is_refused_naming_what_is_wrong(key, value, problem):
    space = new_space(owner=0)
    assert space.merge([[key, value, WINS, 99]], sender=99) == []
    assert key not in space and space.outgoing() == []           # neither stored nor relayed
    assert space.refused == 1 and space.last_refusal == f"robot 99's {key}: {problem}"


def test_the_shapes_the_transport_writes_pass():
    good = [("task/S", dict(TASK, branch="S", index=0, pred=None)), ("task/L1", TASK),
            ("bid/L1/3", {"robot": 4, "bid": 0.25}), ("owner/R12", {"robot": 4, "bid": 1, "epoch": 2}),
            ("member/4", {"tid": "L1", "branch": "L", "index": 1, "dead": True}),
            ("pos/4", [0.1, -2, None, None]), ("pos/4", [0.1, -2.0, 3.1, [0.2, 0.3]]),
            ("closed", {"pair": [2, 5]}), ("grow", {"level": 3}), ("path", [[0, 0.3, 90.0], [0.0, 0.6, 0]]),
            ("arrive/2/r/4", 1), ("done", 1), ("mine/anything", {"x": "a behaviour's own family"})]
    assert [entry_problem(key, value) for key, value in good] == [None] * len(good)


def test_lab6_completes_with_every_hostile_entry_merged_into_every_robot():
    sim = Simulation(load_scenario("lab-6"), seed=1)
    sim.step()
    for behaviour in sim.behaviours:
        behaviour.space.merge([[key, value, WINS, 99] for key, value, _ in HOSTILE], sender=99)
    result = sim.run()
    assert result["caged"] and result["completed"], result["failures"]
    for behaviour in sim.behaviours:
        said = behaviour.telemetry()
        assert said["refused_entries"] >= len(HOSTILE)
        assert said["last_refused"] == "robot 99's done: must be 1"
        # What the swarm wrote itself is of its shapes: the check refuses nothing of the behaviour's own.
        assert [key for key in behaviour.space.keys() if entry_problem(key, behaviour.space.get(key))] == []
