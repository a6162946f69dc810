"""Where am I? The hub's motion-capture pose, bridged with wheel odometry when it is late or missing.

Motion capture arrives with some latency and may drop out; the encoders are always there but drift.
:class:`PoseTracker` keeps a short odometry history, and each step returns the latest motion-capture pose
moved forward by the odometry since that pose was measured. With no pose ever received it returns None;
when the pose is older than ``max_age_s`` it still answers but says it is stale, so behaviours can stop.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Deque, Optional, Tuple

from .hal import Robot, wrap_angle


@dataclass(frozen=True)
class Estimate:
    x: float
    y: float
    yaw: float
    age_s: float      # age of the motion-capture pose this estimate is based on
    stale: bool


class PoseTracker:
    def __init__(self, robot: Robot, max_age_s: float = 1.0, history_s: float = 2.0):
        self.robot = robot
        self.max_age_s = max_age_s
        self.history_s = history_s
        self._odometry: Deque[Tuple[float, float, float]] = deque()   # (time, left, right)

    def update(self) -> Optional[Estimate]:
        now = self.robot.clock.now()
        odo = self.robot.odometry.read()
        self._odometry.append((now, odo.left_m, odo.right_m))
        while self._odometry and self._odometry[0][0] < now - self.history_s:
            self._odometry.popleft()
        pose = self.robot.positioning.pose()
        if pose is None:
            return None
        x, y, yaw = pose.x, pose.y, pose.yaw_rad
        base = self._odometry_at(pose.stamp_s)
        if base is not None:
            # Replay what the wheels did since the pose was measured (straight-line approximation).
            d_left, d_right = odo.left_m - base[0], odo.right_m - base[1]
            distance = 0.5 * (d_left + d_right)
            turn = (d_right - d_left) / self.robot.spec.wheel_base_m
            mid = yaw + 0.5 * turn
            x, y, yaw = x + distance * math.cos(mid), y + distance * math.sin(mid), wrap_angle(yaw + turn)
        return Estimate(x, y, yaw, pose.age_s, pose.age_s > self.max_age_s)

    def _odometry_at(self, stamp: float) -> Optional[Tuple[float, float]]:
        """Wheel distances at (or just before) ``stamp``, if the history reaches back that far."""
        # Newest first: poses are recent, so this usually stops at once (times only grow along the history).
        for t, left, right in reversed(self._odometry):
            if t <= stamp + 1e-9:
                return (left, right)
        return None
