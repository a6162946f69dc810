"""Virtual sensors and the radio relay: the same geometry as the simulator, reach limited to d_C."""
import math

import numpy as np
import pytest

from hub.relay import RadioRelay
from hub.sensors import SensingModel, VirtualSensors
from hub.sources import pose_from_mocap

POSES = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, math.pi / 2], [0.0, 2.5, 0.0], [10.0, 0.0, 0.0]])
IDS = [4, 7, 9, 12]


def exact_sensors(present=(True, True, True, True), range_m=3.0):
    sensors = VirtualSensors(IDS, SensingModel(range_m, 0.0, 0.0), np.random.default_rng(0))
    sensors.update(POSES, np.array(present))
    return sensors


def test_neighbours_within_range_with_range_and_bearing_in_the_observers_frame():
    sensors = exact_sensors()
    assert sensors.neighbours_of(4) == [[7, 1.0, 0.0], [9, 2.5, pytest.approx(math.pi / 2, abs=1e-5)]]
    seen_by_7 = {n[0]: n[1:] for n in sensors.neighbours_of(7)}
    assert seen_by_7[4] == [1.0, pytest.approx(math.pi / 2, abs=1e-5)]   # 7 faces +y: 4 is on its left
    assert 12 not in seen_by_7 and sensors.neighbours_of(12) == []
    assert sensors.receivers_of(4) == [7, 9]


def test_untracked_robots_are_neither_seen_nor_see():
    sensors = exact_sensors(present=(True, False, True, True))
    assert [n[0] for n in sensors.neighbours_of(4)] == [9]
    assert sensors.pose_of(7) is None and sensors.neighbours_of(7) == []


def test_noise_has_the_configured_spread():
    sensors = VirtualSensors(IDS, SensingModel(3.0, 0.05, 0.1), np.random.default_rng(1))
    errors = []
    for _ in range(400):
        sensors.update(POSES, np.ones(4, dtype=bool))
        errors.append(sensors.neighbours_of(4)[0][1] - 1.0)
    assert np.std(errors) == pytest.approx(0.05, rel=0.2)


def test_relay_reaches_only_receivers_and_respects_limits():
    relay = RadioRelay([1, 2, 3], drop=0.0, queue_len=2, max_bytes=100, rng=np.random.default_rng(0))
    assert relay.submit(1, 0.5, {"a": 1}, 7, receivers=[2, 1]) is True
    assert relay.take(2, 10_000) == [[1, 0.5, {"a": 1}]]
    assert relay.take(1, 10_000) == [] and relay.take(3, 10_000) == []      # not itself, not out of range
    assert relay.submit(99, 0.0, {}, 2, receivers=[2]) is False             # unknown sender
    assert relay.submit(1, 0.0, {"big": "x"}, 101, receivers=[2]) is False  # over max_bytes
    for k in range(5):
        relay.submit(1, float(k), {"k": k}, 7, receivers=[2])
    assert [m[2]["k"] for m in relay.take(2, 10_000)] == [3, 4]              # bounded queue keeps the newest
    assert relay.stats.dropped_overflow == 3 and relay.stats.refused == 2


def test_relay_drop_rate():
    relay = RadioRelay([1, 2], drop=0.3, queue_len=10_000, max_bytes=100, rng=np.random.default_rng(2))
    for k in range(2000):
        relay.submit(1, 0.0, {"k": k}, 7, receivers=[2])
    assert len(relay.take(2, 10**9)) / 2000 == pytest.approx(0.7, abs=0.04)


def test_a_frame_carries_messages_only_up_to_its_budget():
    relay = RadioRelay([1, 2], drop=0.0, queue_len=100, max_bytes=8192, rng=np.random.default_rng(0))
    for k in range(10):
        relay.submit(1, 0.0, {"k": k}, 8000, receivers=[2])
    first = relay.take(2, 20_000)
    assert len(first) == 2 and len(relay.take(2, 20_000)) == 2       # the rest waits for later frames


@pytest.mark.parametrize("up, position, quaternion, expected", [
    ("z", (1.0, 2.0, 0.05), (math.cos(0.3), 0.0, 0.0, math.sin(0.3)), (1.0, 2.0, 0.6)),
    # Y-up (Motive's default): the floor is x-z, the world's y is -z, and yaw turns about +y.
    ("y", (1.0, 0.05, -2.0), (math.cos(0.3), 0.0, math.sin(0.3), 0.0), (1.0, 2.0, 0.6)),
])
def test_axis_conventions(up, position, quaternion, expected):
    assert pose_from_mocap(position, quaternion, up) == pytest.approx(expected)
