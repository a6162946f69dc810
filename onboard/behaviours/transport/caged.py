"""The cage before it closes: members hold the object, keep their spacing, reopen the targets of robots that
died on their way, and grow I_d when the swarm is out of robots.

A mixin of :class:`~.behaviour.Transport`, like :class:`~.transport.TransportPhases` (settling, pushing,
rotating), which also holds a position with :meth:`CagedPhase._hold_position`; split out to keep each module
readable.
"""
from __future__ import annotations

from typing import Optional, Tuple

from . import control as c
from .heartbeat import HEARTBEAT_RULES
from .tasks import Task

GROW_PERIOD_S = 1.0           # out of robots: I_d grows one level (2 %) per second
ON_ITS_WAY_WAIT_S = 30.0      # I_d waits this long at most for a robot on its way to its slot (_robot_on_its_way)
OUT_OF_ROBOTS_FACTOR = 3.0    # a target nobody took for 3 T_a means the swarm has no robot left for it
CONTACT_GAIN = 0.3            # gentle push toward the object while holding a cage position
SPACING_GAIN = 4.0
# keep_gap_while_caging: the IR reading a caging robot holds while it slides along the object or holds its
# place (about 4.7 cm from it on the KheperaIV curve, inside the 0.7 contact threshold), and the gain.
GAP_READING = 0.85
GAP_GAIN = 3.0


class CagedPhase:
    # --- caged: hold the object, keep the spacing, watch for closure --------------------------------------
    def _on_caged(self, now: float) -> None:
        if self._finish_if_done():
            return
        if "closed" in self.space:
            if self._caging_only_done():
                self._hold()
                return
            self.closed_at = now
            self.state = "settle"
            return
        if not self.board.is_member(self.robot.id):
            self._drop_task()       # declared dead (_replace_dead_seed) while alive: idle, and bid again
            return
        if self.task.branch != "S":
            self._try_close()
        self._reopen_orphans(now)
        self._grow_if_out_of_robots(now)
        self._hold_position(equalise=False)

    def _hold_position(self, equalise: bool) -> None:
        """Stay on the object and correct the spacing (paper: to the branch predecessor; improved: even out)."""
        percept = self.percept
        x_o = percept.object_vector if percept.object_peak > 0 else c.sub(self._centre_guess(), percept.position)
        error = self._even_spacing_error() if equalise else None    # caged robots (most of them) never even out
        if error is None:
            error = self._predecessor_error() * self._slide_sign(x_o) if self.task.pred is not None else 0.0
        contact = percept.in_contact(self.params.proximity_threshold)
        if abs(error) < self.params.caging_tolerance_m / 2 and contact:
            self._hold()
            return
        if not contact:
            toward = c.scale(c.unit(x_o), CONTACT_GAIN)
        elif self.params.keep_gap_while_caging:
            toward = c.u_keep_gap(x_o, percept.object_peak, GAP_READING, GAP_GAIN)
        else:
            toward = c.ZERO
        u = c.add(c.u_distance_correction(x_o, error, SPACING_GAIN), toward)
        self._drive(u, speed_scale=min(1.0, 0.3 + 4.0 * abs(error)))

    def _even_spacing_error(self) -> Optional[float]:
        """Half the difference of the distances to the two ring neighbours (> 0: move clockwise, toward the
        farther one); None unless both are known."""
        cw, ccw = self._cage_ring_neighbours()
        d_cw, d_ccw = self._distance_to(cw), self._distance_to(ccw)
        return None if d_cw is None or d_ccw is None else 0.5 * (d_cw - d_ccw)

    def _distance_to(self, robot: Optional[int]) -> Optional[float]:
        vector = self._vector_to(robot)
        return None if vector is None else c.norm(vector)

    def _cage_ring_neighbours(self) -> Tuple[Optional[int], Optional[int]]:
        """(clockwise, counter-clockwise) neighbours in the ring S, L1, L2, ... (ccw) and R1, R2, ... (cw)."""
        by_slot, tips = self.board.ring_slots()
        closed = "closed" in self.space

        def slot(branch: str, index: int) -> Optional[int]:
            if index == 0:
                return by_slot.get(("S", 0))
            if index > (tips[branch] or 0):
                other = "R" if branch == "L" else "L"
                return by_slot.get((other, tips[other])) if closed and tips[other] else None
            return by_slot.get((branch, index))

        branch, index = self.task.branch, self.task.index
        if branch == "S":
            return slot("R", 1), slot("L", 1)
        if branch == "L":
            return slot("L", index - 1), slot("L", index + 1)
        return slot("R", index + 1), slot("R", index - 1)

    def _reopen_orphans(self, now: float) -> None:
        """A robot that died on its way to a target this robot opened: open the target again. Ours: the seed's
        successors do the same for a seed that died after settling, before the cage closed (_replace_dead_seed)."""
        members = self.board.members()
        for task in self.board.tasks_opened_by(self.robot.id):
            self.spawned_times.setdefault((task.tid, task.epoch), now)
            owner = self.board.owner(task)
            if owner is None:
                continue
            rid = owner.get("robot")
            if rid not in members and self.board.heard_of(rid) and not self.board.alive(rid, now):
                task.epoch += 1
                self.board.put_task(task)
                self.spawned_times[(task.tid, task.epoch)] = now
        seed = self.board.seed_member()
        if seed is not None and seed == self.task.pred and self._member_dead(seed, now):
            task = self.board.task("S")
            owner = self.board.owner(task) if task is not None else None
            if owner is not None and owner.get("robot") == seed:
                self._replace_dead_seed(seed, task)

    def _member_dead(self, rid: int, now: float) -> bool:
        """A member (other than this robot) whose heartbeat has not changed for the liveness timeout plus the
        period a still caged member beats at (heartbeat.HEARTBEAT_RULES): before closure a live member may be
        silent for that long."""
        window = HEARTBEAT_RULES["caged"].period_s + self.params.liveness_timeout_s
        return rid != self.robot.id and self.board.heard_of(rid) and not self.board.alive(rid, now, window)

    def _replace_dead_seed(self, seed: int, task: Task) -> None:
        """Ours (the paper has no failures): the seed died before closure. It stays where it stopped, an
        obstacle that cages but neither pushes nor tells where it is any more, and it was the cage's pusher
        behind the object (seed_from_rear). A ring closed through it can have all its live members beside and
        ahead of the object: in f-seed (lab-6, robot 4 dead at 40 s) seed 1 the cage closed with the three
        live members there, their ring centroid 0.13 m off; the box never moved while the estimate slid along
        with the members. So declare it dead (it no longer counts as a member: the chain, the closure test
        and the centre guess use live members only) and open task S again as a new epoch: a spare drives in
        as the new seed (behind the dead one, which its IR takes for the object) and the ring closes through
        it. A dead branch member is not replaced (docs/behaviour.md section 8): its successors measure from
        where it stopped, and a replacement cannot take its place, so it settled outside the ring and threw
        the ring centroid off; the estimate counts it where it stopped instead (_dead_members_offset)."""
        self.board.declare_dead(seed)
        task.epoch += 1
        self.board.put_task(task)

    def _grow_if_out_of_robots(self, now: float) -> None:
        """Nobody bids for the next target: grow I_d so the branches spread until the cage closes.

        Only when no open task has had a valid bid for OUT_OF_ROBOTS_FACTOR * T_a either. Idle robots bid
        for their nearest open task only, so while one target is being bid for, the others wait their turn
        unbid; that is a queue, not a swarm out of robots. A member cut off from the swarm's messages still
        sees stale bids and can grow I_d for nothing (docs/behaviour.md section 3)."""
        if any(best is not None for _, _, best in self.board.open_tasks()):
            self.bidding_seen_at = now
        patience = OUT_OF_ROBOTS_FACTOR * self.params.allocation_time_s
        if now - self.bidding_seen_at <= patience or now - self.grow_at < GROW_PERIOD_S:
            return
        for task in self.board.tasks_opened_by(self.robot.id):
            if not self.board.is_open(task):
                continue
            opened = self.spawned_times.get((task.tid, task.epoch), now)
            if now - opened > patience and self.board.best_bid(task) is None:
                if self._robot_on_its_way(now):
                    return
                self.space.put("grow", {"level": self.board.grow_level() + 1})
                self.grow_at = now
                return

    def _robot_on_its_way(self, now: float) -> bool:
        """Ours: a live robot holds a task and has not joined the cage yet; its arrival may close the cage, so
        I_d does not grow meanwhile. Three robots round a 0.3 m box never caged: while the third travelled,
        the second member slid on round the object with every growth, away from the seed and past the chord
        the third could reach (docs/behaviour.md section 8)."""
        for task in self.board.tasks():
            owner = None if task.cancelled else self.board.owner(task)
            if owner is None or self.board.is_member(owner["robot"]) or not self.board.alive(owner["robot"], now):
                continue
            # A robot stuck on its way (shoving a corner it cannot sense) must not hold the swarm for good.
            since = self.on_its_way_since.setdefault((task.tid, task.epoch, owner["robot"]), now)
            if now - since < ON_ITS_WAY_WAIT_S:
                return True
        return False
