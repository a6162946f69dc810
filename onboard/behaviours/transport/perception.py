"""What a robot makes of its raw sensors each step: its pose, its neighbours in the world frame, and
which IR readings are the object (not a neighbouring robot)."""
from __future__ import annotations

import math
from bisect import bisect_left
from collections.abc import ItemsView, Mapping, ValuesView
from dataclasses import dataclass
from typing import Any, Collection, Dict, Iterator, List, Optional, Sequence, Tuple

from ...hal import Neighbour, Neighbours, ProximityReading, wrap_angle
from .control import ZERO, Vec, rotate

# A reading is a neighbouring robot, not the object, when a neighbour lies within this range and bearing
# of the sensor's direction (the authors' check: 0.3 m and 0.5 rad).
ROBOT_ECHO_RANGE_M = 0.3
ROBOT_ECHO_BEARING_RAD = 0.5
# Readings below this are sensor noise and ambient light, not an obstacle (~11 cm on the ARGoS curve).
DETECTION_FLOOR = 0.05


@dataclass
class Percept:
    x: float
    y: float
    yaw: float
    neighbours: Mapping                 # world-frame vector from this robot to each neighbour (id -> Vec)
    object_vector: Vec                  # x_o in the world frame (sum of object readings as vectors)
    object_peak: float                  # strongest object reading
    obstacle_vector: Vec                # every reading (object, robots, walls) as a world vector

    @property
    def position(self) -> Vec:
        return (self.x, self.y)

    def in_contact(self, threshold: float) -> bool:
        return self.object_peak >= threshold


class NeighbourVectors(Mapping):
    """Neighbour id -> world-frame vector (x, y) from this robot: a read-only mapping, made lazily.

    A robot among 99 others gets a new one every step, and most steps use few of the vectors (collision
    avoidance needs only those within d_s, the cage a few members by id). So nothing is computed up front:
    the first full use (iterating, ``len``) rotates every neighbour at once (numpy, the same arithmetic as
    control.rotate, so the same floats) into two lists, and ``items()`` pairs them up on the fly;
    ``get``/``[]``/``in`` find one id by bisection and rotate just that vector (a dict is built instead when
    the ids are not ascending); :meth:`within` rotates only the neighbours in range.
    """

    __slots__ = ("table", "_cos", "_sin", "_xs", "_ys", "_dict")

    def __init__(self, table: Neighbours, yaw: float) -> None:
        self.table = table
        self._cos, self._sin = math.cos(yaw), math.sin(yaw)
        self._xs: Optional[List[float]] = None
        self._ys: Optional[List[float]] = None
        self._dict: Optional[Dict[int, Vec]] = None

    @property
    def ids(self) -> List[int]:
        return self.table.id_list()

    @property
    def xs(self) -> List[float]:
        if self._xs is None:
            self._xs, self._ys = self._rotate(self.table.xy)
        return self._xs

    @property
    def ys(self) -> List[float]:
        if self._ys is None:
            self._xs, self._ys = self._rotate(self.table.xy)
        return self._ys

    def _rotate(self, xy: Any) -> Tuple[List[float], List[float]]:
        c, s = self._cos, self._sin
        x, y = xy
        return (c * x - s * y).tolist(), (s * x + c * y).tolist()

    def within(self, radius: float, exclude: Optional[Collection[int]] = None) -> List[Vec]:
        """The vectors of the neighbours at most ``radius`` away (by measured range, so perhaps a few more
        whose vector is a hair longer: filter exactly if it matters), in sensor order, minus ``exclude``.
        Only those neighbours are rotated (the same arithmetic, so the same floats)."""
        table = self.table
        limit = radius * (1.0 + 1e-9)
        if table.nearest_m > limit:
            return []                   # the usual case: nobody that close
        close = (table.ranges_m <= limit).nonzero()[0].tolist()
        if exclude:
            ids = table.ids
            close = [i for i in close if ids.item(i) not in exclude]
        if self._xs is not None:
            xs, ys = self._xs, self._ys
            return [(xs[i], ys[i]) for i in close]
        c, s = self._cos, self._sin
        vectors = []
        xy = table.known_xy()
        for i in close:                 # a few at most: plain floats beat a dozen small numpy calls
            if xy is None:
                r, b = table.ranges_m.item(i), table.bearings_rad.item(i)
                x, y = r * math.cos(b), r * math.sin(b)
            else:
                x, y = xy.item(0, i), xy.item(1, i)
            vectors.append((c * x - s * y, s * x + c * y))
        return vectors

    def nearest_among(self, among: Collection[int]) -> Any:
        """``nearest(self, among)`` rotating only the neighbours in ``among`` (found by bisection), in the
        sensor's order with the same floats; ``_UNSURE`` when ids cannot be bisected (then ask ``nearest``)."""
        if self._dict is not None or not self.table.ids_ascending():
            return _UNSURE
        ids = self.ids
        count = len(ids)
        indices = []
        for key in among:
            if type(key) is not int:
                return _UNSURE
            index = bisect_left(ids, key)
            if index < count and ids[index] == key:
                indices.append(index)
        if not indices:
            return None
        indices.sort()
        if self._xs is not None:
            xs, ys = self._xs, self._ys
            vectors = [(xs[i], ys[i]) for i in indices]
        else:
            # The x, y the full rotation would use (the table's xy, made now as it would be), rotated with
            # the same arithmetic as _rotate: products and differences of the same floats.
            xy = self.table.xy
            c, s = self._cos, self._sin
            vectors = []
            for i in indices:
                x, y = xy.item(0, i), xy.item(1, i)
                vectors.append((c * x - s * y, s * x + c * y))
        best, best_d = None, math.inf
        for i, v in zip(indices, vectors):
            d = math.hypot(v[0], v[1])
            if d < best_d:
                best, best_d = ids[i], d
        return best

    def _mapping(self) -> Dict[int, Vec]:
        if self._dict is None:
            self._dict = dict(zip(self.ids, zip(self.xs, self.ys)))
        return self._dict

    def _position(self, key: object) -> Optional[int]:
        """Where neighbour ``key`` sits in the sensor's order, found by bisection (None if absent); the
        dict is built instead when ids are not plain ints in ascending order."""
        if self._dict is not None or type(key) is not int or not self.table.ids_ascending():
            return None
        ids = self.ids
        index = bisect_left(ids, key)
        return index if index < len(ids) and ids[index] == key else -1

    def _vector(self, index: int) -> Vec:
        """One neighbour's vector: the same floats as rotating all of them."""
        if self._xs is not None:
            return (self._xs[index], self._ys[index])
        table, xy = self.table, self.table.known_xy()
        if xy is None:
            r, b = table.ranges_m.item(index), table.bearings_rad.item(index)
            x, y = r * math.cos(b), r * math.sin(b)
        else:
            x, y = xy.item(0, index), xy.item(1, index)
        c, s = self._cos, self._sin
        return (c * x - s * y, s * x + c * y)

    def __getitem__(self, key: int) -> Vec:
        index = self._position(key)
        if index is None:
            return self._mapping()[key]
        if index < 0:
            raise KeyError(key)
        return self._vector(index)

    def get(self, key, default=None):
        # A step asks for a few neighbours by id (predecessor, formation): no need to build the whole dict.
        index = self._position(key)
        if index is None:
            return self._mapping().get(key, default)
        return default if index < 0 else self._vector(index)

    def __contains__(self, key: object) -> bool:
        index = self._position(key)
        return key in self._mapping() if index is None else index >= 0

    def __iter__(self) -> Iterator[int]:
        return iter(self._mapping())

    def __len__(self) -> int:
        return len(self._mapping())

    def items(self) -> ItemsView:
        return _Items(self)

    def values(self) -> ValuesView:
        return _Values(self)

    def __repr__(self) -> str:
        return f"NeighbourVectors({self._mapping()!r})"


_UNSURE: Any = object()


def near(neighbours: Mapping, radius: float, exclude: Optional[Collection[int]] = None) -> List[Vec]:
    """The vectors of ``neighbours`` (a Percept's) within about ``radius``, minus ``exclude``: what
    ``control.u_avoid`` needs, without touching the far ones when ``neighbours`` is a NeighbourVectors.
    Vectors slightly beyond ``radius`` may be included; every vector within it is."""
    if isinstance(neighbours, NeighbourVectors):
        return neighbours.within(radius, exclude)
    limit = radius * (1.0 + 1e-9)
    return [v for j, v in neighbours.items() if (not exclude or j not in exclude) and math.hypot(v[0], v[1]) <= limit]


class _Items(ItemsView):
    def __iter__(self) -> Iterator[Tuple[int, Vec]]:
        vectors = self._mapping
        if vectors._dict is None:       # the usual single pass: no dict needed (ids are unique)
            return zip(vectors.ids, zip(vectors.xs, vectors.ys))
        return iter(vectors._dict.items())


class _Values(ValuesView):
    def __iter__(self) -> Iterator[Vec]:
        vectors = self._mapping
        if vectors._dict is None:
            return zip(vectors.xs, vectors.ys)
        return iter(vectors._dict.values())


def perceive(x: float, y: float, yaw: float, neighbours: Sequence[Neighbour],
             reading: ProximityReading) -> Percept:
    table = Neighbours.of(neighbours)
    world_neighbours = NeighbourVectors(table, yaw)
    ox = oy = ax = ay = 0.0
    peak = 0.0
    echoes: Optional[List[Tuple[float, float]]] = None
    for value, angle in zip(reading.values, reading.angles_rad):
        if value < DETECTION_FLOOR:
            continue
        direction = angle + yaw
        vx, vy = value * math.cos(direction), value * math.sin(direction)
        ax += vx
        ay += vy
        if echoes is None:
            echoes = _close_neighbours(table)
        if echoes and _is_robot_echo(angle, echoes):
            continue
        ox += vx
        oy += vy
        if value > peak:
            peak = value
    object_vector = (ox, oy) if peak > 0.0 else ZERO
    return Percept(x, y, yaw, world_neighbours, object_vector, peak, (ax, ay))


def _close_neighbours(table: Neighbours) -> List[Tuple[float, float]]:
    """(range, bearing) of the neighbours near enough to show up on the IR, in the sensor's order."""
    close = (table.ranges_m <= ROBOT_ECHO_RANGE_M).nonzero()[0]
    return list(zip(table.ranges_m[close].tolist(), table.bearings_rad[close].tolist()))


def _is_robot_echo(sensor_angle: float, close: List[Tuple[float, float]]) -> bool:
    for range_m, bearing in close:
        if range_m <= ROBOT_ECHO_RANGE_M and abs(wrap_angle(bearing - sensor_angle)) <= ROBOT_ECHO_BEARING_RAD:
            return True
    return False


def world_to_robot(v: Vec, yaw: float) -> Vec:
    return rotate(v, -yaw)


def nearest(neighbours: Mapping, among: Optional[set] = None) -> Optional[int]:
    if among is not None and isinstance(neighbours, NeighbourVectors):
        found = neighbours.nearest_among(among)
        if found is not _UNSURE:
            return found
    best, best_d = None, math.inf
    for j, v in neighbours.items():
        if among is not None and j not in among:
            continue
        d = math.hypot(v[0], v[1])
        if d < best_d:
            best, best_d = j, d
    return best
