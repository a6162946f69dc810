"""The simulator's fast paths give what the plain paths give: same messages, same records, same physics."""
import json
import math
import random

import numpy as np
import pytest

from onboard.geometry import pairwise_range_bearing, wrap
from onboard.hal import Neighbour
from onboard.stigmergy import Gossip, TupleSpace, lowest_field, lowest_writer
from sim_backend.hal import SensorFrame, encode_payload, make_robot
from sim_backend.runner import Simulation

RULES = {"bid/": lowest_field("bid", "robot"), "task/": lowest_writer}


def snapshot(space):
    return {key: space.entry(key) for key in space.keys()}


def plain(message):
    return json.loads(json.dumps(message, separators=(",", ":")))


# --- radio and tuple space ---------------------------------------------------------------------------------

def test_the_sim_radio_sizes_and_copies_a_gossip_exactly_as_json_would():
    space = TupleSpace(owner=3)
    space.put("pos/3", [1.5, -2.25, None])
    space.put("task/S", {"x": 1.0, "y": 2, "cancelled": False, "pred": None})
    payload = {"ts": space.outgoing(), "extra": (1, 2)}
    encoded, copy = encode_payload(payload)
    assert encoded == json.dumps(payload, separators=(",", ":"))
    assert copy == plain(payload) and type(copy["ts"]) is Gossip
    assert copy["ts"][0] is not payload["ts"][0] and copy["ts"][0][1] is not payload["ts"][0][1]


def test_a_radio_copy_is_isolated_from_the_sender(make_scenario):
    frame = SensorFrame(inboxes=[[]])
    robot = make_robot(frame, 0, Simulation(make_scenario(robots={"count": 1})).world.spec)
    values = {"list": [1, 2]}
    robot.radio.broadcast({"v": values})
    values["list"].append(3)
    assert robot.radio.outbox == [{"v": {"list": [1, 2]}}]
    with pytest.raises(ValueError):
        robot.radio.broadcast({"ts": Gossip([["k", "x" * 9000, 1, 0]], [json.dumps(["k", "x" * 9000, 1, 0])])})


def writes_at(step, robots):
    writes = [(r, f"pos/{r}", [step * 0.5, r, None if step % 3 else 0.25]) for r in range(robots) if step % 2 == r % 2]
    if step in (4, 5):
        writes += [(r, "bid/0", {"bid": float(10 - r % 4), "robot": r}) for r in range(robots)]
        writes += [(r, "task/1", {"x": 1.0, "robot": r}) for r in range(0, robots, 3)]
    if step == 9:
        writes += [(2, "shared", 1), (5, "shared", 1.0)]      # equal as numbers, different as JSON
    return writes


@pytest.mark.parametrize("seed", [0, 1])
def test_merging_gossip_copies_matches_merging_plain_json(seed):
    """Two swarms, one fed the sim radio's Gossip copies and one plain JSON, stay identical step by step."""
    rng = random.Random(seed)
    robots = 8
    swarms = {kind: [TupleSpace(owner=r, max_entries_per_message=5, conflict_rules=RULES) for r in range(robots)]
              for kind in ("gossip", "plain")}
    in_flight = []
    for step in range(120):
        for robot, key, value in writes_at(step, robots) if step < 30 else []:
            for spaces in swarms.values():
                spaces[robot].put(key, value)
        for robot in range(robots):
            sent = {kind: spaces[robot].outgoing() for kind, spaces in swarms.items()}
            assert sent["gossip"] == sent["plain"]
            copy = encode_payload({"ts": sent["gossip"]})[1]["ts"]
            for receiver in range(robots):
                if receiver != robot and rng.random() < 0.7:
                    in_flight.append((step + rng.randint(1, 3), receiver, robot, copy, plain(sent["plain"])))
        due = [item for item in in_flight if item[0] <= step]
        in_flight = [item for item in in_flight if item[0] > step]
        rng.shuffle(due)
        for _, receiver, sender, gossip, message in due:
            changed = swarms["gossip"][receiver].merge(gossip, sender)
            assert changed == swarms["plain"][receiver].merge(message, sender)
    for fast, slow in zip(swarms["gossip"], swarms["plain"]):
        assert snapshot(fast) == snapshot(slow)
    assert snapshot(swarms["gossip"][0]) == snapshot(swarms["gossip"][-1])
    assert snapshot(swarms["gossip"][0])["shared"].value == 1.0


def test_a_replica_forgets_old_versions_without_changing_what_it_holds():
    source, replica = TupleSpace(owner=1), TupleSpace(owner=2)
    messages = []
    for step in range(6000):                  # more versions than the seen-set keeps
        source.put("pos/1", [step])
        message = encode_payload({"ts": source.outgoing()})[1]["ts"]
        messages.append(message)
        replica.merge(message)
    assert len(replica._seen) <= 4 * len(replica) + 4097
    for message in messages[:50]:             # long-forgotten versions: stale, still ignored
        assert replica.merge(message) == []
    assert replica.entry("pos/1") == source.entry("pos/1")


def test_revision_moves_only_when_the_family_changes():
    space, peer = TupleSpace(owner=1), TupleSpace(owner=2)
    space.put("task/L1", {"x": 1})
    before = (space.revision("task"), space.revision("pos"), space.revision())
    space.put("pos/1", [0.0, 0.0])
    assert (space.revision("task"), space.revision("pos")) == (before[0], before[1] + 1)
    peer.put("task/L2", {"x": 2})
    space.merge(encode_payload({"ts": peer.outgoing()})[1]["ts"])
    assert space.revision("task") == before[0] + 1 and space.revision() == before[2] + 2
    space.merge(encode_payload({"ts": peer.outgoing()})[1]["ts"])       # nothing new: no change
    assert space.revision() == before[2] + 2 and space.revision("nothing") == 0


# --- records and geometry ----------------------------------------------------------------------------------

def test_neighbour_many_makes_the_records_the_constructor_makes():
    ids, ranges, bearings = np.array([4, 9]), np.array([0.5, 2.0]), np.array([-3.0, 1.25])
    fast = Neighbour.many(ids, ranges, bearings, age_s=0.1)
    assert fast == [Neighbour(4, 0.5, -3.0, 0.1), Neighbour(9, 2.0, 1.25, 0.1)]
    assert all(type(n.id) is int and type(n.range_m) is float for n in fast)
    for n in fast:
        assert (n.x, n.y) == pytest.approx((n.range_m * math.cos(n.bearing_rad), n.range_m * math.sin(n.bearing_rad)))


def test_wrap_and_pairwise_geometry_match_the_textbook_formulas():
    angles = np.array([math.pi, -math.pi, 3 * math.pi, -3 * math.pi, 0.0, 7.0, -7.0, 1e-17 - math.pi])
    expected = [math.pi, math.pi, math.pi, math.pi, 0.0, 7.0 - 2 * math.pi, 2 * math.pi - 7.0, math.pi]
    assert wrap(angles) == pytest.approx(expected, abs=1e-12)
    assert np.all((wrap(angles) > -math.pi) & (wrap(angles) <= math.pi))
    xy, yaw = np.array([[0.0, 0.0], [1.0, 1.0], [-2.0, 0.5]]), np.array([0.3, -2.0, 3.0])
    ranges, bearings = pairwise_range_bearing(xy, yaw)
    for i in range(3):
        for j in range(3):
            dx, dy = xy[j] - xy[i]
            assert ranges[i, j] == pytest.approx(math.hypot(dx, dy))
            if i != j:
                assert bearings[i, j] == pytest.approx(math.remainder(math.atan2(dy, dx) - yaw[i], 2 * math.pi))


# --- physics -----------------------------------------------------------------------------------------------

def test_the_batched_wheels_drive_each_robot_by_its_own_command(make_scenario):
    scenario = make_scenario(robots={"count": 3, "spawn": {"x": [-2, 2], "y": [-2, 2]}})
    world = Simulation(scenario).world
    commands = [(0.1, 0.1), (-0.05, 0.05), (0.0, 0.0)]
    for i, (left, right) in enumerate(commands):
        world.command(i, left, right)
    start = world.robot_poses()
    world.step(100)
    moved = world.robot_poses() - start
    assert math.hypot(*moved[0, :2]) == pytest.approx(0.1, abs=0.005) and abs(moved[0, 2]) < 1e-3
    assert math.hypot(*moved[1, :2]) < 1e-3 and moved[1, 2] == pytest.approx(0.1 / 0.1054, rel=0.05)
    assert np.abs(moved[2]).max() < 1e-6
    assert (world.robots[0].left_odo, world.robots[1].right_odo) == pytest.approx((0.1, 0.05))
    assert np.array_equal(world.robot_poses()[:, :2], [tuple(r.body.position) for r in world.robots])
