"""The simulator's implementation of the HAL: each device reads the per-step :class:`SensorFrame` that the
runner computes for all robots at once (vectorised), and writes commands the runner forwards to physics.

Nothing here gives a behaviour the world, the object or another robot's state.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Optional

import numpy as np

from onboard import hal
from onboard.hal import Message, Neighbour, Pose, ProximityReading, RobotSpec, WheelOdometry, clamp_wheel_speeds


@dataclass
class SensorFrame:
    """What every robot senses at one control step; filled by the runner."""

    time_s: float = 0.0
    proximity: Optional[np.ndarray] = None          # (N, 8) normalised readings
    neighbour_ids: List[np.ndarray] = field(default_factory=list)   # per robot: ids in range
    ranges: Optional[np.ndarray] = None              # (N, N) noisy ranges
    bearings: Optional[np.ndarray] = None            # (N, N) noisy bearings
    poses: List[Optional[Pose]] = field(default_factory=list)
    inboxes: List[List[Message]] = field(default_factory=list)
    odometry: Optional[np.ndarray] = None            # (N, 2) cumulative wheel distances


class SimProximity(hal.ProximitySensor):
    def __init__(self, frame: SensorFrame, index: int):
        self.frame, self.index = frame, index

    def read(self) -> ProximityReading:
        return ProximityReading(values=tuple(self.frame.proximity[self.index].tolist()))


class SimRangeAndBearing(hal.RangeAndBearingSensor):
    def __init__(self, frame: SensorFrame, index: int):
        self.frame, self.index = frame, index

    def neighbours(self) -> List[Neighbour]:
        i, frame = self.index, self.frame
        ids = frame.neighbour_ids[i]
        ranges = frame.ranges[i, ids].tolist()
        bearings = frame.bearings[i, ids].tolist()
        return [Neighbour(int(j), r, b) for j, r, b in zip(ids.tolist(), ranges, bearings)]


class SimRadio(hal.Radio):
    def __init__(self, frame: SensorFrame, index: int):
        self.frame, self.index = frame, index
        self.outbox: List[Dict[str, Any]] = []

    def broadcast(self, payload: Mapping[str, Any]) -> None:
        # Encode as the real radio would: refuses what could not cross the wire, and isolates the copy
        # the receivers get from later changes by the sender.
        if not isinstance(payload, Mapping):
            raise TypeError(f"robot {self.index}: radio payload must be a mapping, got {type(payload).__name__}")
        encoded = json.dumps(payload, separators=(",", ":"))
        if len(encoded) > self.MAX_PAYLOAD_BYTES:
            raise ValueError(f"robot {self.index}: radio payload of {len(encoded)} bytes exceeds "
                             f"{self.MAX_PAYLOAD_BYTES}")
        self.outbox.append(json.loads(encoded))

    def receive(self) -> List[Message]:
        inbox = self.frame.inboxes[self.index]
        self.frame.inboxes[self.index] = []
        return inbox


class SimWheels(hal.DifferentialSteering):
    def __init__(self, spec: RobotSpec):
        self.spec = spec
        self.left = self.right = 0.0

    def set_speeds(self, left_m_s: float, right_m_s: float) -> None:
        if not (np.isfinite(left_m_s) and np.isfinite(right_m_s)):
            raise ValueError(f"wheel speeds must be finite (got {left_m_s}, {right_m_s})")
        self.left, self.right = clamp_wheel_speeds(float(left_m_s), float(right_m_s), self.spec.max_wheel_speed_m_s)


class SimOdometry(hal.Odometry):
    def __init__(self, frame: SensorFrame, index: int):
        self.frame, self.index = frame, index

    def read(self) -> WheelOdometry:
        left, right = self.frame.odometry[self.index]
        return WheelOdometry(float(left), float(right))


class SimPositioning(hal.Positioning):
    def __init__(self, frame: SensorFrame, index: int):
        self.frame, self.index = frame, index

    def pose(self) -> Optional[Pose]:
        pose = self.frame.poses[self.index]
        if pose is None:
            return None
        return Pose(pose.x, pose.y, pose.yaw_rad, pose.stamp_s, self.frame.time_s - pose.stamp_s)


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
