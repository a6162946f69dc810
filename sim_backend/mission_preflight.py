"""Before a run: a path or faults that ask for less than the user likely meant, said up front as warnings.

These read only the scenario (not the object's shape or the behaviour's mechanics), so any behaviour that follows
a path or is given faults can use them; ``transport_preflight`` adds what the transport's cage makes of them.
"""
from __future__ import annotations

import math
from typing import Any, List

SAME_PLACE_M, SAME_YAW_DEG = 1e-3, 0.5     # a waypoint this close to the one before, in both, asks for nothing


def mission_warnings(scenario: Any, params: Any) -> List[str]:
    return (_fault_times(scenario) + _waypoints_already_there(scenario) + _tolerance_covers_legs(scenario, params)
            + _radians_for_degrees(scenario))


def judges_yaw(obj: Any) -> bool:
    """Whether a run is judged on the object's yaw. A disc looks the same at every yaw, and nothing a robot
    senses can tell how it turned: its orientation is reported but not judged, so a turn asked of it is no
    risk to warn about."""
    return obj is None or obj.shape != "circle"


def _fault_times(scenario: Any) -> List[str]:
    """Faults that never happen within the run, and restarts that never come back within it."""
    limit = scenario.time_limit_s
    found = [f"faults[{i}].at_s: {fault.at_s:g} s is not before the time limit ({limit:g} s): "
             f"robot {fault.robot} never {'fails' if fault.restart_after_s is None else 'restarts'}"
             for i, fault in enumerate(scenario.faults) if fault.at_s >= limit]
    found += [f"faults[{i}].restart_after_s: robot {fault.robot}'s agent is down from {fault.at_s:g} s to past the "
              f"time limit ({limit:g} s), so it never comes back; leave restart_after_s out for a robot that "
              "fails for good"
              for i, fault in enumerate(scenario.faults)
              if fault.restart_after_s is not None and fault.at_s < limit <= fault.at_s + fault.restart_after_s]
    return found


def _waypoints_already_there(scenario: Any) -> List[str]:
    """A waypoint the object stands on already, yaw and all (the object's start written as the path, or a line
    copied twice; a disc's yaw is not judged): it is counted reached as soon as the cage stands, and nothing
    moves for it."""
    if scenario.object is None:
        return []
    found, before, where = [], (*scenario.object.position, scenario.object.yaw_deg), "the object's start"
    for i, waypoint in enumerate(scenario.path):
        if (math.hypot(waypoint[0] - before[0], waypoint[1] - before[1]) < SAME_PLACE_M
                and (abs(wrap_deg(waypoint[2] - before[2])) < SAME_YAW_DEG or not judges_yaw(scenario.object))):
            found.append(f"path[{i}]: it is {where}, yaw and all: the object is there already, so it counts as "
                         "reached at once and nothing is pushed or turned for it")
        before, where = waypoint, f"path[{i}] again"
    return found


def _tolerance_covers_legs(scenario: Any, params: Any) -> List[str]:
    """A waypoint position tolerance as long as the leg to it: the object is "at" the waypoint where the leg
    starts (push_tolerance_m 2 with 0.3 m legs: completed, 0.9 m from the goal, nobody having pushed)."""
    tolerance = getattr(params, "push_tolerance_m", None)
    if tolerance is None or scenario.object is None or not scenario.path:
        return []
    start = tuple(scenario.object.position)
    for i, waypoint in enumerate(scenario.path):
        leg = math.hypot(waypoint[0] - start[0], waypoint[1] - start[1])
        start = (waypoint[0], waypoint[1])
        if leg > 0.0 and tolerance >= leg:       # a turn in place (no leg) is judged by its yaw
            return [f"params.push_tolerance_m: {tolerance:g} m is as long as the leg to path[{i}] ({leg:.2f} m) or "
                    "longer: the object counts as at that waypoint before it has moved, so `completed` and the "
                    "position errors say nothing of the push. Keep it well under the legs (default 0.1 m)"]
    return []


def _radians_for_degrees(scenario: Any) -> List[str]:
    """A yaw of 3.14 or 1.57 is almost surely radians where degrees are asked for: a turn of 3 degrees, not a
    half turn, that the run would carry out without a word."""
    yaws = [(f"path[{i}]", wyaw) for i, (_, _, wyaw) in enumerate(scenario.path)]
    if scenario.object is not None:
        yaws.insert(0, ("object.yaw_deg", scenario.object.yaw_deg))
    found = []
    for field_name, value in yaws:
        quarters = value / (math.pi / 2.0)
        if value != 0.0 and abs(value) <= 2.0 * math.pi + 0.01 and abs(quarters - round(quarters)) * math.pi / 2 < 0.01:
            what = "its yaw" if field_name.startswith("path") else "it"
            found.append(f"{field_name}: {what} is in degrees, and {value:g} looks like radians "
                         f"({math.degrees(value):.0f} degrees); write {math.degrees(value):.0f} if that is meant")
    return found


def wrap_deg(angle: float) -> float:
    return (angle + 180.0) % 360.0 - 180.0
