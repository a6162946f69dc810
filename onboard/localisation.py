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


_new_instance = object.__new__


class PoseTracker:
    def __init__(self, robot: Robot, max_age_s: float = 1.0, history_s: float = 2.0):
        self.robot = robot
        self.max_age_s = max_age_s
        self.history_s = history_s
        self._odometry: Deque[Tuple[float, float, float]] = deque()   # (time, left, right)

    def update(self) -> Optional[Estimate]:
        robot, history = self.robot, self._odometry
        now = robot.clock.now()
        odo = robot.odometry.read()
        left, right = odo.left_m, odo.right_m
        history.append((now, left, right))
        oldest = now - self.history_s
        while history and history[0][0] < oldest:
            history.popleft()
        pose = robot.positioning.pose()
        if pose is None:
            return None
        x, y, yaw = pose.x, pose.y, pose.yaw_rad
        base = self._odometry_at(pose.stamp_s)
        if base is not None:
            # Replay what the wheels did since the pose was measured (straight-line approximation).
            d_left, d_right = left - base[0], right - base[1]
            distance = 0.5 * (d_left + d_right)
            turn = (d_right - d_left) / robot.spec.wheel_base_m
            mid = yaw + 0.5 * turn
            x, y, yaw = x + distance * math.cos(mid), y + distance * math.sin(mid), wrap_angle(yaw + turn)
        age = pose.age_s
        # Estimate(x, y, yaw, age, stale) without the frozen dataclass's per-field __setattr__ (every step).
        estimate = _new_instance(Estimate)
        estimate.__dict__.update(x=x, y=y, yaw=yaw, age_s=age, stale=age > self.max_age_s)
        return estimate

    def _odometry_at(self, stamp: float) -> Optional[Tuple[float, float]]:
        """Wheel distances at (or just before) ``stamp``, if the history reaches back that far."""
        # Newest first: poses are recent, so this usually stops at once (times only grow along the history).
        limit = stamp + 1e-9
        for t, left, right in reversed(self._odometry):
            if t <= limit:
                return (left, right)
        return None
