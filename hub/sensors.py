"""Virtual sensors: from the latest motion-capture poses, every robot's own pose and the range and bearing to
every neighbour within d_C, with configurable noise. Vectorised over all pairs with the simulator's geometry
code (``onboard.geometry``), so the lab computes exactly what the simulator computes.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np

from onboard.geometry import neighbour_mask, pairwise_range_bearing, wrap

# Rounding on the wire: 0.1 mm and 0.1 mrad, far below any noise, and short JSON numbers (fast to encode).
WIRE_DECIMALS = 4


@dataclass
class SensingModel:
    range_m: float = 3.0             # d_C: robots farther apart neither sense nor hear each other
    range_noise_m: float = 0.01      # std of the range error
    bearing_noise_rad: float = 0.02  # std of the bearing error
    pose_noise_m: float = 0.0        # std added to relayed x and y (real motion capture is noisy already)
    pose_noise_rad: float = 0.0      # std added to relayed yaw


class VirtualSensors:
    """Holds one sensing snapshot for a fixed list of robot ids (rows)."""

    def __init__(self, ids: List[int], model: SensingModel, rng: np.random.Generator):
        self.ids = np.asarray(ids, dtype=int)
        self.row = {int(rid): i for i, rid in enumerate(ids)}
        self.model = model
        self.rng = rng
        n = len(ids)
        self.present = np.zeros(n, dtype=bool)
        self.true_ranges = np.full((n, n), np.inf)
        self.mask = np.zeros((n, n), dtype=bool)
        self.bearings = np.zeros((n, n))
        self.poses = np.zeros((n, 3))
        self._noisy: Dict[int, Tuple[np.ndarray, np.ndarray]] = {}

    def update(self, poses: np.ndarray, present: np.ndarray) -> None:
        """``poses`` (N, 3) world x, y, yaw per row; ``present`` rows with a fresh pose (tracked and alive).

        The true geometry is computed for all pairs at once; noise is drawn when a robot's frame is built
        (independently per ordered pair and frame, as in the simulator), so a frame sent to a few robots
        does not pay for N^2 random numbers."""
        true_ranges, true_bearings = pairwise_range_bearing(poses[:, :2], poses[:, 2])
        self.present = present.copy()
        self.true_ranges = true_ranges
        self.bearings = true_bearings
        self.mask = neighbour_mask(true_ranges, self.model.range_m) & present[None, :] & present[:, None]
        self.poses = poses.copy()
        self._noisy: Dict[int, Tuple[np.ndarray, np.ndarray]] = {}

    def prepare(self, robot_ids: List[int]) -> None:
        """Draw the noise for several robots' frames in one vectorised pass (rows of the pair matrices)."""
        rows = [self.row[rid] for rid in robot_ids]
        if not rows:
            return
        m, shape = self.model, (len(rows), len(self.ids))
        ranges = np.maximum(self.true_ranges[rows] + self.rng.normal(0.0, m.range_noise_m, shape), 0.0)
        bearings = wrap(self.bearings[rows] + self.rng.normal(0.0, m.bearing_noise_rad, shape))
        ranges, bearings = np.round(ranges, WIRE_DECIMALS), np.round(bearings, WIRE_DECIMALS)
        for k, row in enumerate(rows):
            self._noisy[row] = (ranges[k], bearings[k])

    def neighbours_of(self, robot_id: int) -> List[list]:
        """``[[id, range_m, bearing_rad], ...]`` for the robot's neighbours, noisy, as the wire carries them."""
        i = self.row[robot_id]
        cols = np.nonzero(self.mask[i])[0]
        if not len(cols):
            return []
        if i not in self._noisy:
            self.prepare([robot_id])
        ranges, bearings = self._noisy.pop(i)     # each frame gets fresh noise
        return [[rid, r, b] for rid, r, b in zip(self.ids[cols].tolist(), ranges[cols].tolist(),
                                                 bearings[cols].tolist())]

    def receivers_of(self, robot_id: int) -> List[int]:
        """Robots within d_C of the sender at the latest snapshot (the radio's reach)."""
        i = self.row.get(robot_id)
        if i is None:
            return []
        return self.ids[np.nonzero(self.mask[i])[0]].tolist()

    def pose_of(self, robot_id: int) -> Optional[List[float]]:
        i, m = self.row[robot_id], self.model
        if not self.present[i]:
            return None
        x, y, yaw = self.poses[i].tolist()
        if m.pose_noise_m > 0.0 or m.pose_noise_rad > 0.0:
            dx, dy, dyaw = self.rng.normal(0.0, (m.pose_noise_m, m.pose_noise_m, m.pose_noise_rad))
            x, y, yaw = x + dx, y + dy, float(wrap(yaw + dyaw))
        return [round(x, WIRE_DECIMALS), round(y, WIRE_DECIMALS), round(yaw, WIRE_DECIMALS)]
