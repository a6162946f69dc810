"""The onboard agent: one process per robot, running a behaviour through a HAL fed by the hub and a driver.

Start it with ``khepri agent --id N --hub HOST --driver kh4|sim`` (or ``python -m onboard.agent ...`` on a
robot). See docs/lab.md and docs/protocol.md.
"""
__all__ = ["Agent", "LoopStats"]


def __getattr__(name):
    # Imported on first use, not with the package: `python -m onboard.agent` on a robot that lacks pyzmq or
    # numpy must reach __main__, which says which package is missing in one line instead of a traceback.
    if name == "Agent":
        from .loop import Agent
        return Agent
    if name == "LoopStats":
        from .loop_stats import LoopStats
        return LoopStats
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
