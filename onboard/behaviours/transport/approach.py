"""Where the seed meets the object (option ``seed_from_rear``; not in the paper).

The paper's seed drives straight at the estimated centroid and touches the object wherever it arrives. The
cage then grows left and right from that point, so on a small object caged by three or four robots the
seed's side decides where the pushers end up: a seed that arrived from the side leaves the face that
must be pushed with one robot at its corner, and that robot alone turns the object as it pushes (lab-6:
0.3 rad in three seconds, unseen by the cage, which turns with it). A seed that arrives from behind -- the
side opposite the first waypoint -- sits on the line of travel through the centroid, and so does the
cage's main pusher.

The seed first circles the estimated centroid at ``radius`` until it is behind it, then drives in along the
line of travel. An object larger than ``radius`` is simply met on the way, as in the paper.
"""
from __future__ import annotations

import math

from . import control as c
from .control import Vec

ON_LINE_RAD = 0.25        # within this angle of the rear direction (seen from the centroid) the seed drives in
RADIAL_GAIN = 3.0         # per metre of distance from the circle while circling
LINE_GAIN = 3.0           # per metre of lateral offset from the line of travel while driving in


def seed_heading(position: Vec, centre: Vec, first_waypoint: Vec, radius: float) -> Vec:
    """Direction (not normalised) for a seed at ``position`` to reach the object from behind."""
    travel = c.sub(first_waypoint, centre)
    offset = c.sub(position, centre)
    distance = c.norm(offset)
    if c.norm(travel) < 0.05 or distance < 1e-6:
        return c.sub(centre, position)        # no direction of travel (a pure rotation first): the paper's way
    travel = c.unit(travel)
    rear = math.atan2(-travel[1], -travel[0])
    off_rear = math.remainder(rear - math.atan2(offset[1], offset[0]), 2.0 * math.pi)
    if abs(off_rear) > ON_LINE_RAD:
        radial = c.scale(offset, 1.0 / distance)
        around = c.perp(radial) if off_rear > 0 else c.scale(c.perp(radial), -1.0)   # the shorter way round
        return c.add(around, c.scale(radial, RADIAL_GAIN * (radius - distance)))
    across = c.perp(travel)
    lateral = offset[0] * across[0] + offset[1] * across[1]
    return c.add(c.unit(c.sub(centre, position)), c.scale(across, -LINE_GAIN * lateral))
