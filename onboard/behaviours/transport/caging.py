"""Sequential caging: the seed, travelling to a branch target, attaching beside the predecessor and opening the
next target. Closing the ring (Proposition 1) is in closure.py.

A mixin of :class:`~.behaviour.Transport`, like :class:`~.transport.TransportPhases`; split out to keep each
module readable. See docs/behaviour.md sections 2 and 3.
"""
from __future__ import annotations

import math

from . import control as c
from .approach import first_travel, seed_heading
from .caged import GAP_GAIN, GAP_READING
from .control import Vec
from .perception import nearest
from .tasks import BRANCH_DIRECTION, Task, distance, task_id

SETTLE_STEPS = 10          # a caging robot must hold its place this many steps to count as settled
# ... or, with readings too noisy for that, hold it this many steps with a mean error within half d_tol and
# without moving more than d_tol (_settled_on_average).
AVERAGE_SETTLE_STEPS = 20
# An attaching robot that touches the object and faces it (within FACING_OBJECT_COS, 60 degrees) turns on the
# spot until it heads within TURN_ON_SPOT_RAD (about 29 degrees) of where it slides (_attach_turn_gate).
FACING_OBJECT_COS = 0.5
TURN_ON_SPOT_RAD = 0.5
ATTACH_RADIUS_M = 0.25     # switch from travelling to attaching this close to the target
# ... or already touching the object this close to it (a target estimated inside the object is unreachable).
TOUCH_ATTACH_RADIUS_M = 0.6
# ... or stuck this close to it: no 2 cm of progress for this long (a target estimated inside a concave
# object, or behind a member that blocks the way, is unreachable; attaching slides along the surface instead).
STALL_ATTACH_S = 20.0
PROGRESS_STEP_M = 0.02
# A seed that has not moved PROGRESS_STEP_M for this long while its IR sees the object is wedged (_seed_wedged).
SEED_WEDGED_S = 10.0
# A predecessor this far (cosine) round the object on the wrong side: slide toward it, not the branch's way.
WRONG_SIDE_COS = 0.5
# travel_speed_m_s applies farther than travel_fast_beyond_m from the target and eases down to the cruise speed
# over the next TRAVEL_EASE_FRACTION of that distance (at most TRAVEL_EASE_M), so a robot reaches its target and
# the members next to it at the cruise speed.
TRAVEL_EASE_FRACTION = 0.4
TRAVEL_EASE_M = 1.0
# head_start: the presumptive winner of a branch target stops this far from it until it owns it.
HEAD_START_STOP_M = 0.6
# An attaching robot that drove SHOVE_ADVANCE_M toward the object while its IR saw it, without touching it
# (reading >= proximity_threshold, about 5 cm off), is shoving it (_shoving); SHOVE_LOST_S without seeing the
# object ends that.
SHOVE_ADVANCE_M = 0.12
SHOVE_LOST_S = 1.0
# An attaching robot whose distance error to its predecessor has grown this many I_d past the smallest it had
# while touching the object is sliding the wrong way round it (_sliding_the_wrong_way).
WRONG_WAY_SPACINGS = 1.0


class CagingPhases:
    # --- seed: drive to the estimated centroid (improved: from behind it) until the IR sees the object -------
    def _on_seed(self, now: float) -> None:
        if not self._still_mine():
            return
        percept, p = self.percept, self.params
        if percept.in_contact(p.proximity_threshold) or self._seed_wedged(now):
            self._settle_as_member(now)
            return
        path = self.space.get("path") or p.path
        if p.seed_from_rear and path:
            travel = first_travel(self.task.position, path, self.initial_yaw)
            toward = seed_heading(percept.position, self.task.position, travel, p.seed_approach_radius_m)
        else:
            toward = c.sub(self.task.position, percept.position)
        self._drive(c.add(c.unit(toward), self._avoid()))

    def _seed_wedged(self, now: float) -> bool:
        """Ours: a seed driven at a corner of the object can touch it where no IR sensor reads contact (the
        corner's tip between two sensors' axes) and push there for ever: in paper-25-straight_rot seed 13 (on
        `7513162`) the seed pushed at a corner of the 2 x 2 m box from 7 s on and the cage never started. A
        seed that has not moved PROGRESS_STEP_M for SEED_WEDGED_S while its IR sees the object settles where
        it is, its branches starting along the tangent to what its IR sees."""
        here = self.percept.position
        anchor, since = self.seed_still
        if anchor is None or distance(here, anchor) >= PROGRESS_STEP_M:
            self.seed_still = (here, now)
            return False
        return self.percept.object_peak > 0 and now - since >= SEED_WEDGED_S

    # --- travel: reach the branch target by following the cage ---------------------------------------------
    def _on_travel(self, now: float) -> None:
        if not self._still_mine():
            return
        percept, p = self.percept, self.params
        to_target = c.sub(self.task.position, percept.position)
        remaining = c.norm(to_target)
        touching = percept.in_contact(p.proximity_threshold) and remaining < TOUCH_ATTACH_RADIUS_M
        if remaining < self.progress[0] - PROGRESS_STEP_M:
            self.progress = (remaining, now)
        stalled = now - self.progress[1] > STALL_ATTACH_S and remaining < TOUCH_ATTACH_RADIUS_M
        if now - self.progress[1] > self.params.attach_timeout_s:
            # Deviation: no 2 cm nearer the target for attach_timeout_s (wedged behind a member, or led past
            # the target round the cage): give the task back, as attach does, instead of holding the slot
            # and the branch behind it for good while idle robots wait for an open task.
            self._give_back(now)
            return
        if remaining < ATTACH_RADIUS_M or touching or stalled:
            self.state = "attach"
            self.attach_since = now
            self.approach_from, self.shove_advance, self.shoving_object = None, 0.0, False
            self.closest_error = math.inf
            self._maybe_pipeline(now)
            return
        self._travel_toward(to_target, self.task.branch, remaining)

    def _travel_toward(self, to_target: Vec, branch: str, remaining: float) -> None:
        """Drive toward a branch target: round the cage by edge-following its members, along the object where
        it is in the way."""
        percept, p = self.percept, self.params
        members = set(self.board.members())
        n = nearest(percept.neighbours, members)
        if n is not None and c.norm(percept.neighbours[n]) < p.inter_robot_distance_m + 0.1:
            # Edge-follow the cage: orbit the nearest member at I_d (the paper's x_n input).
            u = c.u_edge_follow(percept.neighbours[n], p.inter_robot_distance_m, BRANCH_DIRECTION[branch])
            u = c.add(c.unit(u), c.scale(c.unit(to_target), 0.3))
        else:
            u = c.unit(to_target)
        if percept.object_peak > 0.2:
            # The object is in the way: slide along it toward the target.
            tangent = c.perp(c.unit(percept.object_vector))
            if tangent[0] * to_target[0] + tangent[1] * to_target[1] < 0:
                tangent = c.scale(tangent, -1.0)
            u = c.add(tangent, c.scale(c.unit(percept.object_vector), -0.3))
        self._drive(c.add(u, self._avoid()), self._travel_speed_scale(remaining))

    def _head_start(self, task: Task) -> bool:
        """Ours (``head_start``): while T_a runs, the robot whose bid is the lowest stored for a branch target
        sets off toward it, and stops HEAD_START_STOP_M short of it (the previous robot may still be attaching
        there). It would win that target and make the same trip after T_a anyway: the paper's robots stand
        still for the whole bidding window. Its bid only falls as it comes nearer, so the winner stays the
        same; if a lower bid does arrive, it has only moved nearer the cage. Not for the seed's task, which
        meets the object its own way (approach.py). True if it moved."""
        if not self.params.head_start or task.branch == "S":
            return False
        best = self.board.best_bid(task)
        if best is None or best.get("robot") != self.robot.id:
            return False
        to_target = c.sub(task.position, self.percept.position)
        remaining = c.norm(to_target)
        if remaining < HEAD_START_STOP_M:
            return False
        self._travel_toward(to_target, task.branch, remaining)
        return True

    def _travel_speed_scale(self, remaining: float) -> float:
        """travel_speed_m_s over the cruise speed far from the target, easing to 1 (cruise) between
        travel_fast_beyond_m and that minus the ease distance; 1 whenever the object is in the way."""
        p = self.params
        if self.percept.object_peak > 0.0 or p.travel_speed_m_s <= p.cruise_speed_m_s:
            return 1.0
        span = min(TRAVEL_EASE_M, TRAVEL_EASE_FRACTION * p.travel_fast_beyond_m)
        ease = min(1.0, max(0.0, (remaining - p.travel_fast_beyond_m + span) / span))
        return 1.0 + ease * (p.travel_speed_m_s / p.cruise_speed_m_s - 1.0)

    # --- attach: touch the object and correct the distance to the branch predecessor ----------------------
    def _on_attach(self, now: float) -> None:
        if not self._still_mine():
            return
        p, percept = self.params, self.percept
        error = self._predecessor_error()
        contact = percept.in_contact(p.proximity_threshold)
        shoving = self._shoving(now, contact)
        wrong_way = (contact or shoving) and self._sliding_the_wrong_way(error)
        if (wrong_way or now - self.attach_since > p.attach_timeout_s) and not self._branch_grew_past():
            self._give_back(now)
            return
        if wrong_way:
            self._hold()        # blocks nothing there; sliding on would shove the members round the object
            return
        if contact or shoving:
            # u = perp(x_o): slide along the object until the predecessor is I_d away. No push inward: the
            # object must not move while the cage forms.
            # (The branch's direction, as the paper has it, even beyond the predecessor: a robot there slides
            # away round the object until attach_timeout_s gives its task back. _slide_sign here made robots
            # in the notches of irregular-box_rotation, whose predecessor is across the notch, never settle.)
            direction = BRANCH_DIRECTION[self.task.branch]
            u = c.u_distance_correction(percept.object_vector, error * direction, 4.0)
            if p.keep_gap_while_caging and (contact or percept.object_peak > GAP_READING):
                u = c.add(u, c.u_keep_gap(percept.object_vector, percept.object_peak, GAP_READING, GAP_GAIN))
            settled = abs(error) < p.caging_tolerance_m
        else:
            toward = percept.object_vector if percept.object_peak > 0 else c.sub(self._centre_guess(), percept.position)
            u = c.add(c.unit(toward), c.scale(c.unit(c.sub(self.task.position, percept.position)), 0.2))
            settled = False
        self.settled_steps = self.settled_steps + 1 if settled else 0
        if self.settled_steps >= SETTLE_STEPS or self._settled_on_average(error, contact or shoving):
            self._hold()
            self._settle_as_member(now)
            return
        if c.norm(u) < 0.05 or (settled and abs(error) < p.caging_tolerance_m / 2):
            self._hold()
        else:
            self._drive(u, speed_scale=0.6, turn_on_spot_beyond_rad=self._attach_turn_gate(contact or shoving))

    def _attach_turn_gate(self, touching: bool) -> float:
        """Ours: the heading error beyond which an attaching robot turns on the spot instead of driving on.
        A robot that reaches the object nose first, at a corner, must turn up to 90 degrees to slide along
        the face; driving forward at cos(heading error) while it turned pressed it into the corner, and it
        turned the light lab box up to 8 degrees (lab-6 at 20 Hz; 2-5 degrees in some 10 Hz seeds) before
        the cage closed. The swarm starts its yaw estimate at the mission's yaw when the cage closes, so it
        never saw that turn: lab-6 at 20 Hz completed 9 of 16 seeds. Turning on the spot while it faces the
        object: 15 of 16 (params.turn_on_spot_at_object, off by default; docs/behaviour.md section 6)."""
        if not touching or not self.params.turn_on_spot_at_object:
            return math.pi / 2              # vector_to_wheels' own: forward only while heading within 90 degrees
        vector, yaw = self.percept.object_vector, self.percept.yaw
        facing = math.cos(math.atan2(vector[1], vector[0]) - yaw)
        return TURN_ON_SPOT_RAD if facing > FACING_OBJECT_COS else math.pi / 2

    def _sliding_the_wrong_way(self, error: float) -> bool:
        """Ours: this attaching robot touches the object behind its predecessor (between it and the branch's
        start), so sliding along the branch's direction takes it ever farther from its predecessor, round the
        object. Seen when a pipelined successor reached the object while its predecessor was still sliding to
        its own place, past it: in paper-25 with travel_speed_m_s 0.2 it slid for 300 s round the 2 m box,
        and the members opened after it settled interleaved with the branch (docs/behaviour.md section 5,
        travel_fast_beyond_m). Measured as the distance error growing WRONG_WAY_SPACINGS I_d past the
        smallest it had while touching; a robot in a notch, whose predecessor is across it, comes nearer
        as it slides and never trips it. Off with an endless attach_timeout_s (the faithful profile)."""
        if not math.isfinite(self.params.attach_timeout_s):
            return False
        self.closest_error = min(self.closest_error, abs(error))
        return abs(error) > self.closest_error + WRONG_WAY_SPACINGS * self._spacing()

    def _settled_on_average(self, error: float, touching: bool) -> bool:
        """Ours: settled although single readings stray. With a noisy range-and-bearing sensor (a range error
        of 5 cm, as large as d_tol) a robot in its place reads |error| >= d_tol every few steps, so SETTLE_STEPS
        in a row within d_tol may take minutes: on the lab-6 box with comm.range_noise_m 0.05 the cage closed
        at 230 s (seed 3), and with 0.5 s of radio latency as well not in 600 s (seed 1). Touching the object
        for AVERAGE_SETTLE_STEPS steps with a mean error within d_tol / 2, while staying within d_tol of where
        it was, counts as settled too. With the default noise (1 cm) every reading is within d_tol then, so
        the rule in a row decides first."""
        window = self.settle_window
        if not touching:
            window.clear()
            return False
        window.append((error, self.percept.position))
        if len(window) < AVERAGE_SETTLE_STEPS:
            return False
        tolerance = self.params.caging_tolerance_m
        if abs(sum(e for e, _ in window)) >= tolerance / 2 * len(window):
            return False
        first = window[0][1]
        return all(c.norm(c.sub(where, first)) < tolerance for _, where in window)

    def _shoving(self, now: float, contact: bool) -> bool:
        """Ours: whether this attaching robot touches the object although its reading stays below
        proximity_threshold. The IR rays pass on either side of a sharp corner (the KheperaIV's 8 sensors are
        45 degrees apart), so a robot pressed on a 60-degree corner of a triangle read 0-0.7 and drove on
        toward it, shoving the light object 0.45 m while the cage formed (docs/behaviour.md section 8). The IR
        sees no farther than about 0.12 m: a robot that drove SHOVE_ADVANCE_M toward the object since it
        last touched it or first saw it, without touching it, must be pushing it. Once told, it holds until
        the robot has not seen the object for SHOVE_LOST_S (or leaves attach)."""
        percept = self.percept
        if percept.object_peak > 0.0:
            self.object_seen_at = now
        elif now - self.object_seen_at > SHOVE_LOST_S:
            self.shove_advance, self.shoving_object = 0.0, False
        last, self.approach_from = self.approach_from, percept.position
        if contact:
            self.shove_advance = 0.0
        elif last is not None and percept.object_peak > 0.0 and not self.shoving_object:
            step, toward = c.sub(percept.position, last), c.unit(percept.object_vector)
            self.shove_advance += step[0] * toward[0] + step[1] * toward[1]
            self.shoving_object = self.shove_advance >= SHOVE_ADVANCE_M
        return self.shoving_object

    def _slide_sign(self, x_o: Vec) -> float:
        """For a cage member holding its place: which way along perp(x_o) brings it nearer its predecessor.
        The branch direction, as the paper has it, unless the predecessor sits clearly on the other side (the
        member was shoved past it). Sliding the branch's way there takes the member away from its predecessor
        for ever: in paper-100-straight seed 1 a member shoved round a corner slid along the 12 m face and up
        the next one, pushing its neighbours before it."""
        direction = BRANCH_DIRECTION[self.task.branch]
        vector = self._vector_to(self.task.pred)
        if vector is None or direction == 0:
            return direction
        toward, tangent = c.unit(vector), c.perp(c.unit(x_o))
        along = toward[0] * tangent[0] + toward[1] * tangent[1]
        return -direction if along * direction < -WRONG_SIDE_COS else direction

    def _give_back(self, now: float) -> None:
        """attach_timeout_s: this robot has not found its place beside its predecessor (typically it met the
        object on the wrong side of it and slides away round the object), or travelling got it no nearer.
        Re-open the task as a new epoch, as _reopen_orphans does for a dead owner, so that its slot and the
        branch behind it are not held any longer, and go back to idle without bidding for it for a while:
        another robot, arriving from elsewhere, gets the chance to take it."""
        task = self.task
        task.epoch += 1
        self.board.put_task(task)
        self.given_back[task.tid] = now + self.params.attach_timeout_s
        self._drop_task()
        self._hold()

    def _branch_grew_past(self) -> bool:
        """A member farther out on this robot's branch: the branch already goes on past this slot (_chain
        skips a slot still attaching), so holding it blocks nothing, while a robot given the slot afresh
        would open a second successor behind a settled one. Such a robot keeps attaching."""
        index = self.task.index
        return any(k > index for k, _ in self.board.branch_slots(self.task.branch))

    def _drop_task(self) -> None:
        """Back to idle without a task. The successor target this robot opened (pipeline_allocation) is
        measured from this robot, which is leaving: cancel it unless its robot already joined the cage, so
        that the next robot in this slot opens it afresh (a new epoch) from where it attaches, instead of
        two robots ending up in one slot. After closure nothing needs cancelling."""
        successor = self.board.task(self.spawned) if self.spawned is not None else None
        if successor is not None and not successor.cancelled and successor.pred == self.robot.id \
                and "closed" not in self.space and not self._owner_joined(successor):
            successor.cancelled = True
            self.board.put_task(successor)
        self.task, self.spawned, self.state, self.settled_steps = None, None, "idle", 0
        self.settle_window.clear()

    def _owner_joined(self, task: Task) -> bool:
        owner = self.board.owner(task)
        return owner is not None and self.board.is_member(owner.get("robot"))

    def _predecessor_error(self) -> float:
        """|x_pred| - I_d_eff: positive when too far from the predecessor."""
        vector = self._vector_to(self.task.pred)
        if vector is None:
            return 0.0
        return c.norm(vector) - self._spacing()

    # --- becoming a cage member, spawning the next branch target, closing the cage ---------------------------
    def _settle_as_member(self, now: float) -> None:
        self.board.join_cage(self.robot.id, self.task)
        self.state = "caged"
        self.settled_steps = 0
        self.settle_window.clear()
        if self.task.branch == "S":
            for branch in ("L", "R"):
                if not self._slot_held(branch, 1):
                    self._spawn(branch, 1, now)
        elif not self._try_close():
            if self.spawned is None:
                if not self._slot_held(self.task.branch, self.task.index + 1):
                    self._spawn(self.task.branch, self.task.index + 1, now)
            else:
                self._reaim_successor()

    def _slot_held(self, branch: str, index: int) -> bool:
        """The slot's task is live and has an owner: this robot took a slot re-opened after its member died
        (_replace_dead_seed), and the slots after it are already held; opening them again would put a
        second robot in each."""
        task = self.board.task(task_id(branch, index))
        return task is not None and not task.cancelled and self.board.owner(task) is not None

    def _tangent(self, branch: str) -> Vec:
        normal = c.unit(self.percept.object_vector) if self.percept.object_peak > 0 else \
            c.unit(c.sub(self._centre_guess(), self.percept.position))
        # Counter-clockwise around the object is perp(-normal); the left branch grows that way.
        return c.scale(c.perp(normal), -BRANCH_DIRECTION[branch])

    def _next_target(self, branch: str) -> Vec:
        """The successor's place on ``branch``: I_d along the object's tangent from here."""
        return c.add(self.percept.position, c.scale(self._tangent(branch), self._spacing()))

    def _spawn(self, branch: str, index: int, now: float) -> None:
        """Open the next target of ``branch``."""
        self._open_task(branch, index, self._next_target(branch), now)

    def _reaim_successor(self) -> None:
        """A pipelined target was extrapolated from this robot's *target*; now that it sits on the object,
        move the successor's target to I_d along the real tangent from here. Same epoch: the successor
        keeps its task and no new bidding round is needed (its robot picks the new position up)."""
        task = self.board.task(self.spawned)
        if task is None or task.cancelled or task.pred != self.robot.id:
            return
        task.x, task.y = self._next_target(task.branch)
        self.board.put_task(task)

    def _open_task(self, branch: str, index: int, target: Vec, now: float) -> None:
        """Put a caging target (a new epoch if the slot existed before) with this robot as predecessor."""
        tid = task_id(branch, index)
        existing = self.board.task(tid)
        epoch = existing.epoch + 1 if existing is not None else 0
        self.board.put_task(Task(tid, target[0], target[1], branch, index, self.robot.id, epoch))
        self.spawned_times[(tid, epoch)] = now
        if branch == self.task.branch:
            self.spawned = tid

    def _maybe_pipeline(self, now: float) -> None:
        """Improvement: open the successor's target as soon as this robot is near its own."""
        if not self.params.pipeline_allocation or self.task.branch == "S" or self.spawned is not None:
            return
        # Continue round the object, not straight on: step along the tangent of the circle about the
        # estimated centre through this robot's own target (bends round corners of convex objects).
        radial = c.unit(c.sub(self.task.position, self._centre_guess()))
        heading = c.scale(c.perp(radial), BRANCH_DIRECTION[self.task.branch])
        target = c.add(self.task.position, c.scale(heading, self._spacing()))
        self._open_task(self.task.branch, self.task.index + 1, target, now)
