"""``aggregate``: robots gather using range-and-bearing only and avoid each other with IR.

The smallest useful behaviour, written against the HAL only; read it as the template for your own.
Each step a robot computes, in its own frame,

    u = K_agg * (mean neighbour position) - K_avoid * (IR proximity vector)

and drives along u. Robots with no neighbour in range wander straight on. Close enough to the local
centroid (``gather_distance_m``) the attraction is switched off, so the group settles instead of piling up.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Dict

from ..behaviour import Behaviour, register
from ..config import check_range
from ..hal import Neighbours
from ..motion import proximity_vector, vector_to_wheels


@dataclass
class AggregateParams:
    speed_m_s: float = 0.15           # cruise speed; well inside the KheperaIV's 0.81 m/s
    gather_distance_m: float = 0.25   # stop approaching once the neighbours' centroid is this close
    k_aggregate: float = 1.0          # weight of the attraction to the neighbours' centroid (1/m)
    k_avoid: float = 2.0              # weight of the IR repulsion
    turn_gain: float = 2.0            # rad/s per rad of heading error

    def validate(self, where: str) -> None:
        check_range(f"{where}.speed_m_s", self.speed_m_s, 0.0, low_open=True)
        check_range(f"{where}.gather_distance_m", self.gather_distance_m, 0.0)
        check_range(f"{where}.turn_gain", self.turn_gain, 0.0, low_open=True)


@register("aggregate")
class Aggregate(Behaviour):
    Params = AggregateParams

    def step(self) -> None:
        p = self.params
        neighbours = Neighbours.of(self.robot.range_and_bearing.neighbours())
        ux, uy = 0.0, 0.0
        if neighbours:
            xs, ys = neighbours.xy.tolist()      # all neighbours' x and y at once, no record per neighbour
            cx = sum(xs) / len(xs)
            cy = sum(ys) / len(ys)
            if math.hypot(cx, cy) > p.gather_distance_m:
                ux, uy = p.k_aggregate * cx, p.k_aggregate * cy
                self.state = "gathering"
            else:
                self.state = "gathered"
        else:
            ux, uy = 1.0, 0.0
            self.state = "searching"
        reading = self.robot.proximity.read()
        ox, oy = proximity_vector(reading.values, reading.angles_rad)
        ux -= p.k_avoid * ox
        uy -= p.k_avoid * oy
        left, right = vector_to_wheels(ux, uy, p.speed_m_s, self.robot.spec.wheel_base_m, p.turn_gain)
        self.robot.wheels.set_speeds(left, right)

    def telemetry(self) -> Dict[str, Any]:
        return {"state": self.state}
