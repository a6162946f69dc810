"""Virtual sensors: from the latest motion-capture poses, every robot's own pose and the range and bearing to
every neighbour within d_C, with configurable noise, computed with the simulator's geometry
(``onboard.geometry``: the same formulas and ``wrap``, checked bit for bit in tests/test_hub_sensors.py), so the
lab computes exactly what the simulator computes.

Only the rows that are sent are computed: :meth:`VirtualSensors.frames` builds the sensor part of several
robots' downlink frames in one vectorised pass (geometry of those rows against everyone, noise only for the
pairs within d_C, the neighbour records already in the wire layout), so a pose frame that is due for 17 of 100
robots costs 17 rows, not 100 x 100 pairs, and no Python object per neighbour.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from onboard.geometry import wrap
from onboard.protocol import NEIGHBOUR_DTYPE

# Rounding on the wire: 0.1 mm and 0.1 mrad, far below any noise.
WIRE_DECIMALS = 4
_RECORD = NEIGHBOUR_DTYPE.itemsize
NOISE_POOL = 1 << 16


@dataclass
class SensingModel:
    range_m: float = 3.0             # d_C: robots farther apart neither sense nor hear each other
    range_noise_m: float = 0.01      # std of the range error
    bearing_noise_rad: float = 0.02  # std of the bearing error
    pose_noise_m: float = 0.0        # std added to relayed x and y (real motion capture is noisy already)
    pose_noise_rad: float = 0.0      # std added to relayed yaw


@dataclass
class FrameBatch:
    """The sensor part of several robots' frames, in the order asked: frame ``k`` is for ``rows[k]``."""

    rows: List[int]
    present: List[bool]                          # the robot has a pose (tracked, alive)
    poses: List[Optional[Tuple[float, float, float]]]   # rounded, with pose noise; None when not present
    records: np.ndarray                          # NEIGHBOUR_DTYPE records of every frame, back to back
    blob: memoryview                             # records as bytes
    offsets: List[int]                           # frame k's records are records[offsets[k]:offsets[k + 1]]

    def block(self, k: int) -> memoryview:
        """Frame ``k``'s neighbours in the wire layout (a view, no copy)."""
        return self.blob[self.offsets[k] * _RECORD:self.offsets[k + 1] * _RECORD]

    def count(self, k: int) -> int:
        return self.offsets[k + 1] - self.offsets[k]

    def neighbours(self, k: int) -> List[list]:
        """``[[id, range_m, bearing_rad], ...]`` of frame ``k``, as the agent decodes them."""
        part = self.records[self.offsets[k]:self.offsets[k + 1]]
        return [[i, r, b] for i, r, b in zip(part["id"].tolist(), part["range"].tolist(), part["bearing"].tolist())]


class VirtualSensors:
    """Holds one sensing snapshot for a fixed list of robot ids (rows)."""

    def __init__(self, ids: List[int], model: SensingModel, rng: np.random.Generator):
        self.ids = np.asarray(ids, dtype=np.int64)
        self.row = {int(rid): i for i, rid in enumerate(ids)}
        self.model = model
        self.rng = rng
        n = len(ids)
        self.present = np.zeros(n, dtype=bool)
        self.poses = np.zeros((n, 3))
        self._receivers: Dict[int, List[int]] = {}
        self._pool = np.zeros(0)
        self._pool_at = 0

    def restart(self, rng: np.random.Generator) -> None:
        """Draw from ``rng`` from now on, with none of the old stream's normals left in the pool."""
        self.rng = rng
        self._pool = np.zeros(0)
        self._pool_at = 0

    def update(self, poses: np.ndarray, present: np.ndarray) -> None:
        """``poses`` (N, 3) world x, y, yaw per row; ``present`` rows with a fresh pose (tracked and alive).

        Nothing is computed here: the geometry of a row is computed when its frame is built (:meth:`frames`)
        or when it broadcasts (:meth:`receivers_of`), with fresh noise per ordered pair and frame."""
        self.poses = np.array(poses, dtype=float)
        self.present = np.array(present, dtype=bool)
        self._receivers = {}

    def geometry(self, rows: Sequence[int]) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """True range, bearing and within-d_C mask from each of ``rows`` to every robot, each (len(rows), N).

        Row ``k`` equals row ``rows[k]`` of ``onboard.geometry.pairwise_range_bearing`` and ``neighbour_mask``
        (same operations, element by element), restricted to robots with a pose on both ends."""
        rows = np.asarray(rows, dtype=np.intp)
        x, y, yaw = self.poses[:, 0], self.poses[:, 1], self.poses[:, 2]
        dx = x[None, :] - x[rows, None]
        dy = y[None, :] - y[rows, None]
        ranges = np.hypot(dx, dy)
        bearings = wrap(np.arctan2(dy, dx) - yaw[rows, None])
        own = np.arange(len(rows))
        bearings[own, rows] = 0.0
        mask = (ranges <= self.model.range_m) & self.present[None, :] & self.present[rows, None]
        mask[own, rows] = False
        return ranges, bearings, mask

    def frames(self, robot_ids: Sequence[int]) -> FrameBatch:
        """Poses and neighbour records for these robots' frames, with fresh noise, in one vectorised pass.

        Ranges are computed for the rows against everyone (that is the d_C test); bearings and noise only for
        the pairs within d_C, with the same element-wise operations as :meth:`geometry`. The noise comes from
        a pool of standard normals drawn ahead (:meth:`refill`), off the path from pose frame to robots."""
        m = self.model
        rows = [self.row[rid] for rid in robot_ids]
        k, n = len(rows), len(self.ids)
        index = np.asarray(rows, dtype=np.intp)
        x, y, yaw = self.poses[:, 0], self.poses[:, 1], self.poses[:, 2]
        dx = x - x[index, None]
        dy = y - y[index, None]
        ranges = np.hypot(dx, dy)
        mask = ranges <= m.range_m
        mask &= self.present
        mask[np.arange(k), index] = False
        mask[~self.present[index]] = False
        flat = np.flatnonzero(mask)             # row-major: each frame's neighbours together, in id order
        which, cols = np.divmod(flat, n)
        bearings = np.arctan2(dy.take(flat), dx.take(flat))
        bearings -= yaw.take(index.take(which))
        ranges = ranges.take(flat)
        count = len(flat)
        if m.range_noise_m > 0.0 or m.bearing_noise_rad > 0.0:
            noise = self._noise(2 * count)
            ranges += m.range_noise_m * noise[:count]
            np.maximum(ranges, 0.0, out=ranges)
            bearings += m.bearing_noise_rad * noise[count:]
        bearings = wrap(bearings)
        finite = np.isfinite(bearings)          # a non-finite yaw must not reach the wire (the agent rejects it)
        if not finite.all():
            which, cols, ranges, bearings = which[finite], cols[finite], ranges[finite], bearings[finite]
        records = np.empty(len(cols), dtype=NEIGHBOUR_DTYPE)
        records["id"] = self.ids.take(cols)
        records["range"] = ranges.round(WIRE_DECIMALS)
        records["bearing"] = bearings.round(WIRE_DECIMALS)
        offsets = np.zeros(k + 1, dtype=np.int64)
        np.cumsum(np.bincount(which, minlength=k), out=offsets[1:])
        present = self.present.take(index)
        pose = self.poses.take(index, axis=0)
        if m.pose_noise_m > 0.0 or m.pose_noise_rad > 0.0:
            pose += self.rng.normal(0.0, (m.pose_noise_m, m.pose_noise_m, m.pose_noise_rad), (k, 3))
            pose[:, 2] = wrap(pose[:, 2])
        present &= np.isfinite(pose).all(axis=1)
        present_list = present.tolist()
        poses = [tuple(p) if ok else None for p, ok in zip(pose.round(WIRE_DECIMALS).tolist(), present_list)]
        return FrameBatch(rows, present_list, poses, records, memoryview(records.tobytes()), offsets.tolist())

    def _noise(self, count: int) -> np.ndarray:
        """``count`` standard normals from the pool (drawn now if the pool runs short)."""
        if self._pool_at + count > len(self._pool):
            self.refill(count)
        out = self._pool[self._pool_at:self._pool_at + count]
        self._pool_at += count
        return out

    def refill(self, at_least: int = 0) -> None:
        """Top the noise pool up (64 Ki normals: several bursts of 100 robots); the hub calls this after its
        sends, so the next burst does not wait for the random number generator."""
        size = max(NOISE_POOL, 2 * at_least)
        left = self._pool[self._pool_at:]
        if len(left) >= size // 2 and len(left) >= at_least:
            return
        self._pool = np.concatenate([left, self.rng.standard_normal(size - len(left))])
        self._pool_at = 0

    def neighbours_of(self, robot_id: int) -> List[list]:
        """``[[id, range_m, bearing_rad], ...]`` for the robot's neighbours, noisy, as the wire carries them."""
        return self.frames([robot_id]).neighbours(0)

    def receivers_of(self, robot_id: int) -> List[int]:
        """Robots within d_C of the sender at the latest snapshot (the radio's reach)."""
        i = self.row.get(robot_id)
        if i is None:
            return []
        if i not in self._receivers:
            mask = self.geometry([i])[2][0]
            self._receivers[i] = self.ids[np.nonzero(mask)[0]].tolist()
        return list(self._receivers[i])

    def pose_of(self, robot_id: int) -> Optional[List[float]]:
        i, m = self.row[robot_id], self.model
        if not self.present[i]:
            return None
        x, y, yaw = self.poses[i].tolist()
        if m.pose_noise_m > 0.0 or m.pose_noise_rad > 0.0:
            dx, dy, dyaw = self.rng.normal(0.0, (m.pose_noise_m, m.pose_noise_m, m.pose_noise_rad))
            x, y, yaw = x + dx, y + dy, float(wrap(yaw + dyaw))
        return [round(x, WIRE_DECIMALS), round(y, WIRE_DECIMALS), round(yaw, WIRE_DECIMALS)]
