"""Closure of the cage (docs/behaviour.md section 3): the paper's d_T, and ours for two tips on opposite sides
of the object, which would leave a whole end of it open; and a robot attaching on the wrong side of its
predecessor, which would slide round the object through the branch."""
import math

import pytest

from onboard.behaviours.transport.perception import Percept
from onboard.behaviours.transport.tasks import Task
from sim_backend.runner import Simulation
from sim_backend.scenario import load_scenario, parse_scenario

LONG_BOX = {
    "name": "long-box",
    "behaviour": "transport",
    "robots": {"count": 10, "spawn": {"x": [-1.8, -0.8], "y": [-1.8, -1.0]}},
    "object": {"shape": "box", "size": [1.0, 0.3], "mass": 0.6},
    "path": [[0, 0.4, 0], [0, 0.8, 0], [0.5, 0.8, 0]],
    "arena": {"walls": [-2.5, -2.5, 2.5, 2.5]},
    "time_limit_s": 600,
}


def _tip_facing(transport, robot: int, x: float, y: float, normal_deg: float) -> None:
    """Robot ``robot``'s heartbeat as it reaches this one: where it is and which way its IR sees the object."""
    transport.board.space.put(f"pos/{robot}", [x, y, round(math.radians(normal_deg), 3), None])


@pytest.fixture
def tip():
    """A branch tip above the object (its IR sees the object straight below it)."""
    transport = Simulation(load_scenario("lab-6"), seed=1).behaviours[0]
    transport.percept = Percept(0.0, 0.3, 0.0, {}, (0.0, -1.0), 0.9, (0.0, 0.0))
    return transport


def test_tips_on_opposite_sides_close_only_near_while_robots_remain(tip):
    p = tip.params
    _tip_facing(tip, 5, 0.6, -0.3, 90.0)           # below the object, seeing it above: the end between is open
    _tip_facing(tip, 6, 0.6, 0.0, 180.0)           # at the end, seeing it to its left: one corner between
    assert tip._closure_distance(5) == pytest.approx(p.end_gap_closure_factor * p.inter_robot_distance_m)
    assert tip._closure_distance(6) == pytest.approx(p.closure_factor * p.inter_robot_distance_m)
    # A tip near a corner sees the object obliquely; one such reading does not reopen the paper's d_T.
    _tip_facing(tip, 5, 0.6, -0.3, 51.0)
    assert tip._closure_distance(5) == pytest.approx(p.end_gap_closure_factor * p.inter_robot_distance_m)
    # Out of robots (I_d grows): the paper's d_T, or the cage would never close.
    tip.space.put("grow", {"level": 1})
    assert tip._closure_distance(5) == pytest.approx(p.closure_factor * p.inter_robot_distance_m * 1.02)


def test_without_contact_or_in_the_faithful_profile_the_paper_closure_applies(tip):
    p = tip.params
    _tip_facing(tip, 5, 0.6, -0.3, 90.0)
    tip.percept = Percept(0.0, 0.3, 0.0, {}, (0.0, -1.0), 0.2, (0.0, 0.0))     # too far to read contact
    assert tip._closure_distance(5) == pytest.approx(p.closure_factor * p.inter_robot_distance_m)
    faithful = Simulation(load_scenario("lab-6").with_overrides(params={"profile": "faithful"}), seed=1)
    assert faithful.behaviours[0].params.end_gap_closure_factor == faithful.behaviours[0].params.closure_factor


def test_a_long_box_is_caged_at_both_ends():
    """A 1.0 x 0.3 m box and 10 robots (a user's scenario, seed 1): with the paper's d_T alone the cage closed
    with 5 members and the gap over the box's right end (its tips 0.83 m apart, one above, one below), and
    when the path turned along the box nobody was behind it: it ended 0.21 m short. Now a sixth robot
    closes that end before the ring does."""
    sim = Simulation(parse_scenario(LONG_BOX), seed=1)
    while sim.step_index * sim.period < 150.0 and not any(b.state == "settle" for b in sim.behaviours):
        sim.step()
    members = [i for i, b in enumerate(sim.behaviours) if b.state == "settle"]
    assert members, "the cage did not close within 150 s"
    ox, oy, yaw = sim.world.object_pose()
    along = [math.cos(yaw) * (x - ox) + math.sin(yaw) * (y - oy)
             for x, y, _ in (sim.world.robot_poses()[i] for i in members)]
    assert max(along) > 0.5 and min(along) < -0.5, f"members along the box: {sorted(along)}"


def _attaching(transport, monkeypatch, errors):
    """``transport`` attaching for slot L2 behind robot 5, touching the object, whose distance error to robot 5
    is each of ``errors`` in turn (one per call of _on_attach)."""
    transport.task = Task("L2", 0.6, 0.3, "L", 2, 5, 0)
    transport.board.put_task(transport.task)
    transport.state, transport.attach_since, transport.closest_error = "attach", 0.0, math.inf
    monkeypatch.setattr(transport, "_still_mine", lambda: True)
    readings = iter(errors)
    monkeypatch.setattr(transport, "_predecessor_error", lambda: next(readings))


def test_an_attaching_robot_sliding_the_wrong_way_gives_its_slot_back(tip, monkeypatch):
    """Touching the object behind its predecessor, a robot slides ever farther from it round the object (in
    paper-25 with fast travel, for 300 s through the branch's members). Once its distance error grows a whole
    I_d past the smallest it had, it gives the slot back, as attach_timeout_s would 120 s later."""
    spacing = tip._spacing()
    _attaching(tip, monkeypatch, [0.3, 0.1, 0.1 + 0.5 * spacing, 0.1 + 1.1 * spacing])
    for now in (1.0, 1.1, 1.2):
        tip._on_attach(now)
        assert tip.state == "attach"
    tip._on_attach(1.3)
    assert tip.state == "idle" and tip.task is None
    assert tip.board.task("L2").epoch == 1 and "L2" in tip.given_back


def test_in_the_faithful_profile_an_attaching_robot_keeps_sliding(monkeypatch):
    faithful = Simulation(load_scenario("lab-6").with_overrides(params={"profile": "faithful"}), seed=1)
    robot = faithful.behaviours[0]
    robot.percept = Percept(0.0, 0.3, 0.0, {}, (0.0, -1.0), 0.9, (0.0, 0.0))
    spacing = robot._spacing()
    _attaching(robot, monkeypatch, [0.1, 0.1 + 2.0 * spacing])
    robot._on_attach(1.0)
    robot._on_attach(1.1)
    assert robot.state == "attach" and robot.task is not None
