"""The simulator's implementation of the HAL: each device reads the per-step :class:`SensorFrame` that the
runner computes for all robots at once (vectorised), and writes commands the runner forwards to physics.

Nothing here gives a behaviour the world, the object or another robot's state.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Optional, Tuple

import numpy as np

from onboard import hal
from onboard.hal import Message, Neighbour, Pose, ProximityReading, RobotSpec, WheelOdometry, clamp_wheel_speeds
from onboard.stigmergy import Gossip


@dataclass
class SensorFrame:
    """What every robot senses at one control step; filled by the runner.

    Per-robot data is kept as Python lists built once per step for all robots (``set_*``), so a device
    read is a list lookup and a record, not several small numpy operations per robot.
    """

    time_s: float = 0.0
    proximity: Optional[np.ndarray] = None          # (N, 8) normalised readings
    neighbour_ids: List[np.ndarray] = field(default_factory=list)   # per robot: ids in range
    ranges: Optional[np.ndarray] = None              # (N, N) noisy ranges
    bearings: Optional[np.ndarray] = None            # (N, N) noisy bearings
    # Per robot: the latest motion-capture pose as (x, y, yaw, stamp_s), or None before the first one.
    # Plain tuples: the Pose record is built when a behaviour asks, with its age at that moment.
    pose_rows: List[Optional[Tuple[float, float, float, float]]] = field(default_factory=list)
    inboxes: List[List[Message]] = field(default_factory=list)
    odometry: Optional[np.ndarray] = None            # (N, 2) cumulative wheel distances
    proximity_rows: List[Tuple[float, ...]] = field(default_factory=list)
    odometry_rows: List[Tuple[float, float]] = field(default_factory=list)
    # Every robot's neighbours, robot after robot: robot i's are items bounds[i]:bounds[i + 1] of each column.
    neighbour_bounds: List[int] = field(default_factory=list)
    neighbour_columns: Tuple[list, ...] = ()         # ids, ranges, bearings, x, y

    def set_neighbours(self, mask: np.ndarray, ranges: np.ndarray, bearings: np.ndarray) -> None:
        """``mask[i, j]``: j is i's neighbour; ``ranges``/``bearings`` (N, N) as i measures j."""
        self.ranges, self.bearings = ranges, bearings
        rows, cols = np.nonzero(mask)                # row-major: each robot's neighbours in id order
        bounds = np.searchsorted(rows, np.arange(len(mask) + 1))
        self.neighbour_ids = [cols[start:end] for start, end in zip(bounds[:-1], bounds[1:])]
        self.neighbour_bounds = bounds.tolist()
        pair_ranges, pair_bearings = ranges[mask], bearings[mask]     # also row-major, cheaper than [rows, cols]
        self.neighbour_columns = (cols.tolist(), pair_ranges.tolist(), pair_bearings.tolist(),
                                  (pair_ranges * np.cos(pair_bearings)).tolist(),
                                  (pair_ranges * np.sin(pair_bearings)).tolist())

    def set_proximity(self, readings: np.ndarray) -> None:
        self.proximity = readings
        self.proximity_rows = [tuple(row) for row in readings.tolist()]

    def set_odometry(self, distances: np.ndarray) -> None:
        self.odometry = distances
        self.odometry_rows = [tuple(row) for row in distances.tolist()]


class SimProximity(hal.ProximitySensor):
    def __init__(self, frame: SensorFrame, index: int):
        self.frame, self.index = frame, index

    def read(self) -> ProximityReading:
        return ProximityReading(values=self.frame.proximity_rows[self.index])


class SimRangeAndBearing(hal.RangeAndBearingSensor):
    def __init__(self, frame: SensorFrame, index: int):
        self.frame, self.index = frame, index

    def neighbours(self) -> List[Neighbour]:
        start, end = self.frame.neighbour_bounds[self.index:self.index + 2]
        ids, ranges, bearings, xs, ys = (column[start:end] for column in self.frame.neighbour_columns)
        return Neighbour.many(ids, ranges, bearings, xs=xs, ys=ys)


class SimRadio(hal.Radio):
    def __init__(self, frame: SensorFrame, index: int):
        self.frame, self.index = frame, index
        self.outbox: List[Dict[str, Any]] = []
        self.encode_seconds = 0.0        # time spent here, so the runner can count it as radio time

    def broadcast(self, payload: Mapping[str, Any]) -> None:
        started = time.perf_counter()
        try:
            self._queue(payload)
        finally:
            self.encode_seconds += time.perf_counter() - started

    def _queue(self, payload: Mapping[str, Any]) -> None:
        # Encode as the real radio would: refuses what could not cross the wire, and isolates the copy
        # the receivers get from later changes by the sender.
        if not isinstance(payload, Mapping):
            raise TypeError(f"robot {self.index}: radio payload must be a mapping, got {type(payload).__name__}")
        encoded, copy = encode_payload(payload)
        if len(encoded) > self.MAX_PAYLOAD_BYTES:
            raise ValueError(f"robot {self.index}: radio payload of {len(encoded)} bytes exceeds "
                             f"{self.MAX_PAYLOAD_BYTES}")
        self.outbox.append(copy)

    def receive(self) -> List[Message]:
        inbox = self.frame.inboxes[self.index]
        self.frame.inboxes[self.index] = []
        return inbox


_compact_json = json.JSONEncoder(separators=(",", ":")).encode   # built once, not per call as json.dumps does


def encode_payload(payload: Mapping[str, Any]) -> Tuple[str, Dict[str, Any]]:
    """The payload's compact JSON and the decoded copy receivers get (one copy, shared by all of them).

    A tuple-space message (``Gossip``) already knows its JSON text, so it is neither encoded again nor
    re-checked; it is decoded from that text, and stays a Gossip so the receivers' replicas merge it fast.
    """
    if not any(type(value) is Gossip for value in payload.values()) or \
            not all(type(key) is str for key in payload):
        encoded = _compact_json(payload)
        return encoded, json.loads(encoded)
    parts, copy = [], {}
    for key, value in payload.items():
        if type(value) is Gossip:
            text = value.json_text()
            copy[key] = value.decoded_copy(text)
        else:
            text = _compact_json(value)
            copy[key] = json.loads(text)
        parts.append(f"{_compact_json(key)}:{text}")
    return "{" + ",".join(parts) + "}", copy


class SimWheels(hal.DifferentialSteering):
    def __init__(self, spec: RobotSpec):
        self.spec = spec
        self.left = self.right = 0.0

    def set_speeds(self, left_m_s: float, right_m_s: float) -> None:
        if not (math.isfinite(left_m_s) and math.isfinite(right_m_s)):   # math: ~20x cheaper than numpy here
            raise ValueError(f"wheel speeds must be finite (got {left_m_s}, {right_m_s})")
        self.left, self.right = clamp_wheel_speeds(float(left_m_s), float(right_m_s), self.spec.max_wheel_speed_m_s)


class SimOdometry(hal.Odometry):
    def __init__(self, frame: SensorFrame, index: int):
        self.frame, self.index = frame, index

    def read(self) -> WheelOdometry:
        left, right = self.frame.odometry_rows[self.index]
        return WheelOdometry(left, right)


class SimPositioning(hal.Positioning):
    def __init__(self, frame: SensorFrame, index: int):
        self.frame, self.index = frame, index

    def pose(self) -> Optional[Pose]:
        row = self.frame.pose_rows[self.index]
        if row is None:
            return None
        x, y, yaw, stamp = row
        return Pose(x, y, yaw, stamp, self.frame.time_s - stamp)


class SimClock(hal.Clock):
    def __init__(self, frame: SensorFrame):
        self.frame = frame

    def now(self) -> float:
        return self.frame.time_s


def make_robot(frame: SensorFrame, index: int, spec: RobotSpec) -> hal.Robot:
    return hal.Robot(
        id=index,
        proximity=SimProximity(frame, index),
        range_and_bearing=SimRangeAndBearing(frame, index),
        radio=SimRadio(frame, index),
        wheels=SimWheels(spec),
        odometry=SimOdometry(frame, index),
        positioning=SimPositioning(frame, index),
        clock=SimClock(frame),
        spec=spec,
    )
