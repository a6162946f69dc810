"""Where a world's robots start: uniformly at random in ``robots.spawn``, without overlap, clear of the object
and of the walls, each with a random heading (:func:`spawn_poses`, called by :class:`~.world.World` as it is
built, after the object and the walls are in its space)."""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Dict, List, Tuple

import numpy as np
import pymunk

from onboard.config import ConfigError

from .shapes import dimension_field, extent_at

if TYPE_CHECKING:
    from .scenario import Scenario
    from .world import World

# Robots start at least this far clear of the object and of the walls' inner face (the walls are segments of
# the world's wall thickness centred on the arena's edges, so their face lies half a thickness inside).
SPAWN_GAP_M = 0.01
# Random placement jams now and then well before the area is full: 12 robots in lab-6's 0.6 x 0.6 m area,
# which check_spawn_room accepts, jammed in about 15 % of seeds. A jammed try starts again from scratch, up to
# this many times (fewer for thousands of robots, whose tries are slow), before the area counts as too small.
# A seed whose first try places every robot gives the same start as before.
SPAWN_ATTEMPTS = 20
RANDOM_FILL = 0.45          # of the spawn area (check_spawn_room)


def spawn_poses(world: World, rng: np.random.Generator, wall_thickness_m: float) -> List[tuple]:
    """Uniform, non-overlapping (and clear of the object), random heading; a try that jams starts again."""
    scenario = world.scenario
    count = scenario.robots.count
    clearance = 2.0 * world.spec.radius_m + 0.02
    check_spawn_room(scenario, count, clearance)
    blocked = {"other robots": 0, "the object": 0, "the walls": 0}    # why tries failed, for the error
    for _ in range(max(1, min(SPAWN_ATTEMPTS, 2000 // count))):
        placed = _drop_at_random(world, rng, count, clearance, wall_thickness_m, blocked)
        if len(placed) == count or max(blocked, key=blocked.get) != "other robots":
            break
    if len(placed) < count:
        cause = max(blocked, key=blocked.get)
        advice = {"other robots": "make the area larger", "the walls": "move the area off the walls"}.get(cause)
        if advice is None:          # the object: its size may be the typo (centimetres for metres)
            advice = "move the area off the object ({} makes it {:.3g} x {:.3g} m; sizes are in metres)".format(
                dimension_field(scenario.object), *object_span(world))
        raise ConfigError("robots.spawn", f"cannot place {count} robots without overlap in this area "
                          f"(placed {len(placed)}; most tries landed on {cause}): {advice}")
    return placed


def _drop_at_random(world: World, rng: np.random.Generator, count: int, clearance: float,
                    wall_thickness_m: float, blocked: Dict[str, int]) -> List[tuple]:
    """One try at placing every robot: 200 random positions per robot, each kept if it is clear of the robots
    placed before it, of the object and of the walls (counted in ``blocked`` by what it landed on)."""
    scenario, radius = world.scenario, world.spec.radius_m
    spawn = scenario.robots.spawn
    placed: List[tuple] = []
    for _ in range(200 * count):
        if len(placed) == count:
            break
        x, y = rng.uniform(*spawn.x), rng.uniform(*spawn.y)
        if any((x - px) ** 2 + (y - py) ** 2 < clearance ** 2 for px, py, _ in placed):
            blocked["other robots"] += 1
            continue
        if _on_object(world, x, y, radius + SPAWN_GAP_M):
            blocked["the object"] += 1
            continue
        if not _inside_walls(scenario, x, y, radius + wall_thickness_m / 2.0 + SPAWN_GAP_M):
            blocked["the walls"] += 1
            continue
        placed.append((x, y, rng.uniform(-math.pi, math.pi)))
    return placed


def check_spawn_room(scenario: Scenario, count: int, clearance: float) -> None:
    """Refuse at once a spawn area that random placement cannot fill (instead of trying 200 times per
    robot): dropping discs at random jams at about 55 % of the area they may cover in an endless plane
    (random sequential adsorption), far below the 91 % of a hexagonal packing, and sooner in a small area
    with edges. The bar is RANDOM_FILL: up to it spawn_poses placed 6, 12 and 25 robots in a square in every
    one of 100 seeds; at 52 % a third of the seeds failed (and at 54.7 %, the bar before, lab-6's area with
    12 robots, 12 seeds of 100)."""
    spawn = scenario.robots.spawn
    room = (spawn.x[1] - spawn.x[0] + clearance) * (spawn.y[1] - spawn.y[0] + clearance)
    needed = count * math.pi * (clearance / 2.0) ** 2 / RANDOM_FILL
    if count > 1 and needed > room:
        area = (spawn.x[1] - spawn.x[0]) * (spawn.y[1] - spawn.y[0])
        raise ConfigError("robots.spawn", f"{count} robots need about {needed:.3g} m² to be placed at random "
                          f"without overlap; x {list(spawn.x)}, y {list(spawn.y)} is {area:.3g} m² "
                          f"({room:.3g} m² with a robot's width round it): make the area larger")


def object_span(world: World) -> Tuple[float, float]:
    """The object's width and height (m) along x and y at its starting yaw."""
    yaw = math.radians(world.scenario.object.yaw_deg)
    left, bottom, right, top = extent_at(world.geometry, 0.0, 0.0, yaw)
    return right - left, top - bottom


def _on_object(world: World, x: float, y: float, distance: float) -> bool:
    """Whether the object lies within ``distance`` of (x, y). The space holds the walls too: counting them
    here said `most tries landed on the object` of a spawn area that lay on a wall."""
    if world.object_body is None:
        return False
    hits = world.space.point_query((x, y), distance, pymunk.ShapeFilter())
    return any(hit.shape.body is world.object_body for hit in hits if hit.shape is not None)


def _inside_walls(scenario: Scenario, x: float, y: float, margin: float) -> bool:
    walls = scenario.arena.walls
    if walls is None:
        return True
    xmin, ymin, xmax, ymax = walls
    return xmin + margin < x < xmax - margin and ymin + margin < y < ymax - margin
