"""The simulator's implementation of the HAL: each device reads the per-step :class:`SensorFrame` that the
runner computes for all robots at once (vectorised), and writes commands the runner forwards to physics.

Nothing here gives a behaviour the world, the object or another robot's state: the frame holds every robot's
readings, so each device keeps it (and its own index) in an underscored attribute.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Optional, Tuple

import numpy as np

from onboard import hal
from onboard.hal import (
    PROXIMITY_ANGLES_RAD,
    Message,
    Neighbours,
    Pose,
    ProximityReading,
    RobotSpec,
    WheelOdometry,
    commanded_wheel_speeds,
)
from onboard.hal.payload import plain_payload
from onboard.stigmergy import Gossip


class PairColumns:
    """One step's range-and-bearing pairs, robot after robot: neighbour ids, ranges and bearings (M,), and
    their x, y (2, M) in the observer's frame, computed for all robots at once the first time a robot needs
    them (a behaviour may never need them)."""

    __slots__ = ("ids", "ranges", "bearings", "bounds", "_xy", "_nearest")

    def __init__(self, ids: np.ndarray, ranges: np.ndarray, bearings: np.ndarray, bounds: np.ndarray) -> None:
        # Read-only: every robot's device hands out views of these, and the radio routes by ``ids``; a
        # behaviour writing into its neighbours' columns would otherwise change what others sense and hear.
        for column in (ids, ranges, bearings):
            column.flags.writeable = False
        self.ids, self.ranges, self.bearings, self.bounds = ids, ranges, bearings, bounds
        self._xy: Optional[np.ndarray] = None
        self._nearest: Optional[List[float]] = None

    def nearest(self, index: int) -> float:
        """Robot ``index``'s smallest range (inf without neighbours), for all robots at once on first use."""
        if self._nearest is None:
            starts, counts = self.bounds[:-1], np.diff(self.bounds)
            nearest = np.full(len(counts), np.inf)
            has = counts > 0
            if has.any():
                nearest[has] = np.minimum.reduceat(self.ranges, starts[has])
            self._nearest = nearest.tolist()
        return self._nearest[index]

    def xy(self) -> np.ndarray:
        if self._xy is None:
            xy = np.empty((2, len(self.ranges)))
            np.multiply(self.ranges, np.cos(self.bearings), out=xy[0])
            np.multiply(self.ranges, np.sin(self.bearings), out=xy[1])
            xy.flags.writeable = False
            self._xy = xy
        return self._xy


@dataclass
class SensorFrame:
    """What every robot senses at one control step; filled by the runner.

    Per-robot data is kept as Python lists or numpy columns built once per step for all robots (``set_*``),
    so a device read is a list lookup or a slice, not several small numpy operations per robot.
    """

    time_s: float = 0.0
    proximity: Optional[np.ndarray] = None          # (N, 8) normalised readings
    ranges: Optional[np.ndarray] = None              # (N, N) noisy ranges
    bearings: Optional[np.ndarray] = None            # (N, N) noisy bearings
    # Per robot: the latest motion-capture pose as (x, y, yaw, stamp_s), or None before the first one.
    # Plain tuples: the Pose record is built when a behaviour asks, with its age at that moment.
    pose_rows: List[Optional[Tuple[float, float, float, float]]] = field(default_factory=list)
    inboxes: List[List[Message]] = field(default_factory=list)
    odometry: Optional[np.ndarray] = None            # (N, 2) cumulative wheel distances
    proximity_rows: List[Tuple[float, ...]] = field(default_factory=list)
    odometry_rows: List[Tuple[float, float]] = field(default_factory=list)
    # Every robot's neighbours, robot after robot: robot i's are items bounds[i]:bounds[i + 1] of each column
    # of ``pairs``; a robot's device hands out slices (views).
    neighbour_bounds: List[int] = field(default_factory=list)
    pairs: Optional[PairColumns] = None

    def set_neighbours(self, mask: np.ndarray, ranges: np.ndarray, bearings: np.ndarray) -> None:
        """``mask[i, j]``: j is i's neighbour; ``ranges``/``bearings`` (N, N) as i measures j."""
        self.ranges, self.bearings = ranges, bearings
        rows, cols = np.nonzero(mask)                # row-major: each robot's neighbours in id order
        bounds = np.searchsorted(rows, np.arange(len(mask) + 1))
        self.neighbour_bounds = bounds.tolist()
        self.pairs = PairColumns(cols, ranges[mask], bearings[mask], bounds)   # row-major; cheaper than [rows, cols]

    def receivers(self, index: int) -> np.ndarray:
        """Ids of the robots within radio range of robot ``index`` (its neighbours), ascending."""
        start, end = self.neighbour_bounds[index:index + 2]
        return self.pairs.ids[start:end]

    def set_proximity(self, readings: np.ndarray) -> None:
        self.proximity = readings
        self.proximity_rows = [tuple(row) for row in readings.tolist()]

    def set_odometry(self, distances: np.ndarray) -> None:
        self.odometry = distances
        self.odometry_rows = [tuple(row) for row in distances.tolist()]


_new_instance = object.__new__


def _record(cls: type, **fields: Any) -> Any:
    """The frozen record ``cls(**fields)`` (every field given), filled without the dataclass __init__'s
    per-field ``object.__setattr__``: 2-3x cheaper, and devices are read by every robot at every step."""
    record = _new_instance(cls)
    record.__dict__.update(fields)
    return record


class SimProximity(hal.ProximitySensor):
    def __init__(self, frame: SensorFrame, index: int):
        self._frame, self._index = frame, index

    def read(self) -> ProximityReading:
        values = self._frame.proximity_rows[self._index]
        return _record(ProximityReading, values=values, angles_rad=PROXIMITY_ANGLES_RAD)


class SimRangeAndBearing(hal.RangeAndBearingSensor):
    def __init__(self, frame: SensorFrame, index: int):
        self._frame, self._index = frame, index

    def neighbours(self) -> Neighbours:
        # Views into the step's columns, sliced when first read: no record is made, and no x/y computed,
        # unless the behaviour asks.
        start, end = self._frame.neighbour_bounds[self._index:self._index + 2]
        return _PairNeighbours(self._frame.pairs, self._index, start, end)


_MISSING: Any = object()


class _PairNeighbours(Neighbours):
    """A robot's slice of one step's pairs; its ``xy`` is the same slice of the pairs' x/y (the same values
    as computing them from this robot's columns alone). The columns are sliced on first use: many steps
    only ask for ``nearest_m`` or a neighbour's vector."""

    __slots__ = ("_pairs", "_index", "_start", "_end", "_columns")

    def __init__(self, pairs: PairColumns, index: int, start: int, end: int) -> None:
        # Neighbours.__init__ minus its conversions, which the pairs' columns (int64 ids, float ranges and
        # bearings) do not need; the columns themselves are made by the properties below.
        self._pairs, self._index, self._start, self._end = pairs, index, start, end
        self._columns: Any = _MISSING
        self.age_s = 0.0
        self._xy = None
        self._records = None
        self._id_list = None
        self._ascending = True                     # row-major pairs: each robot's neighbours in id order

    def _slice(self) -> Any:
        start, end, pairs = self._start, self._end, self._pairs
        self._columns = (np.asarray(pairs.ids[start:end], dtype=np.int64), pairs.ranges[start:end],
                         pairs.bearings[start:end])
        return self._columns

    @property
    def ids(self) -> np.ndarray:               # type: ignore[override]
        columns = self._columns
        return (self._slice() if columns is _MISSING else columns)[0]

    @property
    def ranges_m(self) -> np.ndarray:          # type: ignore[override]
        columns = self._columns
        return (self._slice() if columns is _MISSING else columns)[1]

    @property
    def bearings_rad(self) -> np.ndarray:      # type: ignore[override]
        columns = self._columns
        return (self._slice() if columns is _MISSING else columns)[2]

    def __len__(self) -> int:
        return self._end - self._start

    @property
    def xy(self) -> np.ndarray:
        if self._xy is None:
            self._xy = self._pairs.xy()[:, self._start:self._end]
        return self._xy

    @property
    def nearest_m(self) -> float:
        return self._pairs.nearest(self._index)


class SimRadio(hal.Radio):
    def __init__(self, frame: SensorFrame, index: int):
        self._frame, self._index = frame, index
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
            raise TypeError(f"radio payload must be a mapping, got {type(payload).__name__}")
        encoded, copy = encode_payload(payload)
        if len(encoded) > self.MAX_PAYLOAD_BYTES:
            raise ValueError(f"radio payload of {len(encoded)} bytes exceeds "
                             f"{self.MAX_PAYLOAD_BYTES}")
        self.outbox.append(copy)

    def receive(self) -> List[Message]:
        inbox = self._frame.inboxes[self._index]
        self._frame.inboxes[self._index] = []
        return inbox


# Built once, not per call as json.dumps does. No NaN or infinity: the wire protocol refuses them (JSON has none).
_compact_json = json.JSONEncoder(separators=(",", ":"), allow_nan=False).encode


def encode_payload(payload: Mapping[str, Any]) -> Tuple[str, Dict[str, Any]]:
    """The payload's compact JSON and the decoded copy receivers get (one copy, shared by all of them).
    RadioPayloadError names a field that JSON could not carry as sent (``onboard.hal.payload``).

    A tuple-space message (``Gossip``) already knows its JSON text, so it is neither encoded again nor
    re-checked; it is decoded from that text, and stays a Gossip so the receivers' replicas merge it fast.
    """
    if len(payload) == 1:                          # the usual tuple-space message: {"ts": Gossip}
        ((key, value),) = payload.items()
        if type(key) is str and type(value) is Gossip:
            text = value.json_text()
            return f"{{{_compact_json(key)}:{text}}}", {key: value.decoded_copy(text) if value else Gossip()}
    if not any(type(value) is Gossip for value in payload.values()) or \
            not all(type(key) is str for key in payload):
        copy = plain_payload(payload)              # fresh, so it is also the copy receivers share
        return _compact_json(copy), copy
    plain = plain_payload({key: value for key, value in payload.items() if type(value) is not Gossip})
    parts, copy = [], {}
    for key, value in payload.items():
        if type(value) is Gossip:
            text = value.json_text()
            copy[key] = value.decoded_copy(text)
        else:
            text = _compact_json(plain[key])
            copy[key] = plain[key]
        parts.append(f"{_compact_json(key)}:{text}")
    return "{" + ",".join(parts) + "}", copy


class SimWheels(hal.DifferentialSteering):
    def __init__(self, spec: RobotSpec):
        self.spec = spec
        self.left = self.right = 0.0

    def set_speeds(self, left_m_s: float, right_m_s: float) -> None:
        self.left, self.right = commanded_wheel_speeds(left_m_s, right_m_s, self.spec.max_wheel_speed_m_s)

    def stop(self) -> None:
        self.left = self.right = 0.0               # what set_speeds(0.0, 0.0) stores, without its checks


class SimOdometry(hal.Odometry):
    def __init__(self, frame: SensorFrame, index: int):
        self._frame, self._index = frame, index
        self._left_zero = self._right_zero = 0.0

    def read(self) -> WheelOdometry:
        left, right = self._frame.odometry_rows[self._index]
        return _record(WheelOdometry, left_m=left - self._left_zero, right_m=right - self._right_zero)

    def count_from_here(self, counts: Tuple[float, float]) -> None:
        """Count from 0 again, from the world's ``counts`` now, as a restarted agent's KheperaIV driver does (it
        reads its encoders' start)."""
        self._left_zero, self._right_zero = counts


class SimPositioning(hal.Positioning):
    def __init__(self, frame: SensorFrame, index: int):
        self._frame, self._index = frame, index

    def pose(self) -> Optional[Pose]:
        row = self._frame.pose_rows[self._index]
        if row is None:
            return None
        x, y, yaw, stamp = row
        return _record(Pose, x=x, y=y, yaw_rad=yaw, stamp_s=stamp, age_s=self._frame.time_s - stamp)


class SimClock(hal.Clock):
    def __init__(self, frame: SensorFrame):
        self._frame = frame

    def now(self) -> float:
        return self._frame.time_s


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
