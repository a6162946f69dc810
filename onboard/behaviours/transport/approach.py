"""Where the seed meets the object (option ``seed_from_rear``; not in the paper).

The paper's seed drives straight at the estimated centroid and touches the object wherever it arrives. The
cage then grows left and right from that point, so on a small object caged by three or four robots the
seed's side decides where the pushers end up: a seed that arrived from the side leaves the face that
must be pushed with one robot at its corner, and that robot alone turns the object as it pushes (lab-6:
0.3 rad in three seconds, unseen by the cage, which turns with it). A seed that arrives from behind -- the
side opposite the first leg of travel -- sits on the line of travel through the centroid, and so does the
cage's main pusher.

The seed first circles the estimated centroid at ``radius`` until it is behind it, then drives in along the
line of travel. An object larger than ``radius`` is simply met on the way, as in the paper.
"""
from __future__ import annotations

import math
from typing import Optional, Sequence

from . import control as c
from .control import Vec

ON_LINE_RAD = 0.25        # within this angle of the rear direction (seen from the centroid) the seed drives in
RADIAL_GAIN = 3.0         # per metre of distance from the circle while circling
LINE_GAIN = 3.0           # per metre of lateral offset from the line of travel while driving in
MIN_LEG_M = 0.05          # a waypoint closer than this to where the object is moves it nowhere: a turn at most


def first_travel(centre: Vec, path: Sequence[Sequence[float]], start_yaw: float) -> Optional[Vec]:
    """The unit direction of the object's first leg of travel: from ``centre`` to the first waypoint at least
    MIN_LEG_M away, or between the waypoints before it. Waypoints on the object's start only turn it: a
    user's path that starts where the object lies ([[0, 0, 0], [0, 0.9, 0]]) used to leave the seed to
    arrive from anywhere, and the lab box spun 10-45 degrees under a pusher at its corner (6 of 10 seeds).
    None when the path never moves the object, or turns it more than ON_LINE_RAD before it does: the
    paper's approach then. (Going behind the turned object instead, where the seed would be once the cage
    had turned it, completed 0 of 6 seeds of a 0.8 x 0.5 m box turned 90 degrees and then pushed, against
    2 of 6 the paper's way: members slide round a turning object, so the seed does not stay behind it.)"""
    here, yaw = centre, start_yaw
    for waypoint in path:
        travel = (float(waypoint[0]) - here[0], float(waypoint[1]) - here[1])
        if abs(math.remainder(yaw - start_yaw, 2.0 * math.pi)) > ON_LINE_RAD:
            return None
        if c.norm(travel) >= MIN_LEG_M:
            return c.unit(travel)
        here, yaw = (float(waypoint[0]), float(waypoint[1])), math.radians(float(waypoint[2]))
    return None


def seed_heading(position: Vec, centre: Vec, travel: Optional[Vec], radius: float) -> Vec:
    """Direction (not normalised) for a seed at ``position`` to reach the object from behind, given the
    unit direction of travel (:func:`first_travel`); straight at the centroid when ``travel`` is None."""
    offset = c.sub(position, centre)
    distance = c.norm(offset)
    if travel is None or distance < 1e-6:
        return c.sub(centre, position)        # no direction of travel (the path only turns): the paper's way
    rear = math.atan2(-travel[1], -travel[0])
    off_rear = math.remainder(rear - math.atan2(offset[1], offset[0]), 2.0 * math.pi)
    if abs(off_rear) > ON_LINE_RAD:
        radial = c.scale(offset, 1.0 / distance)
        around = c.perp(radial) if off_rear > 0 else c.scale(c.perp(radial), -1.0)   # the shorter way round
        return c.add(around, c.scale(radial, RADIAL_GAIN * (radius - distance)))
    across = c.perp(travel)
    lateral = offset[0] * across[0] + offset[1] * across[1]
    return c.add(c.unit(c.sub(centre, position)), c.scale(across, -LINE_GAIN * lateral))
