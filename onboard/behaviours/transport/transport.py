"""The cage's life after closure: settling, pushing, rotating (before it, caged.py holds the cage).

A mixin of :class:`~.behaviour.Transport`; split out to keep each module readable. Control terms carry the
paper's names: u_fp = u_t + u_f + u_cp (push), u_fr = u_r + u_f + u_cr (rotate).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Dict, List, Optional

import numpy as np

from ...hal import wrap_angle
from . import control as c
from .control import Vec

LOST_CONTACT_READING = 0.3    # below this IR reading (~8 cm) a cage robot has lost touch with the object
# hold_yaw_while_pushing acts only while the push gets somewhere. A cage stalled against a heavy object reads
# its yaw from members shuffling along the faces: on a 4 kg 0.6 m box standing still the edge estimate swung
# +-17 degrees in 8 s, and correcting it turned the box for real, 17.5 degrees in 2 s, after which the cage
# left it behind (behaviour.md section 8). Not in the paper, which has no yaw correction while pushing.
HOLD_YAW_PROGRESS_M = 0.02
HOLD_YAW_STALL_S = 3.0
PACE_AHEAD_M = 0.04   # pace_formation: this far ahead of its formation a non-pushing robot is down to PACE_MIN
PACE_MIN = 0.2
PACE_STOP_M = 0.08    # ... and this far ahead, stopped (it slows from PACE_MIN to 0 in between)
PACE_ANGLE = math.radians(45.0)   # ... a robot whose object lies more than this off its way (not behind it)


@dataclass
class ProgressWatch:
    """How long a distance to a target has not come ``step_m`` nearer on one leg: the stall test that
    hold_yaw_while_pushing (a member, _pushing_on) and reinforce_when_stalled_s (a spare, reinforce.py) share."""

    step_m: float
    leg: Any = None                 # the leg watched (None: none yet)
    since: float = 0.0              # when the distance last came step_m nearer, or the watch restarted
    distance: float = math.inf

    def waited(self, leg: Any, now: float, distance: float) -> float:
        """Seconds since the distance last came step_m nearer on ``leg``: 0 when it just did or the leg is new."""
        if leg != self.leg or distance < self.distance - self.step_m:
            self.restart(leg, now, distance)
        return now - self.since

    def restart(self, leg: Any, now: float, distance: float) -> None:
        self.leg, self.since, self.distance = leg, now, distance

    def clear(self) -> None:
        self.leg = None


class TransportPhases:
    # --- settle: even out the spacing once the ring is closed --------------------------------------------
    def _on_settle(self, now: float) -> None:
        if self._finish_if_done():
            return
        if now - self.closed_at >= self.params.settle_time_s:
            self._begin_transport(now)
            return
        self._hold_position(equalise=self.params.equalise_spacing)

    def _begin_transport(self, now: float) -> None:
        self._start_estimate(now)
        self.formation = self._formation_now()
        self.path = [tuple(w) for w in (self.space.get("path") or self.params.path)]
        self.waypoint, self.phase, self.state = 0, "p", "push"
        self.estimated_at = now
        self.yaw_from_normals = self._yaw_from_contact_normals()   # the path is known from here on
        self.push_watch = ProgressWatch(HOLD_YAW_PROGRESS_M)      # _pushing_on

    def _formation_now(self) -> Dict[int, Vec]:
        """N_f: cage members within k * I_d, as world-frame vectors from this robot."""
        members = set(self.board.members())
        reach = self.params.formation_range_factor * self._spacing()
        return {j: v for j, v in self.percept.neighbours.items() if j in members and c.norm(v) <= reach}

    def _barrier_passed(self, now: float) -> bool:
        live = self._members_alive(now)
        arrived = self.board.arrivals(self.waypoint, self.phase)
        return len(arrived & set(live)) >= self._barrier_needed(len(live))

    def _barrier_needed(self, live: int) -> int:
        """Arrivals that pass a barrier among ``live`` members: ⌈barrier_fraction × live⌉."""
        return math.ceil(self.params.barrier_fraction * live - 1e-9)

    def _object_direction(self, centre: Vec) -> Vec:
        """x_o: from the IR when the object is seen, else toward the estimated centroid."""
        percept = self.percept
        return percept.object_vector if percept.object_peak > 0 else c.sub(centre, percept.position)

    # --- push: u_fp = u_t + u_f + u_cp -------------------------------------------------------------------
    def _on_push(self, now: float) -> None:
        if self._finish_if_done():
            return
        x, y, yaw = self._estimate_object(now)
        p, centre = self.params, (x, y)
        tau = self.path[self.waypoint]
        to_target = c.sub((tau[0], tau[1]), centre)
        remaining = c.norm(to_target)
        if self._waypoint_gate(now, remaining <= p.position_tolerance_m, remaining <= p.push_tolerance_m):
            return
        x_o = self._object_direction(centre)
        self.effective = c.is_effective_pusher(x_o, to_target, math.radians(p.theta_p_deg))
        held_yaw = self._held_yaw()
        term_t = c.u_t(centre, (tau[0], tau[1]), p.k_t_push, p.position_tolerance_m)
        term_f = c.u_f(self.percept.neighbours, self.formation, p.k_f_push, held_yaw - self.reference_yaw)
        if p.keep_contact and not self.percept.in_contact(LOST_CONTACT_READING):
            # Improvement: a robot that lost the object goes back to it instead of running on toward the
            # target or keeping pace with its formation neighbours; a cage that outruns its object (a heavy
            # one that its pushers move slowly) would also drag the centroid estimate ahead of it.
            term_t = term_f = c.ZERO
        term_cp = c.u_cp(x_o, self.effective, p.k_cp_effective, p.k_cp_other)
        if p.soft_side_contact:
            term_cp = c.scale(term_cp, self._side_factor(x_o, to_target))
        u = c.add(term_t, term_f, term_cp)
        if p.hold_yaw_while_pushing and self._pushing_on(now, remaining):
            # Improvement: a pushed object also turns; correct it on the way instead of only at waypoints.
            tolerance = math.radians(p.rotation_tolerance_deg)
            u = c.add(u, c.u_r(self.percept.position, centre, wrap_angle(held_yaw - yaw), p.k_t_push, tolerance))
        speed = self._ramp(remaining)
        sparse = p.pace_formation and self._sparse_cage()       # asked once: it walks the member table
        if p.pace_formation and (sparse or self._small_cage()):
            leg = self._leg()
            if c.norm(leg) > 0 and c.angle_between(x_o, leg) > PACE_ANGLE:
                speed *= self._pace(leg, held_yaw - self.reference_yaw, now, pushers_only=sparse)
        self._drive(u, speed)

    def _pushing_on(self, now: float, remaining: float) -> bool:
        """Whether the push got HOLD_YAW_PROGRESS_M nearer the waypoint (by this robot's estimate) within the
        last HOLD_YAW_STALL_S: hold_yaw_while_pushing corrects the yaw only then."""
        return self.push_watch.waited((self.waypoint, self.phase), now, remaining) < HOLD_YAW_STALL_S

    def _leg(self) -> Vec:
        """The way from the previous waypoint (the start, for the first) to the current one: unlike the way
        from the estimate, it does not swing round when the estimate is within centimetres of the target.
        Zero while returning to the waypoint after a turn (no leg: pacing stays off)."""
        if self.phase == "c":
            return c.ZERO
        start = self.reference_centre if self.waypoint == 0 else self.path[self.waypoint - 1]
        target = self.path[self.waypoint]
        return (target[0] - start[0], target[1] - start[1])

    def _pace(self, leg: Vec, rotation: float, now: float, pushers_only: bool = False) -> float:
        """Improvement for small cages: a robot that does not push (beside or ahead of the object) slows down
        as it gets ahead of its formation neighbours along the leg, down to PACE_MIN of its speed
        PACE_AHEAD_M ahead. At full speed it outruns a heavy object that the pushers move slowly, sliding
        along its faces: the cage's spacing spreads and the ring centroid runs ahead of the object. Large
        cages (surface_estimate_min_points members or more) do not pace: their surface estimate does not
        follow a sliding robot, and pacing 16-18 robots against each other slowed a paper-25 cage with two
        dead members to a crawl and let its estimate fall 0.24 m behind. Only live members that
        touch the object count: a dead robot stays where it stopped, and one that lost the object drives
        back to it (keep_contact), so everyone would seem to run ahead of them.

        ``pushers_only`` (cages of surface_estimate_min_points to 9 members, ours, 2026-11-29): only the
        members that push from behind count (their contact normal within PACE_ANGLE of the leg), as they move
        only as the object does, and only a runaway is held: full speed up to PACE_AHEAD_M ahead of them,
        stopped at PACE_STOP_M. Round a 1.0 x 0.8 m box of 4 kg that its one rear member could not move, the
        side members of an 8-member cage slid round its front corners within seconds, the estimate 0.2 m ahead
        with them, and the runs ended 0.2-0.8 m off (0 of 4; now 4 of 4). Paced as small cages are, against
        all their neighbours (who slide too) and from the first centimetre, a 1 kg box on a zigzag 40 degrees
        off its faces turned 5-9 degrees (7 of 8 runs completed fell to 0 of 8); this way 10 of 16 against
        13 of 16 (docs/behaviour.md section 8)."""
        direction = c.unit(leg)
        leads = []
        live = set(self._members_alive(now))
        for j, r_ref in self.formation.items():
            normal = self.board.contact_normal(j) if j in live else None
            if normal is not None and pushers_only and \
                    c.angle_between((math.cos(normal), math.sin(normal)), leg) > PACE_ANGLE:
                continue        # beside or ahead of the object: it slides as this robot does
            r_now = self.percept.neighbours.get(j) if normal is not None else None
            if r_now is not None:
                error = c.sub(r_now, c.rotate(r_ref, rotation))    # < 0 along the way: j fell behind me
                leads.append(-(error[0] * direction[0] + error[1] * direction[1]))
        if not leads:
            return 1.0
        ahead = sum(leads) / len(leads)
        if pushers_only:        # only a runaway: level with the pushers to a few centimetres, full speed
            return float(np.clip((PACE_STOP_M - ahead) / (PACE_STOP_M - PACE_AHEAD_M), 0.0, 1.0))
        if ahead > PACE_AHEAD_M:
            # Ours: farther ahead it stops altogether, at PACE_STOP_M: crawling on at PACE_MIN beside an object
            # that does not move (too heavy for its pushers) slid the side robots 0.27 m along its faces, and
            # the ring centroid ran 0.12 m ahead of it.
            beyond = (ahead - PACE_AHEAD_M) / (PACE_STOP_M - PACE_AHEAD_M)
            return float(max(0.0, PACE_MIN * (1.0 - beyond)))
        return float(np.clip(1.0 - (1.0 - PACE_MIN) * ahead / PACE_AHEAD_M, PACE_MIN, 1.0))

    @staticmethod
    def _side_factor(x_o: Vec, to_target: Vec) -> float:
        """Improvement: robots beside the object (x_o across the direction of travel) press less hard, so
        that two of them at different heights do not squeeze the object into a spin."""
        return max(0.25, math.cos(c.angle_between(x_o, to_target)))

    def _held_yaw(self) -> float:
        """The yaw the object should keep while pushed toward waypoint k: the one reached at waypoint k-1, or
        waypoint k's own while returning to it after turning there."""
        if self.phase == "c":
            return math.radians(self.path[self.waypoint][2])
        if self.waypoint == 0:
            return self.initial_yaw
        return math.radians(self.path[self.waypoint - 1][2])

    def _ramp(self, remaining: float) -> float:
        radius = self.params.slow_down_radius_m
        return 1.0 if radius <= 0 else float(np.clip(remaining / radius, 0.3, 1.0))

    # --- rotate: u_fr = u_r + u_f + u_cr ------------------------------------------------------------------
    def _on_rotate(self, now: float) -> None:
        if self._finish_if_done():
            return
        x, y, yaw = self._estimate_object(now)
        p, centre = self.params, (x, y)
        # Improvement: arrive with a margin inside the tolerance the waypoint is judged by (the estimate
        # is not the truth); the faithful profile arrives at Orient. tol. itself.
        tolerance = math.radians(p.rotation_tolerance_deg)
        error = wrap_angle(math.radians(self.path[self.waypoint][2]) - yaw)
        if self._waypoint_gate(now, abs(error) <= tolerance, abs(error) <= math.radians(p.orientation_tolerance_deg)):
            return
        x_o = self._object_direction(centre)
        term_r = c.u_r(self.percept.position, centre, error, p.k_r, tolerance)
        self.rotating = c.norm(term_r) > 0
        u = c.add(term_r,
                  c.u_f(self.percept.neighbours, self.formation, p.k_f_rotate, yaw - self.reference_yaw),
                  c.u_cr(x_o, p.k_cr))
        self._drive(u, self._ramp(abs(error) * c.norm(c.sub(self.percept.position, centre))))

    def _waypoint_gate(self, now: float, within: bool, within_paper_tolerance: bool) -> bool:
        """The barrier of the current waypoint and phase: flag arrival, move on once enough live members
        arrived, and hold still meanwhile. True when this robot must not drive this step.

        ``within`` is this robot's estimate inside our tight arrival tolerance. Once half the live members
        arrived and hold still, the few still pushing cannot move the object alone, and their estimates
        (a few millimetres apart from the others' after lost messages) would never get there: a robot then
        also arrives within the paper's own tolerance (d_tol, Orient. tol.), and after ``barrier_stall_s``
        of that whatever its estimate says, so the cage cannot deadlock."""
        arrivals = self.board.arrivals(self.waypoint, self.phase)
        if not within and self.robot.id not in arrivals:
            live = self._members_alive(now)
            held_up = self._held_up_for(now, 2 * len(arrivals & set(live)) >= len(live))
            within = held_up is not None and (within_paper_tolerance or held_up >= self.params.barrier_stall_s)
        if within:
            self.board.arrive(self.waypoint, self.phase, self.robot.id)
        if self._barrier_passed(now):
            self._hold()
            if self.phase == "p":
                self.phase, self.state = "r", "rotate"
            elif self.phase == "r" and self._returns_after_turning(self.path, self.waypoint):
                self.phase, self.state = "c", "push"
            else:
                self._next_waypoint()
            return True
        if self.robot.id in self.board.arrivals(self.waypoint, self.phase):
            self.effective = self.rotating = False
            self._hold()
            return True
        return False

    def _returns_after_turning(self, path: List, k: int) -> bool:
        """Whether waypoint k has the "c" phase (return_after_turning): the path turns the object there."""
        if not self.params.return_after_turning:
            return False
        before = self.initial_yaw if k == 0 else math.radians(path[k - 1][2])
        turn = wrap_angle(math.radians(path[k][2]) - before)
        return abs(turn) > math.radians(self.params.rotation_tolerance_deg)

    def _final_phase(self, path: List, k: int) -> str:
        """The phase whose barrier ends waypoint k."""
        return "c" if self._returns_after_turning(path, k) else "r"

    def _held_up_for(self, now: float, majority_arrived: bool) -> Optional[float]:
        """How long at least half the live members have held still at this barrier while this robot has not
        arrived (None while fewer have)."""
        barrier = (self.waypoint, self.phase)
        if not majority_arrived:
            self.held_up_since = None
            return None
        if self.held_up_since is None or self.held_up_since[0] != barrier:
            self.held_up_since = (barrier, now)
        return now - self.held_up_since[1]

    def _next_waypoint(self) -> None:
        self.rotating = False
        if self.waypoint + 1 >= len(self.path):
            self.space.put("done", 1)
            self.state = "done"
            return
        self.waypoint, self.phase, self.state = self.waypoint + 1, "p", "push"

    def _on_done(self, now: float) -> None:
        self._hold()

    def _members_alive(self, now: float) -> List[int]:
        return [m for m in self.board.members() if m == self.robot.id or self.board.alive(m, now)]
