"""Closing the cage (Proposition 1): which members are the two branch tips, the paper's closure distance
d_T between them, and our guards against a closure that is not a cage (a gap across the object, a ring that
does not enclose C_o(0), a gap over a whole end of it).

A mixin of :class:`~.behaviour.Transport`, like :class:`~.caging.CagingPhases`. See docs/behaviour.md section 3.
"""
from __future__ import annotations

import math
from typing import List, Optional

from . import control as c
from .control import Vec
from .estimator import encloses
from .tasks import distance

CHAIN_LINK_FACTOR = 2.0    # a branch member farther than this times I_d from its predecessor breaks the chain
# Two branch tips whose IR directions to the object differ by more than this sit on opposite sides of it
# (_closure_distance).
OPPOSITE_TIPS_DEG = 150.0


class ClosurePhase:
    def _gap_crosses_object(self, to_tip: Vec) -> bool:
        """Deviation from the paper: two tips facing each other *across* a small object are close too, but
        the ring is not closed. A closing gap lies on the rim, far from the centre; a chord through the
        object passes near it. Reject gaps whose chord comes closer to the estimated centre than half the
        robots' own distance from it."""
        me = self.percept.position
        centre = self._centre_guess()
        length_sq = to_tip[0] ** 2 + to_tip[1] ** 2
        rel = c.sub(centre, me)
        t = max(0.0, min(1.0, (rel[0] * to_tip[0] + rel[1] * to_tip[1]) / length_sq)) if length_sq > 0 else 0.0
        closest = c.add(me, c.scale(to_tip, t))
        tip = c.add(me, to_tip)
        return distance(closest, centre) < 0.5 * min(distance(me, centre), distance(tip, centre))

    def _ring_encloses_estimate(self) -> bool:
        """Deviation from the paper: Proposition 1 assumes the branches went round the object in opposite
        directions. On a concave object a branch can fold back (its tangent flips in a notch), and its tip
        then meets the other tip on the same side, with the object outside the ring. Close only a ring (L tip
        .. L1, S, R1 .. R tip, each branch up to its first gap) that encloses C_o(0), where the seed was sent."""
        seed = self.board.seed_member()
        order = self._chain("L")[::-1] + ([] if seed is None else [seed]) + self._chain("R")
        ring = [q for q in (self._member_position(rid) for rid in order) if q is not None]
        return len(ring) >= 3 and encloses(ring, self.hint)

    def _opposite_tip(self) -> Optional[int]:
        """The last robot of the other branch's unbroken chain from the seed (the seed belongs to both)."""
        other = "R" if self.task.branch == "L" else "L"
        return self._chain_tip(other)

    def _chain_tip(self, branch: str) -> Optional[int]:
        chain = self._chain(branch)
        return chain[-1] if chain else None

    def _chain(self, branch: str) -> List[int]:
        """The members of ``branch`` in index order, up to the first one that sits farther than
        CHAIN_LINK_FACTOR * I_d from the member before it: a robot that attached somewhere else (early
        attach on a concave outline) does not continue the branch. An index whose robot has not settled yet
        is skipped: one robot stuck attaching must not hide the rest of its branch from the closure test."""
        previous = self.board.seed_member()
        chain: List[int] = []
        for _, rid in self.board.branch_slots(branch):
            if self._breaks_chain(rid, previous):
                break
            chain.append(rid)
            previous = rid
        return chain

    def _breaks_chain(self, rid: int, previous: Optional[int]) -> bool:
        here, there = self._member_position(rid), self._member_position(previous)
        return here is not None and there is not None and \
            distance(here, there) > CHAIN_LINK_FACTOR * self._spacing()

    def _may_be_tip(self, branch: str) -> bool:
        """False when this robot is surely not the tip of ``branch``'s chain: it holds no slot there, or the
        next slot's member continues the chain from it. Only the few robots left need the whole walk
        (_chain), which every branch member would otherwise do every step."""
        slots = self.board.branch_slots(branch)
        me = self.robot.id
        for k, (_, rid) in enumerate(slots):
            if rid == me:
                return k + 1 == len(slots) or self._breaks_chain(slots[k + 1][1], me)
        return False

    def _closure_distance(self, tip: int) -> float:
        """d_T, the paper's closure distance; ours, while robots remain, a tighter one for tips on opposite
        sides of the object. Their gap leaves a whole end of it open: a 1.0 x 0.3 m box caged by 5 robots
        with its end in the gap had nobody behind it when the path turned along its length (docs/behaviour.md
        section 3). Once the swarm is out of robots (I_d grows) the paper's d_T applies again."""
        p = self.params
        factor = p.closure_factor
        if self.board.grow_level() == 0 and self._tips_face_apart(tip):
            factor = min(factor, p.end_gap_closure_factor)
        return factor * self._spacing()

    def _tips_face_apart(self, tip: int) -> bool:
        """Once seen, for good: a tip near a corner sees the object obliquely, and one such reading must not
        let the pair close a gap that spans the object's end (it did, 2 s after 20 readings said so)."""
        if tip in self.tips_seen_apart:
            return True
        mine, theirs = self._contact_normal(), self.board.contact_normal(tip)
        if mine is None or theirs is None:
            return False
        if abs(math.remainder(mine - theirs, 2.0 * math.pi)) > math.radians(OPPOSITE_TIPS_DEG):
            self.tips_seen_apart.add(tip)
            return True
        return False

    def _try_close(self) -> bool:
        """Proposition 1: the cage is closed when the two branch tips are within d_T."""
        if self.task is None or self.task.branch == "S" or "closed" in self.space:
            return "closed" in self.space
        if not self._may_be_tip(self.task.branch) or self._chain_tip(self.task.branch) != self.robot.id:
            return False   # only the tip of an unbroken branch may close the ring
        tip = self._opposite_tip()
        if tip is None:
            return False
        vector = self._vector_to(tip)
        if vector is None or c.norm(vector) > self._closure_distance(tip):
            return False
        if self._gap_crosses_object(vector) or not self._ring_encloses_estimate():
            return False
        self.space.put("closed", {"pair": sorted([self.robot.id, tip])})
        if self.spawned is not None:
            task = self.board.task(self.spawned)
            if task is not None and not task.cancelled:
                task.cancelled = True
                self.board.put_task(task)
        return True
