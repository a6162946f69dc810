"""Ground-truth metrics for the ``transport`` behaviour (result.json), measured outside the behaviour.

A waypoint counts as reached when the cage's barrier for it completes (push and rotate); errors are then
measured against the simulator's true object pose, which the robots never see.
"""
from __future__ import annotations

import math
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from onboard.behaviours.transport.params import TransportParams
from onboard.hal import wrap_angle

from .metrics import Evaluator, register_evaluator, waypoint_error
from .transport_preflight import floor_friction_n, judges_yaw, push_force_n, transport_warnings
from .wall_room import room_to_walls, wall_room_needed

SPACING_SAMPLE_PERIOD_S = 1.0
STUCK_BELOW_M = 0.05            # a closed cage that moved the object less than this got nowhere
# A push is judged stuck only when the run went on this long after the cage settled (the stall detection's own
# window, reinforce_when_stalled_s): a run stopped sooner (a short --time-limit) did not get to push.
PUSH_JUDGED_AFTER_S = 15.0
# Progress toward the next waypoint: its distance this much shorter, or its yaw error this much smaller, than
# the best so far. An object still making progress when the time limit came was not stuck, however little it
# had moved (a turn in place moves it not at all).
PROGRESS_M = 0.01
PROGRESS_RAD = math.radians(1.0)
# A cage that did not close by the time limit was still forming when a robot joined it this recently, or within
# twice the run's mean time between joins (a 100-robot cage takes a minute or more per member).
CAGING_PROGRESS_S = 60.0
CAGING_STATES = ("seed", "travel", "attach")    # robots on their way to the object or attaching to it
CAGE_STATES = ("caged", "settle", "push", "rotate", "done")


@register_evaluator("transport")
class TransportEvaluator(Evaluator):
    def __init__(self, scenario, world):
        super().__init__(scenario, world)
        self.closed_at: Optional[float] = None
        self.pose_at_closure: Optional[np.ndarray] = None
        self.gap_at_closure_rad: Optional[float] = None   # the members' widest gap round the true centroid
        self.members: List[int] = []
        self.reached: Dict[int, Dict[str, Any]] = {}
        self.pushers: Dict[int, List[int]] = {}
        self.rotators: Dict[int, List[int]] = {}
        self.spacings: List[float] = []
        self.phase_steps: Dict[tuple, int] = {}      # (phase, waypoint) -> control steps spent in it
        self.next_spacing_sample = 0.0
        self.last_time = 0.0
        self.best_toward: Tuple[int, float, float] = (-1, math.inf, math.inf)   # waypoint, distance, yaw error
        self.progress_at: Optional[float] = None      # when the object last got nearer its next waypoint
        self.joined_at: List[float] = []              # before closure: each time the cage gained members
        self.caging_members = self.caging_busy = 0    # before closure: members, and robots caging (CAGING_STATES)

    def warnings(self, params: Any) -> List[str]:
        return transport_warnings(self.scenario, self.world, params)

    def on_step(self, time_s: float, telemetry: List[Optional[Dict[str, Any]]]) -> None:
        self.last_time = time_s
        reports = {i: t for i, t in enumerate(telemetry) if t is not None}
        if self.closed_at is None:
            if any(t.get("closed") for t in reports.values()):
                self.closed_at = time_s
                self.pose_at_closure = self.world.object_pose()
                positions = self.world.robot_poses()[:, :2]
                members = [positions[i] for i, t in reports.items() if t.get("member")]
                self.gap_at_closure_rad = widest_gap_rad(members, self.pose_at_closure[:2])
            else:
                self._note_caging(time_s, reports)
            return
        members = [i for i, t in reports.items() if t["state"] in CAGE_STATES and t.get("member")]
        self.members = members or self.members
        live = [i for i in self.members if i in reports]
        transporting = [i for i in live if reports[i]["state"] in ("push", "rotate")]
        for i in transporting:
            t = reports[i]
            if t["state"] == "push" and t.get("effective"):
                self.pushers.setdefault(t["waypoint"], []).append(i)
            elif t["state"] == "rotate" and t.get("rotating"):
                self.rotators.setdefault(t["waypoint"], []).append(i)
        self._count_steps(transporting, reports)
        self._check_waypoints(time_s, live, reports)
        self._note_progress(time_s)
        if transporting and time_s >= self.next_spacing_sample:
            self.next_spacing_sample = time_s + SPACING_SAMPLE_PERIOD_S
            self.spacings.extend(self._adjacent_distances(live))

    def _note_caging(self, time_s: float, reports: Dict[int, Dict[str, Any]]) -> None:
        members = sum(1 for t in reports.values() if t.get("member"))
        if members > self.caging_members:
            self.joined_at.append(time_s)
        self.caging_members = members
        self.caging_busy = sum(1 for t in reports.values() if t.get("state") in CAGING_STATES)

    def _not_caged_hint(self) -> List[str]:
        """How far the cage got by the time limit, and whether it was still forming: a short time limit was
        said in the same words as a cage that could not close ("cage did not close")."""
        limit_s = self.scenario.time_limit_s
        if self.last_time + 2.0 / self.scenario.physics.control_hz < limit_s:   # stopped early: stop_reason says why
            return []
        members, busy, joins = self.caging_members, self.caging_busy, self.joined_at
        bidding_s = float(self.scenario.params.get("allocation_time_s", TransportParams.allocation_time_s))
        if not joins and not busy and self.last_time <= 2.0 * bidding_s:
            return [f"by its {limit_s:g} s time limit the robots were still bidding for the first place in the "
                    f"cage (params.allocation_time_s, {bidding_s:g} s): give it a longer time limit (time_limit_s, "
                    "--time-limit)"]
        text = f"by its {limit_s:g} s time limit {members} robot{'' if members == 1 else 's'} had joined the cage"
        if joins:
            text += f", the last {self.last_time - joins[-1]:.0f} s before the end"
        if busy:
            text += f", and {busy} {'was' if busy == 1 else 'were'} on the way to the object or attaching"
        window = max(CAGING_PROGRESS_S, 2.0 * joins[-1] / len(joins)) if joins else CAGING_PROGRESS_S
        if busy and (not joins or self.last_time - joins[-1] <= window):
            text += ": the cage was still forming, give it a longer time limit (time_limit_s, --time-limit)"
        return [text]

    def _note_progress(self, time_s: float) -> None:
        k = len(self.reached)
        if not self.scenario.path or k >= len(self.scenario.path):
            return
        distance, yaw_error = waypoint_error(self.world.object_pose(), self.scenario.path[k])
        index, best_distance, best_yaw = self.best_toward
        if index != k or distance < best_distance - PROGRESS_M or yaw_error < best_yaw - PROGRESS_RAD:
            self.best_toward, self.progress_at = (k, distance, yaw_error), time_s

    def _count_steps(self, transporting: List[int], reports: Dict[int, Dict[str, Any]]) -> None:
        # Per waypoint and phase, how many control steps were spent (to average the robot counts).
        for phase in ("push", "rotate"):
            waypoints = {reports[i]["waypoint"] for i in transporting if reports[i]["state"] == phase}
            for wp in waypoints:
                self.phase_steps[(phase, wp)] = self.phase_steps.get((phase, wp), 0) + 1

    def _check_waypoints(self, time_s: float, live: List[int], reports: Dict[int, Dict[str, Any]]) -> None:
        if not live or not self.scenario.path:
            return
        # Waypoint k is reached once most live members have moved past it (the barrier completed).
        progress = sorted(reports[i]["waypoint"] + (1 if reports[i]["state"] == "done" else 0) for i in live)
        passed = progress[len(progress) // 2]
        for k in range(min(passed, len(self.scenario.path))):
            if k not in self.reached:
                self.reached[k] = self._errors_now(k, time_s, live, reports)

    def _errors_now(self, k: int, time_s: float, live: List[int], reports: Dict[int, Dict[str, Any]]) -> Dict[str, Any]:
        truth = self.world.object_pose()
        target = self.scenario.path[k]
        estimates = [reports[i]["estimate"] for i in live if "estimate" in reports[i]]
        est_error = float(np.mean([math.hypot(e[0] - truth[0], e[1] - truth[1]) for e in estimates])) \
            if estimates else None
        yaw_error = float(np.mean([abs(wrap_angle(e[2] - truth[2])) for e in estimates])) if estimates else None
        steps = self.phase_steps
        position_error, orientation_error = waypoint_error(truth, target)
        return {
            "index": k,
            "reached_s": round(time_s, 2),
            "position_error_m": position_error,
            "orientation_error_rad": orientation_error,
            "centroid_estimation_error_m": est_error,
            "yaw_estimation_error_rad": yaw_error,
            "effective_pushers": round(len(self.pushers.get(k, [])) / max(1, steps.get(("push", k), 1)), 2),
            "effective_rotators": round(len(self.rotators.get(k, [])) / max(1, steps.get(("rotate", k), 1)), 2),
        }

    def waypoints_reached(self) -> Optional[int]:
        return len(self.reached) if self.scenario.path else None

    def _adjacent_distances(self, live: List[int]) -> List[float]:
        """Distances between neighbours around the cage, in angular order about the true centroid."""
        if len(live) < 2:
            return []
        poses = self.world.robot_poses()[live, :2]
        centre = self.world.object_pose()[:2]
        order = np.argsort(np.arctan2(poses[:, 1] - centre[1], poses[:, 0] - centre[0]))
        ring = poses[order]
        return np.hypot(*(np.roll(ring, -1, axis=0) - ring).T).tolist()

    def centroid_estimate(self, telemetry: List[Optional[Dict[str, Any]]]) -> np.ndarray:
        poses = [t["estimate"][:2] for t in telemetry if t is not None and "estimate" in t]
        return np.mean(poses, axis=0) if poses else np.array([np.nan, np.nan])

    def _too_soon_hint(self) -> List[str]:
        """A run that ended soon after its cage closed (a short time limit) had no time to push: said instead of
        the stuck hint, which would blame the floor friction for an object the cage never got to push."""
        params = self.scenario.params
        faithful = params.get("profile") == "faithful"
        settle_s = 0.0 if faithful else float(params.get("settle_time_s", TransportParams.settle_time_s))
        after_s = self.last_time - self.closed_at
        if after_s >= settle_s + PUSH_JUDGED_AFTER_S:
            return []
        limit_s = self.scenario.time_limit_s
        if self.last_time + 2.0 / self.scenario.physics.control_hz < limit_s:   # crashed, killed, stopped
            return [f"the run ended {after_s:.1f} s after the cage closed, at {self.last_time:.1f} s of its "
                    f"{limit_s:g} s time limit (see its stop_reason): the push was not judged"]
        settle = f" (the cage settles for {settle_s:g} s before it pushes)" if settle_s > 0 else ""
        return [f"the run ended {after_s:.1f} s after the cage closed{settle}, too soon to judge the push: "
                f"give it a longer time limit (time_limit_s, --time-limit)"]

    def _still_going_hint(self, truth: np.ndarray) -> List[str]:
        """An object still getting nearer its next waypoint when the time limit came: the run was short, not
        stuck (a box turned 171° of a 180° turn in place was said to be held by floor friction)."""
        if self.progress_at is None or self.last_time - self.progress_at >= PUSH_JUDGED_AFTER_S:
            return []
        if self.last_time + 2.0 / self.scenario.physics.control_hz < self.scenario.time_limit_s:
            return []       # stopped early: its stop_reason says why
        k = len(self.reached)
        distance, yaw_error = waypoint_error(truth, self.scenario.path[k])
        return [f"the object was still on its way when the run reached its {self.scenario.time_limit_s:g} s time "
                f"limit ({distance:.2f} m and {math.degrees(yaw_error):.0f}° from waypoint {k + 1}, nearer "
                f"{self.last_time - self.progress_at:.0f} s before the end): give it a longer time limit "
                "(time_limit_s, --time-limit)"]

    def _turn_hint(self, truth: np.ndarray, d_tol: float, yaw_tol: float) -> List[str]:
        """An object that stands at its next waypoint but not at its yaw: the turn is what failed, which floor
        friction against the pushers does not explain (u_r and u_cr turn it, after the push). The tolerances are
        result()'s (``yaw_tol`` infinite for an object whose yaw is not judged)."""
        params = self.scenario.params
        k = len(self.reached)
        distance, yaw_error = waypoint_error(truth, self.scenario.path[k])
        if distance > d_tol or yaw_error <= yaw_tol:
            return []
        turned = abs(wrap_angle(truth[2] - self.pose_at_closure[2])) if self.pose_at_closure is not None else 0.0
        off = [name for name in ("k_r", "k_cr") if float(params.get(name, 1.0)) == 0.0]
        why = (f"{' and '.join('params.' + name for name in off)} {'is' if len(off) == 1 else 'are'} 0" if off else
               f"{len(self.members)} members turning it against its floor friction: more robots or less friction")
        return [f"the object stands {distance:.2f} m from waypoint {k + 1} but {math.degrees(yaw_error):.0f}° off "
                f"its yaw, having turned {math.degrees(turned):.0f}° since the cage closed; the members turn it "
                f"with u_r and u_cr (params.k_r, params.k_cr): {why}"]

    def _stuck_hint(self, truth: np.ndarray) -> List[str]:
        """Why a closed cage may not have got anywhere: said when the object hardly moved after closure."""
        start = self.pose_at_closure
        moved = math.inf if start is None else math.hypot(truth[0] - start[0], truth[1] - start[1])
        if moved >= STUCK_BELOW_M:
            return []
        near_wall = self._wall_hint(truth, moved)
        if near_wall:
            return near_wall
        spec, robots = self.scenario.object, self.scenario.robots
        resisting = floor_friction_n(spec)
        everyone = robots.count * push_force_n(robots)
        hint = (f"the object moved {moved:.2f} m after the cage closed: {len(self.members)} members against "
                f"{resisting:.1f} N of floor friction (object.friction x mass x g)")
        if resisting > everyone:        # then the robots left out would not help either
            return [hint + f"; all {robots.count} robots together push at most {everyone:.1f} N (robots.traction "
                           "x robots.mass_kg x g each): more robots, a lighter object or less friction"]
        # A denser cage has more members behind the object: a 4 kg 0.6 m box that 6 members (I_d 0.45 m) could
        # not move was delivered by 10 (I_d 0.3 m) in 4 of 4 runs (behaviour.md section 8).
        hint += "; more robots, less friction, a smaller params.inter_robot_distance_m (more members behind it)"
        params = self.scenario.params
        stall_s = float(params.get("reinforce_when_stalled_s", TransportParams.reinforce_when_stalled_s))
        if params.get("reinforce_push", False) or len(self.members) >= robots.count:
            return [hint]       # every robot is a member: nobody was left out to push too
        if params.get("profile") != "faithful" and stall_s > 0:
            return [hint + f" (the robots left out pushed too once the push stalled for {stall_s:g} s)"]
        return [hint + ", or params: {reinforce_push: true} (the robots left out push too)"]

    def _wall_hint(self, truth: np.ndarray, moved: float) -> List[str]:
        """A stuck object next to a wall: members likely caged the wall too, which floor friction does not
        explain (a 0.4 kg box 0.4 m from a wall was said to be held by 1.2 N of friction)."""
        walls = self.scenario.arena.walls
        if walls is None or self.world.geometry is None:
            return []
        geometry = self.world.geometry
        room = room_to_walls(geometry, walls, float(truth[0]), float(truth[1]), float(truth[2]))
        needed = wall_room_needed(self.world.spec)
        if room >= needed:
            return []
        return [f"the object moved {moved:.2f} m after the cage closed, {room:.2f} m from an arena wall where "
                f"robots need about {needed:.2f} m to get round it: members likely caged the wall too (their IR "
                "cannot tell it from the object). Start the object and its path farther from the walls"]

    def result(self) -> Dict[str, Any]:
        scenario = self.scenario
        params = scenario.params
        d_tol = float(params.get("push_tolerance_m", 0.1))
        yaw_tol = math.radians(float(params.get("orientation_tolerance_deg", 5.72)))
        caged = self.closed_at is not None
        # Rounded as reached_s is: a sum of 0.1 s steps gave 62.300000000000004 in result.json.
        closed = None if self.closed_at is None else round(self.closed_at, 2)
        out: Dict[str, Any] = {"caged": caged, "time_to_cage_s": closed, "cage_size": len(self.members)}
        failures = [] if caged else ["cage did not close", *self._not_caged_hint()]
        # The swarm decides closure from what it senses; the truth may differ (a ring on one side of the object).
        encloses = None if self.gap_at_closure_rad is None else self.gap_at_closure_rad < math.pi
        out["cage_encloses_object"] = encloses
        if encloses is False:
            failures.append(f"the cage closed without enclosing the object: seen from its true centroid, the "
                            f"members left a gap of {math.degrees(self.gap_at_closure_rad):.0f}° (all on one side)")
        dead = [f.describe() for f in scenario.faults if f.at_s <= self.last_time]
        if scenario.path:
            waypoints = [self.reached[k] for k in sorted(self.reached)]
            done = len(waypoints) == len(scenario.path)
            judge_yaw = judges_yaw(scenario.object)     # not a disc's
            judged_yaw_tol = yaw_tol if judge_yaw else math.inf
            within = all(w["position_error_m"] <= d_tol and (not judge_yaw or w["orientation_error_rad"] <= yaw_tol)
                         for w in waypoints)
            truth = self.world.object_pose()
            final_position_error, final_orientation_error = waypoint_error(truth, scenario.path[-1])
            out.update({
                "completed": bool(caged and done and within),
                "time_to_complete_s": round(waypoints[-1]["reached_s"] - self.closed_at, 2) if done and caged else None,
                "waypoints": waypoints,
                "final_position_error_m": final_position_error,
                "final_orientation_error_rad": final_orientation_error,
                "cage_spacing_m": {"mean": float(np.mean(self.spacings)) if self.spacings else None,
                                   "std": float(np.std(self.spacings)) if self.spacings else None},
            })
            if caged and not done:
                failures.append(f"reached {len(waypoints)} of {len(scenario.path)} waypoints")
                failures.extend(self._too_soon_hint() or self._still_going_hint(truth)
                                or self._turn_hint(truth, d_tol, judged_yaw_tol)
                                or self._stuck_hint(truth))
            failures.extend(self._outside_tolerance(waypoints, d_tol, judged_yaw_tol))
        out["failures"] = failures
        out["faults_fired"] = dead          # not failures: a run that loses a robot may still complete
        return out

    @staticmethod
    def _outside_tolerance(waypoints: List[Dict[str, Any]], d_tol: float, yaw_tol: float) -> List[str]:
        """One line per waypoint the swarm passed (by its own estimate) with the object outside tolerance."""
        lines = []
        for w in waypoints:
            off = []
            if w["position_error_m"] > d_tol:
                error, tolerance = beyond_tolerance(w["position_error_m"], d_tol, 2, 2)
                off.append(f"{error} m from it (tolerance {tolerance} m)")
            if w["orientation_error_rad"] > yaw_tol:
                error, tolerance = beyond_tolerance(math.degrees(w["orientation_error_rad"]),
                                                    math.degrees(yaw_tol), 1, 2)
                off.append(f"{error}° off its yaw (tolerance {tolerance}°)")
            if off:
                estimate, yaw_estimate = w.get("centroid_estimation_error_m"), w.get("yaw_estimation_error_rad")
                known = "" if estimate is None else f"; the swarm's centroid estimate was {estimate:.2f} m off"
                if known and yaw_estimate is not None and w["orientation_error_rad"] > yaw_tol:
                    # Why nobody corrected the turn: the cage believed the object had kept its yaw.
                    known += f" and its yaw estimate {math.degrees(yaw_estimate):.1f}° off"
                lines.append(f"waypoint {w['index'] + 1} was passed with the object {' and '.join(off)}{known}")
        return lines


def beyond_tolerance(value: float, tolerance: float, value_decimals: int,
                     tolerance_decimals: int) -> Tuple[str, str]:
    """``value`` and the ``tolerance`` it exceeds, as text that reads above it: with more decimals where the
    usual ones round the two together ("0.10 m from it (tolerance 0.10 m)" was 0.104 against 0.100)."""
    text = f"{value:.{value_decimals}f}", f"{tolerance:.{tolerance_decimals}f}"
    decimals = max(value_decimals, tolerance_decimals)
    while float(text[0]) <= float(text[1]) and decimals <= MAX_TOLERANCE_DECIMALS:
        text = f"{value:.{decimals}f}", f"{tolerance:.{decimals}f}"
        decimals += 1
    return text


MAX_TOLERANCE_DECIMALS = 9      # beyond, the value is over its tolerance by float noise only


def widest_gap_rad(points: List[np.ndarray], centre: np.ndarray) -> float:
    """The widest angle between neighbouring points as seen from ``centre``: below pi exactly when the points
    surround it (it lies inside their convex hull). 2 pi for fewer than 2 points."""
    if len(points) < 2:
        return 2.0 * math.pi
    angles = sorted(math.atan2(float(p[1] - centre[1]), float(p[0] - centre[0])) for p in points)
    gaps = [b - a for a, b in zip(angles, angles[1:])]
    gaps.append(angles[0] + 2.0 * math.pi - angles[-1])
    return max(gaps)
