"""What a new run starts from (``khepri ctl start`` with no run going, ``hub/control_service.py``).

With the ``sim`` source the hub holds the world, and a run's mission (the scenario's waypoints, the object estimate
the behaviour starts from, the faults' times) is the scenario's, from its start. So, as a new ``khepri sim run``
would, each run begins in the world the scenario builds for its seed: robots, object and their velocities,
faults, and the hub's own noise (range and bearing, relay drops) from the start of its stream. A world
that has not moved since it was built (``khepri sil``'s one run, in lockstep) is used as it is;
``source.reset_each_run: false`` keeps the world as the last run left it (docs/lab.md). A replay likewise plays
its log from the first record again for each run.
"""
from __future__ import annotations

import time
from typing import TYPE_CHECKING

from .sources import SourceRestartError

if TYPE_CHECKING:
    from .server import Hub


def prepare_new_run(hub: Hub) -> bool:
    """Leave nothing of the last run to the new one; whether the world was set back to the scenario's start."""
    for robot in hub.ids:         # messages the last run's robots sent, still waiting for a robot out of reach
        hub.relay.clear(robot)
    source = hub.source
    restart = getattr(source, "restart", None)
    if restart is None or not hub.config.source.reset_each_run or source.pristine:
        return False
    # The new world's first frame goes through the hub as any frame does: poses, presence, the killed robots,
    # IR and odometry, the clock, the log. Its robots' wheels stand still until their agents start the run.
    try:
        first = restart(time.monotonic())
    except SourceRestartError as err:
        hub.log(f"hub: {err}")
        return False
    if first is not None:          # a replay whose first record is unreadable: its next one comes in time
        hub.on_pose_frame(first)
    hub.restart_noise()
    return True
