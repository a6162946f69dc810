"""The simulator's fast paths give what the plain paths give: same messages, same records, same physics."""
import json
import math
import random

import numpy as np
import pytest

from onboard.behaviours.transport import control as c
from onboard.behaviours.transport import tasks as tasks_module
from onboard.behaviours.transport.control import rotate
from onboard.behaviours.transport.perception import near, perceive
from onboard.behaviours.transport.tasks import Task, TaskBoard, new_space
from onboard.geometry import pairwise_range_bearing, wrap
from onboard.hal import Message, Neighbour, Neighbours, Pose, ProximityReading, WheelOdometry
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


# --- the bulk neighbour interface (HAL) and what the transport makes of it --------------------------------

def test_a_neighbour_table_holds_the_records_the_constructor_makes():
    table = Neighbours([4, 9, 2], [0.5, 2.0, 0.3], [-3.0, 1.25, 0.1], age_s=0.2)
    assert table == [Neighbour(4, 0.5, -3.0, 0.2), Neighbour(9, 2.0, 1.25, 0.2), Neighbour(2, 0.3, 0.1, 0.2)]
    assert len(table) == 3 and table[1].id == 9 and [n.id for n in table[1:]] == [9, 2] and table
    assert table.nearest_m == 0.3 and Neighbours([], [], []).nearest_m == math.inf and not Neighbours([], [], [])
    assert table.xy.tolist() == [[n.x for n in table], [n.y for n in table]]
    assert all(type(n.id) is int and type(n.range_m) is float for n in table)
    records = [Neighbour(1, 1.0, 0.5, 0.1)]
    assert Neighbours.of(records) == records and Neighbours.of(records)[0] is records[0]
    assert Neighbours.of(table) is table


def test_the_sim_range_and_bearing_device_hands_out_the_frame_columns(make_scenario):
    sim = Simulation(make_scenario(robots={"count": 6, "spawn": {"x": [-1, 1], "y": [-1, 1]}}, comm={"range_m": 1.2}))
    sim.step()
    frame = sim.frame
    for i, robot in enumerate(sim.robots):
        seen = robot.range_and_bearing.neighbours()
        ids = [j for j in range(6) if j != i and sim.frame.ranges[i, j] >= 0 and
               np.hypot(*(sim.recording.robot_pose[-1][j, :2] - sim.recording.robot_pose[-1][i, :2])) <= 1.2]
        assert [n.id for n in seen] == ids == frame.receivers(i).tolist()
        expected = Neighbour.many(ids, frame.ranges[i, ids], frame.bearings[i, ids])
        assert seen.nearest_m == min((n.range_m for n in expected), default=math.inf)
        assert list(seen) == expected and [(n.x, n.y) for n in seen] == [(n.x, n.y) for n in expected]


def reference_perception(yaw, neighbours):
    return {n.id: rotate((n.x, n.y), yaw) for n in neighbours}


@pytest.mark.parametrize("yaw", [0.0, 0.7, -2.9])
def test_neighbour_vectors_are_the_rotated_records_to_the_last_bit(yaw):
    rng = np.random.default_rng(3)
    table = Neighbours(np.arange(40) * 3, rng.uniform(0.1, 3.0, 40), rng.uniform(-math.pi, math.pi, 40))
    expected = reference_perception(yaw, list(table))
    reading = ProximityReading((0.0,) * 8)
    fresh = lambda: perceive(1.0, 2.0, yaw, Neighbours(table.ids, table.ranges_m, table.bearings_rad),  # noqa: E731
                             reading).neighbours
    assert dict(fresh().items()) == expected and list(fresh().values()) == list(expected.values())
    vectors = fresh()
    assert vectors.get(3) == expected[3] and vectors.get(1) is None and 6 in vectors and len(vectors) == 40
    assert vectors == expected and list(vectors) == list(expected)
    for ids in ([5, 2, 9], [2, 5, 9]):          # found by bisection when ascending, else by a dict
        small = perceive(0.0, 0.0, yaw, Neighbours(ids, [1.0, 2.0, 3.0], [0.1, 0.2, 0.3]), reading).neighbours
        few = Neighbours(ids, [1.0, 2.0, 3.0], [0.1, 0.2, 0.3])
        assert small.get(9) == reference_perception(yaw, list(few))[9] == small[9]
        assert small.get(None) is None and small.get(4, "no") == "no" and 4 not in small and 5 in small
        with pytest.raises(KeyError):
            small[4]
    for radius in (0.05, 0.5, 1.5, 10.0):
        close = [v for v in expected.values() if math.hypot(*v) < radius]
        for neighbours in (fresh(), expected):          # lazily rotated, fully rotated and a plain dict
            found = near(neighbours, radius)
            assert [v for v in found if math.hypot(*v) < radius] == close
            assert all(math.hypot(*v) <= radius * (1 + 1e-6) for v in found)
        excluded = set(list(expected)[::2])
        kept = [v for j, v in expected.items() if j not in excluded and math.hypot(*v) < radius]
        assert [v for v in near(fresh(), radius, excluded) if math.hypot(*v) < radius] == kept
        assert c.u_avoid(near(fresh(), radius), radius, 2.0) == reference_u_avoid(expected.values(), radius, 2.0)


def reference_u_avoid(neighbours, safety_distance, gain):
    total = c.ZERO
    for r in neighbours:
        d = c.norm(r)
        if 1e-6 < d < safety_distance:
            total = c.add(total, c.scale(c.unit(r), -gain * (safety_distance - d) / safety_distance))
    return total


def test_u_avoid_skips_far_neighbours_without_changing_the_sum():
    rng = np.random.default_rng(5)
    vectors = [tuple(v) for v in rng.uniform(-1.0, 1.0, (200, 2)).tolist()] + [(0.0, 0.0), (1e-7, 0.0), (0.35, 0.0)]
    assert c.u_avoid(vectors, 0.35, 2.0) == reference_u_avoid(vectors, 0.35, 2.0) != c.ZERO


def test_perception_of_a_table_matches_perception_of_records():
    table = Neighbours([1, 2, 3], [0.2, 0.25, 1.0], [0.05, 1.6, -2.0])
    reading = ProximityReading((0.9, 0.0, 0.6, 0.0, 0.3, 0.0, 0.0, 0.04))
    fast, slow = perceive(0.5, -0.5, 0.3, table, reading), perceive(0.5, -0.5, 0.3, list(table), reading)
    assert (fast.object_vector, fast.object_peak, fast.obstacle_vector) == \
        (slow.object_vector, slow.object_peak, slow.obstacle_vector)
    assert fast.object_peak == 0.3 and dict(fast.neighbours) == reference_perception(0.3, list(table))


# --- the transport's views of the tuple space --------------------------------------------------------------

def uncached_tasks(space):
    found = []
    for key, value in space.items("task/"):
        fields = tasks_module._parse_task(key[len("task/"):], value)
        if fields is not None:
            found.append(Task(**fields))
    return found


def uncached_busy(space, robot, except_tid):
    if f"member/{robot}" in space:
        return True
    tasks = {t.tid: t for t in uncached_tasks(space)}
    for key, value in space.items("owner/"):
        if key != f"owner/{except_tid}" and isinstance(value, dict) and value.get("robot") == robot:
            task = tasks.get(key[len("owner/"):])
            if task is not None and not task.cancelled and task.epoch == value.get("epoch"):
                return True
    return False


def test_cached_task_views_follow_every_change():
    space = new_space(1)
    board = TaskBoard(space, 4.0)
    peer = TaskBoard(new_space(2), 4.0)
    for step in range(30):
        if step % 3 == 0:
            board.put_task(Task(f"L{step}", step * 0.1, 1.0, "L", step, 1, 0))
        if step % 4 == 1:
            peer.put_task(Task(f"R{step}", 1.0, step * 0.1, "R", step, 2, step % 2, cancelled=step % 8 == 1))
            peer.take(Task(f"R{step}", 0, 0, "R", step, 2, step % 2), 7 + step % 3, 0.5)
        if step % 5 == 2:
            space.put(f"task/bad{step}", "junk")
            peer.join_cage(step, Task("S", 0, 0, "S", 0, None, 0))
        space.merge(encode_payload({"ts": peer.space.outgoing()})[1]["ts"], 2)
        assert board.tasks() == uncached_tasks(space)
        assert board.task("L0") == uncached_tasks(space)[0] and board.task("nope") is None
        for robot in range(6, 12):
            for except_tid in ("", "R5", "R9"):
                assert board.busy(robot, except_tid) == uncached_busy(space, robot, except_tid)
        assert board.members() == {int(k[len("member/"):]): v for k, v in space.items("member/")}
    listed = board.tasks()
    listed[0].x = 99.0                       # a copy: the next call is unaffected
    assert board.tasks()[0].x != 99.0 and board.task(listed[0].tid).x != 99.0


def test_liveness_follows_changed_heartbeats_only():
    space = new_space(1)
    board = TaskBoard(space, 4.0)
    board.refresh_liveness(0.0)
    space.put("pos/5", [0.0, 0.0, None])
    space.put("pos/x", [0.0, 0.0, None])     # not a robot id: ignored
    board.refresh_liveness(1.0)
    assert board.alive(5, 5.0) and not board.alive(5, 5.1) and board.heard_of(5) and not board.heard_of(6)
    board.refresh_liveness(3.0)              # nothing changed: still heard at 1.0
    assert not board.alive(5, 5.1)
    space.put("pos/5", [0.5, 0.0, None])
    board.refresh_liveness(4.0)
    assert board.alive(5, 8.0)


def test_a_heartbeat_is_written_when_it_says_something_new():
    space = new_space(3)
    board = TaskBoard(space, 4.0)
    writes = []
    for step, (x, normal) in enumerate([(0.0, None), (0.005, None), (0.009, None), (0.011, None), (0.011, 0.5),
                                        (0.011, 0.55), (0.011, 0.7), (0.011, None)] + [(0.011, None)] * 12):
        board.refresh_liveness(step * 0.1)
        before = space.entry("pos/3")
        board.heartbeat(3, x, 0.0, normal)
        writes.append(space.entry("pos/3") is not before)
    assert writes[:8] == [True, False, False, True, True, False, True, True]
    assert writes[8:].count(True) == 1 and writes[17]             # still: once a second (last write at step 7)
    writes = []
    for step, surface in enumerate([None, (0.2, 0.0), (0.205, 0.0), (0.215, 0.0), None], start=20):
        board.refresh_liveness(step * 0.1)
        before = space.entry("pos/3")
        board.heartbeat(3, 0.011, 0.0, None, surface)
        writes.append(space.entry("pos/3") is not before)
    assert writes == [False, True, False, True, True]             # the surface point seen, moved 1 cm, lost
    assert board.surface_point(3) is None and board.position(3) == (0.011, 0.0)


def test_travellers_and_caged_members_write_fewer_heartbeats_and_a_new_state_writes_at_once():
    """Travellers: once a second; caged: on 2 cm, else every 10 s, normals aside; other states: on 1 cm or a
    change of contact, and once a second."""
    space = new_space(3)
    board = TaskBoard(space, 4.0)
    writes = []
    for step in range(25):                       # 2 cm a step, as a traveller at 0.2 m/s
        board.refresh_liveness(step * 0.1)
        before = space.entry("pos/3")
        board.heartbeat(3, 0.02 * step, 0.0, None, state="travel")
        writes.append(space.entry("pos/3") is not before)
    assert [step for step, wrote in enumerate(writes) if wrote] == [0, 10, 20]
    board.refresh_liveness(2.5)
    board.heartbeat(3, 0.5, 0.0, None, state="attach")      # now a member-to-be: others steer by it
    assert board.position(3) == (0.5, 0.0)
    board.refresh_liveness(2.6)
    board.heartbeat(3, 0.52, 0.0, None, state="attach")     # and every centimetre counts again
    assert board.position(3) == (0.52, 0.0)
    board.refresh_liveness(2.7)
    board.heartbeat(3, 0.54, 0.0, 0.3, state="travel")      # a contact appearing still counts for a traveller
    board.refresh_liveness(2.8)
    board.heartbeat(3, 0.56, 0.0, 0.3, state="travel")
    assert board.position(3) == (0.54, 0.0) and board.contact_normal(3) == 0.3
    for t, x in [(2.9, 0.56), (3.0, 0.575), (3.1, 0.585)]:  # caged: 2 cm from the last write counts
        board.refresh_liveness(t)
        board.heartbeat(3, x, 0.0, 0.3, state="caged")
    assert board.position(3) == (0.585, 0.0)
    board.refresh_liveness(3.2)
    board.heartbeat(3, 0.60, 0.0, 0.3, state="caged")      # 1.5 cm: not yet
    assert board.position(3) == (0.585, 0.0)
    writes = []
    for step in range(33, 136):                             # a still caged member: every 10 s, not every 1 s,
        board.refresh_liveness(step * 0.1)
        before = space.entry("pos/3")
        board.heartbeat(3, 0.60, 0.0, (0.3, 0.6, None)[step % 3], state="caged")   # whatever its normal does
        writes.append(space.entry("pos/3") is not before)
    assert [33 + i for i, wrote in enumerate(writes) if wrote] == [131]    # 10 s after the write at 3.1 s
    board.refresh_liveness(13.6)
    board.heartbeat(3, 0.60, 0.0, 0.3, state="settle")     # closure: a new state writes at once,
    board.refresh_liveness(14.7)
    before = space.entry("pos/3")
    board.heartbeat(3, 0.60, 0.0, 0.3, state="settle")     # and from then on once a second again
    assert space.entry("pos/3") is not before


# --- traffic options of the tuple space --------------------------------------------------------------------

def test_plain_tuple_space_defaults_still_relay_at_once_and_gossip_every_message():
    space = TupleSpace(owner=2)
    assert (space.relay_rounds, space.relay_delay_steps, space.relay_quorum, space.anti_entropy_period) == (3, 0, 0, 1)


def run_cluster(robots, steps, writes, **options):
    """Everyone hears everyone; a robot skips empty messages. Returns the replicas and the messages sent."""
    spaces = [TupleSpace(owner=r, conflict_rules=RULES, **options) for r in range(robots)]
    sent, inbox = 0, []
    for step in range(steps):
        for robot, key, value in writes.get(step, []):
            spaces[robot].put(key, value)
        for sender, message in inbox:
            for receiver, space in enumerate(spaces):
                if receiver != sender:
                    space.merge(message, sender)
        inbox = []
        for robot, space in enumerate(spaces):
            message = space.outgoing()
            if message:
                sent += 1
                inbox.append((robot, encode_payload({"ts": message})[1]["ts"]))
    return spaces, sent


def test_counter_based_relays_and_rare_anti_entropy_cut_traffic_not_convergence():
    writes = {0: [(r, "path", [r]) for r in range(40)], 5: [(3, "bid/0", {"bid": 2.0, "robot": 3})],
              9: [(r, f"pos/{r}", [r, 0.0]) for r in range(0, 40, 4)], 12: [(7, "bid/0", {"bid": 1.0, "robot": 7})]}
    plain, plain_sent = run_cluster(40, 60, writes)
    tuned, tuned_sent = run_cluster(40, 60, writes, relay_rounds=1, relay_delay_steps=7, relay_quorum=2,
                                    anti_entropy_period=10)
    for space in plain + tuned:
        assert snapshot(space) == snapshot(plain[0])
    assert plain_sent == 40 * 60 and tuned_sent < plain_sent / 5


@pytest.mark.parametrize("seed", [0, 1])
def test_tuned_replicas_converge_on_a_lossy_line(seed):
    """Where each robot hears only its two neighbours, nobody suppresses the relays they depend on."""
    rng = random.Random(seed)
    spaces = [TupleSpace(owner=r, max_entries_per_message=4, conflict_rules=RULES, relay_rounds=1,
                         relay_delay_steps=7, relay_quorum=2, anti_entropy_period=10) for r in range(10)]
    in_flight = []
    for step in range(400):
        if step < 40:
            for robot in (0, 9):
                if step % 5 == 0:
                    spaces[robot].put(f"pos/{robot}", [step])
            if step == 5:
                for robot in range(10):
                    spaces[robot].put("bid/0", {"bid": float(10 - robot), "robot": robot})
        for robot, space in enumerate(spaces):
            message = space.outgoing()
            if not message:
                continue
            copy = encode_payload({"ts": message})[1]["ts"] if step % 2 else plain(message)
            for neighbour in (robot - 1, robot + 1):
                if 0 <= neighbour < 10 and rng.random() >= 0.3:
                    in_flight.append((step + rng.randint(1, 3), neighbour, robot, copy))
        due = [item for item in in_flight if item[0] <= step]
        in_flight = [item for item in in_flight if item[0] > step]
        rng.shuffle(due)
        for _, receiver, sender, message in due:
            spaces[receiver].merge(message, sender)
    for space in spaces:
        assert snapshot(space) == snapshot(spaces[0])
    assert spaces[0].get("pos/9") == [35] and spaces[9].get("bid/0") == {"bid": 1.0, "robot": 9}


def test_changed_keys_reports_each_family_change_once():
    space = TupleSpace(owner=1)
    space.put("pos/1", [0])
    space.put("task/S", {})
    assert space.changed_keys("pos") == ["pos/1"] and space.changed_keys("pos") == []
    space.put("pos/2", [0])
    space.put("pos/1", [1])
    space.put("pos/2", [1])
    space.merge([["pos/1", [0], 1, 9]])                     # stale: no change
    assert space.changed_keys("pos") == ["pos/1", "pos/2"] and space.changed_keys("task") == ["task/S"]


# --- small records and physics -----------------------------------------------------------------------------

def test_the_sim_devices_fast_records_equal_the_constructors(make_scenario):
    sim = Simulation(make_scenario(robots={"count": 2, "spawn": {"x": [-1, 1], "y": [-1, 1]}}))
    sim.step()
    robot = sim.robots[1]
    pose, odometry, reading = robot.positioning.pose(), robot.odometry.read(), robot.proximity.read()
    # What the constructors make of robot 1's rows of the frame: the same class, every field in the instance
    # (not a class default) and the same values. Built from the record's own fields, as this test was, they held
    # for any values: robot 0's pose, or x and y swapped, passed.
    x, y, yaw, stamp = sim.frame.pose_rows[1]
    assert sim.frame.pose_rows[0][:2] != (x, y)
    expected = (Pose(x, y, yaw, stamp, sim.frame.time_s - stamp), WheelOdometry(*sim.frame.odometry_rows[1]),
                ProximityReading(sim.frame.proximity_rows[1]))
    for fast, made in zip((pose, odometry, reading), expected):
        assert fast == made and vars(fast) == vars(made), (fast, made)
    assert hash(pose)
    message = Message(1, {"ts": []}, 0.5)
    sim.radio.send(0, 1, {"ts": []}, 0.5, np.array([0]))
    sim.radio.deliver(5, sim.frame.inboxes, np.array([True, True]))
    assert sim.robots[0].radio.receive() == [message]


def test_commands_for_many_robots_at_once_skip_dead_ones(make_scenario):
    world = Simulation(make_scenario(robots={"count": 3, "spawn": {"x": [-2, 2], "y": [-2, 2]}})).world
    world.kill(1)
    world.command_many([(0, 0.1, 0.2), (1, 0.3, 0.3), (2, -0.1, 0.0)])
    assert world._commands.tolist() == [[0.1, 0.2], [0.0, 0.0], [-0.1, 0.0]]


def test_a_delayed_relay_without_quorum_is_never_suppressed():
    writer, relay = TupleSpace(owner=1), TupleSpace(owner=2, relay_rounds=1, relay_delay_steps=3,
                                                         anti_entropy_period=1000)
    writer.put("k", 1)
    message = encode_payload({"ts": writer.outgoing()})[1]["ts"]
    relay.merge(message, sender=1)
    relay.merge(message, sender=5)                # a copy from another robot: no quorum, so still relayed
    sent = [[entry[0] for entry in relay.outgoing()] for _ in range(5)]
    assert sent.count(["k"]) == 1
