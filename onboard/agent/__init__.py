"""The onboard agent: one process per robot, running a behaviour through a HAL fed by the hub and a driver.

Start it with ``khepri agent --id N --hub HOST --driver kh4|sim`` (or ``python -m onboard.agent ...`` on a
robot). See docs/lab.md and docs/protocol.md.
"""
from .loop import Agent, LoopStats

__all__ = ["Agent", "LoopStats"]
