"""Plain records that sensors return. Units: metres, seconds, radians; frames are documented per field.

The robot frame has x forward and y to the left; angles grow counter-clockwise (ARGoS convention).
The world frame is the motion-capture frame, z up, yaw measured from the world x axis.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Dict, Iterator, List, Optional, Sequence, Tuple, Union, overload

import numpy as np

PROXIMITY_SENSOR_COUNT = 8
#: Angle of each proximity sensor in the robot frame: sensor 0 faces forward, index grows counter-clockwise.
PROXIMITY_ANGLES_RAD: Tuple[float, ...] = tuple(i * math.pi / 4.0 for i in range(PROXIMITY_SENSOR_COUNT))


@dataclass(frozen=True)
class ProximityReading:
    """Eight normalised IR readings in [0, 1] (1 = touching, 0 = nothing within ~0.12 m).

    ``values[i]`` belongs to the sensor at ``angles_rad[i]`` (robot frame).
    """

    values: Tuple[float, ...]
    angles_rad: Tuple[float, ...] = PROXIMITY_ANGLES_RAD


@dataclass(frozen=True)
class Neighbour:
    """Another robot within communication range, as a range-and-bearing sensor reports it.

    ``bearing_rad`` is in the observing robot's frame, in (-pi, pi]; ``age_s`` is how old the
    measurement is (0 in simulation without latency; on real robots the hub frame's age).
    """

    id: int
    range_m: float
    bearing_rad: float
    age_s: float = 0.0

    # Computed once per record (a cached_property lives in the instance, so frozen records can hold it).
    @cached_property
    def x(self) -> float:
        return self.range_m * math.cos(self.bearing_rad)

    @cached_property
    def y(self) -> float:
        return self.range_m * math.sin(self.bearing_rad)

    @classmethod
    def many(cls, ids: Sequence[int], ranges_m: Sequence[float], bearings_rad: Sequence[float],
             age_s: float = 0.0, xs: Optional[Sequence[float]] = None,
             ys: Optional[Sequence[float]] = None) -> List[Neighbour]:
        """One record per (id, range, bearing): the same records as the constructor makes, about twice as
        fast, for backends that make hundreds per step. ``xs``/``ys``, if given, must be range * cos/sin
        bearing (a backend may compute them for all robots at once); otherwise they are computed here."""
        if xs is None or ys is None:
            ranges, bearings = np.asarray(ranges_m, dtype=float), np.asarray(bearings_rad, dtype=float)
            xs, ys = (ranges * np.cos(bearings)).tolist(), (ranges * np.sin(bearings)).tolist()
            ids, ranges_m, bearings_rad = np.asarray(ids).tolist(), ranges.tolist(), bearings.tolist()
        records = []
        for neighbour_id, range_m, bearing, x, y in zip(ids, ranges_m, bearings_rad, xs, ys):
            record = _new_instance(cls)
            # Fills the instance as the frozen dataclass's own __init__ does, minus its per-field overhead.
            fields = record.__dict__
            fields["id"] = neighbour_id
            fields["range_m"] = range_m
            fields["bearing_rad"] = bearing
            fields["age_s"] = age_s
            fields["x"] = x
            fields["y"] = y
            records.append(record)
        return records


_new_instance = object.__new__


class Neighbours(Sequence):
    """What :meth:`RangeAndBearingSensor.neighbours` returns: a read-only sequence of :class:`Neighbour`
    records that also holds the same measurements as numpy columns, for code that handles every neighbour
    at once.

    With 100 robots each one sees 99 others every step; a behaviour that only needs sums, the nearest few
    or a rotation of all of them can use the columns (``ids``, ``ranges_m``, ``bearings_rad``, ``xy``)
    and never make the 99 Python records. Indexing or iterating makes them once, on first use.

    ``xy`` is (2, n): row 0 the neighbours' x, row 1 their y in the observer's frame (range * cos/sin
    bearing, the records' ``x``/``y``). Treat every column as read-only: a backend may share them.
    """

    __slots__ = ("ids", "ranges_m", "bearings_rad", "age_s", "_xy", "_records", "_id_list", "_ascending")

    def __init__(self, ids: Any, ranges_m: Any, bearings_rad: Any, age_s: float = 0.0,
                 xy: Optional[np.ndarray] = None) -> None:
        self.ids = np.asarray(ids, dtype=np.int64)
        self.ranges_m = np.asarray(ranges_m, dtype=float)
        self.bearings_rad = np.asarray(bearings_rad, dtype=float)
        self.age_s = age_s
        self._xy = xy
        self._records: Optional[List[Neighbour]] = None
        self._id_list: Optional[List[int]] = None
        self._ascending: Optional[bool] = None

    @classmethod
    def of(cls, records: Sequence[Neighbour]) -> Neighbours:
        """A table holding ``records`` (for backends that make records one by one); ``age_s`` is the first
        record's. The records themselves are kept and handed out unchanged."""
        if isinstance(records, Neighbours):
            return records
        records = list(records)
        table = cls([n.id for n in records], [n.range_m for n in records], [n.bearing_rad for n in records],
                    records[0].age_s if records else 0.0,
                    np.array([[n.x for n in records], [n.y for n in records]], dtype=float).reshape(2, -1))
        table._records = records
        return table

    @property
    def xy(self) -> np.ndarray:
        if self._xy is None:
            self._xy = np.array([self.ranges_m * np.cos(self.bearings_rad),
                                 self.ranges_m * np.sin(self.bearings_rad)]).reshape(2, -1)
            self._xy.flags.writeable = False     # one table may be handed out to several calls
        return self._xy

    @property
    def nearest_m(self) -> float:
        """The smallest range (inf without neighbours): lets code skip a search for close neighbours."""
        return float(self.ranges_m.min()) if len(self.ranges_m) else math.inf

    def ids_ascending(self) -> bool:
        """True if ``ids`` strictly increase (then an id can be found by bisection)."""
        if self._ascending is None:
            self._ascending = bool(np.all(self.ids[1:] > self.ids[:-1]))
        return self._ascending

    def known_xy(self) -> Optional[np.ndarray]:
        """``xy`` if it was given or computed already, else None (then x, y = range * cos/sin bearing)."""
        return self._xy

    def id_list(self) -> List[int]:
        """``ids`` as a list of Python ints (made once)."""
        if self._id_list is None:
            self._id_list = self.ids.tolist()
        return self._id_list

    def records(self) -> List[Neighbour]:
        """The records as a list (made once; the list is shared, do not change it)."""
        if self._records is None:
            xs, ys = self.xy.tolist()
            self._records = Neighbour.many(self.id_list(), self.ranges_m.tolist(), self.bearings_rad.tolist(),
                                           self.age_s, xs=xs, ys=ys)
        return self._records

    def __len__(self) -> int:
        return len(self.ids)

    @overload
    def __getitem__(self, index: int) -> Neighbour: ...

    @overload
    def __getitem__(self, index: slice) -> List[Neighbour]: ...

    def __getitem__(self, index: Union[int, slice]) -> Union[Neighbour, List[Neighbour]]:
        return self.records()[index]

    def __iter__(self) -> Iterator[Neighbour]:
        return iter(self.records())

    def __eq__(self, other: object) -> bool:
        if isinstance(other, Neighbours):
            return self.records() == other.records()
        if isinstance(other, (list, tuple)):
            return self.records() == list(other)
        return NotImplemented

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"Neighbours({self.records()!r})"


@dataclass(frozen=True)
class Message:
    """A radio message received from ``sender``; ``payload`` is a JSON-compatible mapping.

    ``sent_s`` is the sender's clock when it broadcast (informational: clocks are not synchronised).
    Treat ``payload`` as read-only: in simulation all receivers of one broadcast share it (decoding it once
    per receiver would cost more than the rest of the radio), so a change would reach the others.
    """

    sender: int
    payload: Dict[str, Any]
    sent_s: float = 0.0


@dataclass(frozen=True)
class Pose:
    """The robot's own pose in the world frame, as the hub computed it from motion capture.

    ``stamp_s`` is when the pose was measured on the robot's clock; ``age_s`` how old it was when read.
    """

    x: float
    y: float
    yaw_rad: float
    stamp_s: float
    age_s: float = 0.0


@dataclass(frozen=True)
class WheelOdometry:
    """Cumulative distance each wheel has rolled since start (m), from the encoders. Forward is positive."""

    left_m: float
    right_m: float


@dataclass(frozen=True)
class RobotSpec:
    """Physical facts about the robot that behaviours may use (KheperaIV defaults)."""

    radius_m: float = 0.0704           # ARGoS body radius; diameter 140.8 mm
    wheel_base_m: float = 0.1054       # distance between the wheels
    max_wheel_speed_m_s: float = 0.81  # K-Team spec top speed; scenarios may lower it
    proximity_range_m: float = 0.12    # beyond this the IR reading is 0


def wrap_angle(angle: float) -> float:
    """Wrap an angle to (-pi, pi]."""
    wrapped = math.fmod(angle + math.pi, 2.0 * math.pi)
    if wrapped <= 0.0:
        wrapped += 2.0 * math.pi
    return wrapped - math.pi


__all__ = [
    "PROXIMITY_SENSOR_COUNT", "PROXIMITY_ANGLES_RAD", "ProximityReading", "Neighbour", "Neighbours", "Message", "Pose",
    "WheelOdometry", "RobotSpec", "wrap_angle",
]
