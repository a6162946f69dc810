"""The second round of fast paths (issue #5) give exactly what the plain paths give: the batched receive loop,
the lazy relay scan, the cached rules, prefix lists and bid views, nearest among members, the lazy neighbour
columns, and the simulator's noise draw and bearing wrap."""
import copy
import math
import random
from types import SimpleNamespace

import numpy as np
import pytest

from onboard.behaviours.transport.entries import entry_problem
from onboard.behaviours.transport.perception import NeighbourVectors, nearest
from onboard.behaviours.transport.tasks import Task, TaskBoard, new_space, task_from
from onboard.geometry import pairwise_range_bearing, wrap
from onboard.hal import Message, Neighbours
from onboard.stigmergy import TupleSpace, lowest_field
from sim_backend.hal import encode_payload
from sim_backend.runner import Simulation, _wrap_noisy


class PlainSpace(TupleSpace):
    """The transport's replica with every new shortcut turned off: relays scanned at every call, prefix
    lists rebuilt, conflict rules looked up afresh."""

    def outgoing(self):
        self._next_due = -1
        return super().outgoing()

    def keys(self, prefix=""):
        self._keys_by_prefix.clear()
        return super().keys(prefix)

    def _resolve(self, key, local, remote):
        self._rule_of.clear()
        return super()._resolve(key, local, remote)


def plain_space(owner):
    rule = lowest_field("bid", "robot")
    return PlainSpace(owner, conflict_rules={"bid/": rule, "owner/": rule}, relay_rounds=1, relay_delay_steps=7,
                      relay_quorum=2, anti_entropy_period=10, check=entry_problem)


def state(space):
    return ({key: space.entry(key) for key in space.keys()}, dict(space._pending), list(space._dirty.items()),
            space.keys("pos/"), space.keys("bid/"), space.rejected)


def message(sender, payload):
    return Message(sender=sender, payload=payload, sent_s=0.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_batched_receive_and_lazy_relays_match_the_plain_replica(seed):
    """Two swarms step by step: one merges its inbox with merge_messages and the shortcuts, the other merges
    message by message with none. They send the same messages and hold the same state throughout."""
    rng = random.Random(seed)
    robots = 7
    fast = [new_space(r) for r in range(robots)]
    slow = [plain_space(r) for r in range(robots)]
    inboxes = {kind: [[] for _ in range(robots)] for kind in ("fast", "slow")}
    for step in range(150):
        for r in range(robots):
            if step < 60 and (step + r) % 3 == 0:
                for spaces in (fast, slow):
                    spaces[r].put(f"pos/{r}", [round(step * 0.01 * r, 4), r, None, None])
            if step in (10, 11, 30) and r % 2 == 0:
                for spaces in (fast, slow):
                    spaces[r].put("bid/S/0", {"robot": r, "bid": float(9 - r)})
                    spaces[r].put(f"owner/L{r}", {"robot": r, "bid": 1.0, "epoch": 0})
        for kind, spaces in (("fast", fast), ("slow", slow)):
            for r in range(robots):
                inbox, inboxes[kind][r] = inboxes[kind][r], []
                if kind == "fast":
                    spaces[r].merge_messages(inbox, "ts")
                else:
                    for m in inbox:
                        if isinstance(m.payload, dict):
                            spaces[r].merge(m.payload.get("ts"), m.sender)
        for r in range(robots):
            sent_fast, sent_slow = fast[r].outgoing(), slow[r].outgoing()
            assert sent_fast == sent_slow and sent_fast.wires == sent_slow.wires
            if not sent_fast and step % 17:
                continue
            copies = {"fast": encode_payload({"ts": sent_fast})[1], "slow": encode_payload({"ts": sent_slow})[1]}
            for receiver in range(robots):
                if receiver != r and rng.random() < 0.8:
                    for kind in ("fast", "slow"):
                        inboxes[kind][receiver].append(message(r, copies[kind]))
            if step % 13 == 0:                     # odd payloads: not a dict, no "ts", a plain list
                for kind in ("fast", "slow"):
                    inboxes[kind][(r + 1) % robots] += [message(r, [1, 2]), message(r, {"other": 1}),
                                                        message(r, {"ts": [["pos/99", [0, 0, None], 1, 99]]}),
                                                        message(r, {"ts": [["pos/98", [0, 0, None, None], 1, 99]]})]
        for a, b in zip(fast, slow):
            assert state(a) == state(b)
    assert state(fast[0])[0] == state(fast[-1])[0]


def uncached_best_bid(board, task):
    value = board.space.get(f"bid/{task.tid}/{task.epoch}")
    if not isinstance(value, dict) or "bid" not in value:
        return None
    return None if board.busy(value.get("robot"), task.tid) else value


def test_bid_views_follow_every_change():
    space = new_space(1)
    board, peer = TaskBoard(space, 4.0), TaskBoard(new_space(2), 4.0)
    rng = random.Random(3)
    for step in range(60):
        tid = rng.choice(["S", "L1", "L2", "R1"])
        task = Task(tid, rng.random(), rng.random(), tid[0], int(tid[1:] or 0), rng.choice([None, 1, 2]),
                    rng.randint(0, 1), cancelled=rng.random() < 0.1)
        action = step % 5
        if action == 0:
            peer.put_task(task)
        elif action == 1:
            peer.bid(task, rng.randint(3, 8), rng.random())
        elif action == 2:
            peer.take(task, rng.randint(3, 8), 0.5)
        elif action == 3:
            peer.join_cage(rng.randint(3, 8), task)
        else:
            board.bid(task, 1, rng.random())
        space.merge(encode_payload({"ts": peer.space.outgoing()})[1]["ts"], 2)
        expected = [(t, f"{t.tid}/{t.epoch}", uncached_best_bid(board, t)) for t in board.tasks() if board.is_open(t)]
        got = board.open_tasks()
        assert [(task_from(f), key, best) for f, key, best in got] == expected
        for robot in (1, 2):     # what a member looks after every step: the same as filtering tasks()
            assert board.tasks_opened_by(robot) == [t for t in board.tasks() if t.pred == robot and not t.cancelled]
        for t in board.tasks():
            for epoch in (t.epoch, t.epoch + 1):
                probe = Task(t.tid, 0.0, 0.0, t.branch, t.index, None, epoch)
                assert board.best_bid(probe) is uncached_best_bid(board, probe)


@pytest.mark.parametrize("yaw", [0.0, 0.7, -2.9])
def test_nearest_among_members_matches_the_full_scan_to_the_last_bit(yaw):
    rng = np.random.default_rng(4)
    for trial in range(30):
        count = int(rng.integers(0, 30))
        ids = np.sort(rng.choice(200, count, replace=False))
        ranges, bearings = rng.uniform(0.1, 3.0, count), rng.uniform(-math.pi, math.pi, count)
        if count > 3 and trial % 3 == 0:
            ranges[1] = ranges[2]                  # ties: the first in sensor order wins
            bearings[1] = bearings[2]
        among = set(rng.choice(200, int(rng.integers(0, 40)), replace=False).tolist())
        among |= set(ids[: count // 3].tolist())
        for given_xy in (False, True):
            table = Neighbours(ids, ranges, bearings)
            if given_xy:
                assert table.xy.shape == (2, count)   # xy made already (as by another robot's use of the pairs)
            fast = NeighbourVectors(table, yaw)
            reference = dict(NeighbourVectors(Neighbours(ids, ranges, bearings), yaw).items())
            assert nearest(fast, among) == nearest(reference, among)
            found = nearest(fast, among)
            if found is not None:
                assert fast[found] == reference[found]
            assert dict(fast.items()) == reference


def test_noisy_bearings_wrap_exactly_as_geometry_wrap():
    rng = np.random.default_rng(5)
    edges = np.array([0.0, -0.0, math.pi, -math.pi, 3.0, -3.0, np.nextafter(3.0, 0), np.nextafter(-3.0, 0),
                      math.pi + 1e-12, -math.pi - 1e-12, 7.0, -7.0, 1e-300])
    angles = np.concatenate([edges, rng.uniform(-math.pi, math.pi, 5000) + rng.normal(0.0, 0.3, 5000)])
    fast = angles.copy().reshape(1, -1)
    _wrap_noisy(fast)
    expected = wrap(angles)
    assert np.array_equal(fast.ravel(), expected) and np.array_equal(np.signbit(fast.ravel()), np.signbit(expected))


def test_one_standard_normal_draw_gives_the_two_normal_draws(make_scenario):
    """The simulator's own sensing step, against the plain path it replaced: two normal draws, range noise
    then bearing noise, and the IR noise after them from the same stream. (This test drew numpy's numbers
    alone, never the simulator's: a swapped or rescaled noise matrix passed it.)"""
    sim = Simulation(make_scenario(robots={"count": 9, "spawn": {"x": [-1, 1], "y": [-1, 1]}},
                                   comm={"range_noise_m": 0.02, "bearing_noise_rad": 0.05},
                                   sensors={"proximity_noise": 0.03}))
    poses, alive = sim.world.robot_poses(), np.ones(9, dtype=bool)
    plain = copy.deepcopy(sim.rng_sensors)
    sim._sense(poses, alive)
    true_ranges, true_bearings = pairwise_range_bearing(poses[:, :2], poses[:, 2])
    ranges = np.maximum(true_ranges + plain.normal(0.0, 0.02, (9, 9)), 0.0)
    bearings = wrap(true_bearings + plain.normal(0.0, 0.05, (9, 9)))
    assert np.array_equal(sim.frame.ranges, ranges) and np.array_equal(sim.frame.bearings, bearings)
    ir = sim.ir.readings(poses[:, :2], poses[:, 2], true_ranges, sim.world.obstacle_groups(), plain, 0.03)
    assert np.array_equal(sim.frame.proximity, ir)      # the stream goes on from the same place


def test_lazy_neighbour_columns_are_the_frame_slices(make_scenario):
    sim = Simulation(make_scenario(robots={"count": 7, "spawn": {"x": [0, 1.2], "y": [0, 1.2]}}, comm={"range_m": 0.8}))
    for _ in range(3):
        sim.step()
    frame = sim.frame
    for i, robot in enumerate(sim.robots):
        table = robot.range_and_bearing.neighbours()
        ids = [j for j in range(7) if j != i and frame.pairs is not None and j in frame.receivers(i).tolist()]
        plain = Neighbours(ids, frame.ranges[i, ids], frame.bearings[i, ids])
        assert len(table) == len(ids) and table.id_list() == ids
        assert np.array_equal(table.ranges_m, plain.ranges_m) and np.array_equal(table.bearings_rad, plain.bearings_rad)
        assert table.ids.dtype == np.int64 and np.array_equal(table.xy, plain.xy)
        assert table == plain and table.nearest_m == plain.nearest_m


def walked_chain(transport, branch):
    """The closure test's chain as it was before the cached slots: members parsed and sorted afresh."""
    members = transport.board.members()
    slots = {v.get("index"): rid for rid, v in members.items() if v.get("branch") == branch}
    previous = next((rid for rid, v in members.items() if v.get("branch") == "S"), None)
    chain = []
    for index in sorted(k for k in slots if isinstance(k, int) and k >= 1):
        rid = slots[index]
        here, there = transport._member_position(rid), transport._member_position(previous)
        if here is not None and there is not None and math.dist(here, there) > 2.0 * transport._spacing():
            break
        chain.append(rid)
        previous = rid
    return chain


@pytest.mark.parametrize("seed", range(4))
def test_the_tip_shortcut_and_cached_slots_give_the_walked_chain(seed):
    """_may_be_tip lets most branch members skip the walk each step; it must never skip the real tip, and the
    cached slots (and the ring slots behind _cage_ring_neighbours) must follow every change of the members:
    gaps, unsettled robots, two robots on one index, malformed indices, the robot's own moves."""
    from sim_backend.scenario import load_scenario
    transport = Simulation(load_scenario("lab-6"), seed=1).behaviours[0]
    space, me, rng = transport.space, transport.robot.id, random.Random(seed)
    transport.percept = SimpleNamespace(position=(0.0, 0.0))
    tips_seen = []
    for step in range(800):
        rid = rng.choice([me] * 3 + list(range(10, 22)))
        roll = rng.random()
        if roll < 0.6:
            branch = rng.choice("LLRRS")
            index = rng.choice([rng.randint(1, 12)] * 8 + [0, "3", None])
            space.put(f"member/{rid}", {"tid": f"{branch}{index}", "branch": branch, "index": index})
        elif roll < 0.9 and rid != me:
            angle = rng.uniform(0.0, 2.0 * math.pi)
            radius = rng.choice([0.2, 0.2, 0.2, 3.0])
            xy = [round(radius * math.cos(angle), 4), round(radius * math.sin(angle), 4)]
            space.put(f"pos/{rid}", xy + [None, None])
        else:
            transport.percept = SimpleNamespace(position=(rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 3)))
        for branch in "LR":
            expected = walked_chain(transport, branch)
            assert transport._chain(branch) == expected, (step, branch)
            is_tip = bool(expected) and expected[-1] == me
            tips_seen.append(is_tip)
            assert (transport._may_be_tip(branch) and transport._chain_tip(branch) == me) == is_tip, (step, branch)
        by_slot = {(v.get("branch"), v.get("index")): r for r, v in transport.board.members().items()}
        tips = {b: max((i for (bb, i) in by_slot if bb == b and type(i) is int), default=None) for b in "LR"}
        assert transport.board.ring_slots() == (by_slot, tips), step
    assert 20 < sum(tips_seen) < len(tips_seen) - 20      # this robot was the tip often, and often not
