"""The room between the object and the arena's walls that robots need to cage it: the IR cannot tell a wall
from the object. Read before a run (transport_preflight) and during one (transport_metrics)."""
from __future__ import annotations

import math
from typing import Any, List

from .object_hull import CAGE_GAP_M
from .shapes import Geometry, extent_at


def wall_room_needed(spec: Any) -> float:
    """The room robots need between the object and a wall to cage it without caging the wall (see above)."""
    return CAGE_GAP_M + 2.0 * (2.0 * spec.radius_m + spec.proximity_range_m)


def room_to_walls(geometry: Geometry, walls: Any, x: float, y: float, yaw_rad: float) -> float:
    """The gap between the object at (x, y, yaw) and the nearest of the arena walls."""
    xmin, ymin, xmax, ymax = walls
    left, bottom, right, top = extent_at(geometry, x, y, yaw_rad)
    return min(left - xmin, bottom - ymin, xmax - right, ymax - top)


def room_to_walls_warnings(scenario: Any, geometry: Geometry, needed: float) -> List[str]:
    """Robots must get all round the object at its start and at every waypoint without their IR seeing a
    wall: the IR cannot tell a wall from the object, so robots attach to the wall and the cage closes on it."""
    spec = scenario.object
    poses = [("object.position", spec.position[0], spec.position[1], spec.yaw_deg)]
    poses += [(f"path[{i}]", x, y, yaw) for i, (x, y, yaw) in enumerate(scenario.path)]
    close = [(field_name, room_to_walls(geometry, scenario.arena.walls, x, y, math.radians(yaw_deg)))
             for field_name, x, y, yaw_deg in poses]
    close = [(field_name, room) for field_name, room in close if room < needed - 1e-9]
    if not close:
        return []
    (field_name, room), others = close[0], close[1:]
    where = "starts" if field_name == "object.position" else "would be at this waypoint"
    also = "; also " + ", ".join(f"{name} ({gap:.2f} m)" for name, gap in others) if others else ""
    return [f"{field_name}: the object {where} {room:.2f} m from an arena wall{also}. Robots need about "
            f"{needed:.2f} m to cage it (their gap, then a body and the IR's reach for a member and again for the "
            "robot rounding it): their IR cannot tell the wall from the object, so members attach to the wall "
            "and the swarm's estimate of the object is pulled toward it (a 0.5 m box 0.5 m from a wall, pushed "
            "along it: 0 of 3 runs delivered it)"]
