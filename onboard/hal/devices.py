"""One small interface per sensor and actuator. Backends (simulator, hub + driver) implement them.

A behaviour receives a :class:`Robot` bundle of these devices and nothing else: no simulator, no world,
no object pose. Each interface is deliberately tiny so that a real implementation is a few lines.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, List, Mapping, Optional

from .records import Message, Neighbours, Pose, ProximityReading, RobotSpec, WheelOdometry


class ProximitySensor(ABC):
    @abstractmethod
    def read(self) -> ProximityReading:
        """The latest 8 normalised IR readings (ARGoS order: 0 forward, counter-clockwise)."""


class RangeAndBearingSensor(ABC):
    @abstractmethod
    def neighbours(self) -> Neighbours:
        """Robots within communication range d_C at the latest measurement: a sequence of ``Neighbour``
        records that also offers them as numpy columns (see :class:`Neighbours`; ``Neighbours.of(records)``
        wraps a list of records)."""


class Radio(ABC):
    #: Largest payload (bytes of compact JSON) a backend must carry; larger broadcasts are refused.
    MAX_PAYLOAD_BYTES = 8192
    #: Messages a robot keeps between two of its steps; beyond, the oldest are dropped (and counted). The
    #: simulator and the agent both keep this many, so a swarm that floods a robot loses the same messages.
    INBOX_LIMIT = 256

    @abstractmethod
    def broadcast(self, payload: Mapping[str, Any]) -> None:
        """Send a JSON-compatible mapping to every robot within communication range (best effort)."""

    @abstractmethod
    def receive(self) -> List[Message]:
        """Messages that arrived since the previous call (each delivered once)."""


class DifferentialSteering(ABC):
    @abstractmethod
    def set_speeds(self, left_m_s: float, right_m_s: float) -> None:
        """Command wheel speeds (m/s, forward positive); values beyond the robot's limit are clamped."""

    def stop(self) -> None:
        self.set_speeds(0.0, 0.0)


class Odometry(ABC):
    @abstractmethod
    def read(self) -> WheelOdometry:
        """Cumulative wheel distances from the encoders."""


class Positioning(ABC):
    @abstractmethod
    def pose(self) -> Optional[Pose]:
        """The latest pose the hub sent (noisy, maybe stale: check ``age_s``), or None if none yet."""


class Clock(ABC):
    @abstractmethod
    def now(self) -> float:
        """Seconds since the behaviour started (simulated time in simulation)."""


@dataclass
class Robot:
    """Everything a behaviour may touch. ``spec`` carries the robot's physical constants."""

    id: int
    proximity: ProximitySensor
    range_and_bearing: RangeAndBearingSensor
    radio: Radio
    wheels: DifferentialSteering
    odometry: Odometry
    positioning: Positioning
    clock: Clock
    spec: RobotSpec


def commanded_wheel_speeds(left_m_s: Any, right_m_s: Any, limit: float) -> tuple:
    """What a behaviour's ``set_speeds(left_m_s, right_m_s)`` drives: both numbers, clamped together
    (clamp_wheel_speeds). Anything else is refused naming the argument: a NaN would reach the motors, and
    Python's own "must be real number, not str" named neither the call nor the wheel."""
    try:
        if math.isfinite(left_m_s) and math.isfinite(right_m_s):
            return clamp_wheel_speeds(float(left_m_s), float(right_m_s), limit)
    except (TypeError, OverflowError):     # OverflowError: an int too large for a float (10 ** 400)
        pass
    bad, value = ("left_m_s", left_m_s) if not _finite_number(left_m_s) else ("right_m_s", right_m_s)
    raise ValueError(f"set_speeds({bad}={value!r}): wheel speeds must be finite numbers (m/s)")


def _finite_number(value: Any) -> bool:
    try:
        return math.isfinite(value)
    except (TypeError, OverflowError):
        return False


def clamp_wheel_speeds(left: float, right: float, limit: float) -> tuple:
    """Clamp each wheel to ±limit, scaling both together so the robot keeps its turning radius."""
    biggest = max(abs(left), abs(right))
    if biggest > limit > 0.0:
        scale = limit / biggest
        return left * scale, right * scale
    return left, right
