"""What a robot makes of its raw sensors each step: its pose, its neighbours in the world frame, and
which IR readings are the object (not a neighbouring robot)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, List, Optional

from ...hal import Neighbour, ProximityReading, wrap_angle
from .control import ZERO, Vec, rotate

# A reading is a neighbouring robot, not the object, when a neighbour lies within this range and bearing
# of the sensor's direction (the authors' check: 0.3 m and 0.5 rad).
ROBOT_ECHO_RANGE_M = 0.3
ROBOT_ECHO_BEARING_RAD = 0.5
# Readings below this are sensor noise and ambient light, not an obstacle (~11 cm on the ARGoS curve).
DETECTION_FLOOR = 0.05


@dataclass
class Percept:
    x: float
    y: float
    yaw: float
    neighbours: Dict[int, Vec]          # world-frame vector from this robot to each neighbour
    object_vector: Vec                  # x_o in the world frame (sum of object readings as vectors)
    object_peak: float                  # strongest object reading
    obstacle_vector: Vec                # every reading (object, robots, walls) as a world vector

    @property
    def position(self) -> Vec:
        return (self.x, self.y)

    def in_contact(self, threshold: float) -> bool:
        return self.object_peak >= threshold


def perceive(x: float, y: float, yaw: float, neighbours: List[Neighbour],
             reading: ProximityReading) -> Percept:
    world_neighbours = {n.id: rotate((n.x, n.y), yaw) for n in neighbours}
    ox = oy = ax = ay = 0.0
    peak = 0.0
    for value, angle in zip(reading.values, reading.angles_rad):
        if value < DETECTION_FLOOR:
            continue
        direction = angle + yaw
        ax += value * math.cos(direction)
        ay += value * math.sin(direction)
        if _is_robot_echo(angle, neighbours):
            continue
        ox += value * math.cos(direction)
        oy += value * math.sin(direction)
        peak = max(peak, value)
    object_vector = (ox, oy) if peak > 0.0 else ZERO
    return Percept(x, y, yaw, world_neighbours, object_vector, peak, (ax, ay))


def _is_robot_echo(sensor_angle: float, neighbours: List[Neighbour]) -> bool:
    for n in neighbours:
        if n.range_m <= ROBOT_ECHO_RANGE_M and abs(wrap_angle(n.bearing_rad - sensor_angle)) <= ROBOT_ECHO_BEARING_RAD:
            return True
    return False


def world_to_robot(v: Vec, yaw: float) -> Vec:
    return rotate(v, -yaw)


def nearest(neighbours: Dict[int, Vec], among: Optional[set] = None) -> Optional[int]:
    best, best_d = None, math.inf
    for j, v in neighbours.items():
        if among is not None and j not in among:
            continue
        d = math.hypot(*v)
        if d < best_d:
            best, best_d = j, d
    return best
