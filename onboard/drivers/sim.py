"""The ``sim`` driver: the robot is simulated by the hub's ``sim`` source.

Wheel commands go up to the hub as ``wheels`` messages; IR and encoder readings come down in every frame's
``sim`` field. Everything else in the agent is the code that runs on a real robot.
"""
from __future__ import annotations

import time
from typing import Any, Callable, Dict, List, Optional

from onboard.drivers import Driver
from onboard.hal import WheelOdometry


class SimDriver(Driver):
    name = "sim"

    def __init__(self, send: Callable[[Dict[str, Any]], bool], readings: Callable[[], Optional[Dict[str, Any]]],
                 first: Optional[Callable[[], Optional[Dict[str, Any]]]] = None):
        """``send`` delivers an uplink message to the hub; ``readings`` returns the latest frame's ``sim`` field,
        ``first`` the first frame's since the agent started (where the encoders count from; without it, the
        first reading's)."""
        self.send = send
        self.readings = readings
        self.first = first if first is not None else readings
        self.left = self.right = 0.0
        self._zero: Optional[WheelOdometry] = None   # the simulator's counts when this agent's frames began

    def set_wheel_speeds(self, left_m_s: float, right_m_s: float) -> None:
        self.left, self.right = float(left_m_s), float(right_m_s)
        # at_s: when the agent set them, on its monotonic clock: what a test on this machine compares with when
        # it stopped sending frames (the watchdog's 0.3 s), without the hub's and the test's own delays.
        self.send({"type": "wheels", "left": self.left, "right": self.right, "at_s": time.monotonic()})

    def proximity(self) -> List[float]:
        data = self.readings()
        return list(data["ir"]) if data else [0.0] * 8

    def encoders(self) -> WheelOdometry:
        """Distances rolled since the agent's first frame, as the KheperaIV driver counts from its start: an
        agent restarted mid-run starts at 0 on either driver, whenever its behaviour first reads them."""
        data = self.readings()
        if not data:
            return WheelOdometry(0.0, 0.0)
        if self._zero is None:
            start = self.first() or data
            self._zero = WheelOdometry(*start["odo"])
        counts = WheelOdometry(*data["odo"])
        return WheelOdometry(counts.left_m - self._zero.left_m, counts.right_m - self._zero.right_m)
