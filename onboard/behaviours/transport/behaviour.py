"""The transport state machine (work in progress: see issue #3)."""
from __future__ import annotations

from ...behaviour import Behaviour, register
from .params import TransportParams


@register("transport")
class Transport(Behaviour):
    Params = TransportParams

    def step(self) -> None:
        self.robot.wheels.stop()
        self.state = "idle"
