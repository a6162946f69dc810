"""Drivers: what the onboard agent uses to move wheels and read the robot's own sensors.

A driver is the robot-side half of the HAL. The agent combines it with what the hub sends (pose, neighbours'
range and bearing, relayed messages) into the :class:`onboard.hal.Robot` bundle a behaviour receives.
Implementations: ``kh4`` (libkhepera through ctypes, :mod:`onboard.drivers.kh4`) and ``sim`` (wheels and IR
through the hub's ``sim`` source).
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from typing import List, Optional

from onboard.hal import WheelOdometry


class DriverError(RuntimeError):
    """The robot's own hardware failed (a bus error, a device that will not open): not the behaviour's bug."""


class Driver(ABC):
    """The robot's own hardware. Every method must be cheap: the agent calls them at 10 Hz."""

    name = ""      # as the agent's --driver names it (kh4, sim); the hub's status shows it

    @abstractmethod
    def set_wheel_speeds(self, left_m_s: float, right_m_s: float) -> None:
        """Command wheel speeds in m/s (forward positive); the driver converts to hardware units."""

    def stop(self) -> None:
        """Stop both wheels now. Must be safe to call any number of times, also after :meth:`close`."""
        self.set_wheel_speeds(0.0, 0.0)

    @abstractmethod
    def proximity(self) -> List[float]:
        """Eight normalised IR readings (0 nothing .. 1 touching) in the HAL's order (0 forward, CCW)."""

    @abstractmethod
    def encoders(self) -> WheelOdometry:
        """Cumulative distance each wheel travelled since the driver opened, metres."""

    def battery_v(self) -> Optional[float]:
        """Battery voltage if the hardware reports it."""
        return None

    def close(self) -> None:
        """Stop the wheels and release the hardware."""
        self.stop()
