"""Robots left out of the cage push from behind (``reinforce_push``, or once the push stalls; not in the paper).

The paper's robots that are not needed for the cage stay out of the way. On the lab's loaded box (4.3 kg)
the one or two cage members behind the object cannot overcome its friction, while two robots wait idle
beside it. With ``reinforce_push`` they join the push without joining the cage: each estimates the object's
centroid from the members' shared positions (as the members do), works out which waypoint the cage is
heading for from the members' arrival flags, gets behind the cage on the line through the centroid and
pushes along the direction of travel. They hold still while the cage rotates and never count in a barrier.

``reinforce_push`` is off by default: on a light object the extra pushers move it faster than the cage ring
follows, and the centroid estimate (the ring's centroid) falls behind the object (lab-6: up to 0.28 m instead
of 0.06 m). What the default does instead (``reinforce_when_stalled_s``): the spares watch the cage, and
once it has pushed toward its waypoint for that long without coming STALL_PROGRESS_M nearer, the object is
too heavy for the members behind it (its mass is unknown to the swarm), and they reinforce the push from
then on: a light object never stalls, so its runs are the same as without.

A mixin of :class:`~.behaviour.Transport`, like :class:`~.transport.TransportPhases`.
"""
from __future__ import annotations

import math
from typing import List, Optional, Tuple

from . import control as c
from .control import Vec

BEHIND_MARGIN_M = 0.2      # queue this far behind the cage ring before moving in
LATERAL_GAIN = 10.0        # pull toward the line of travel through the centroid (per metre of offset)
LINE_UP_M = 0.1           # push forward only this close to the line (full speed on it)
ARRIVED_M = 0.05           # closer than this to the waypoint, the cage is arriving: stop pushing
NEAR_OBJECT_READING = 0.3  # an object IR reading this strong (~8 cm): no more lining up sideways, push on
STALL_PROGRESS_M = 0.03    # a cage pushing that came less than this nearer its waypoint ... is stalled
STALL_CHECK_S = 1.0        # how often a spare looks at the cage's progress (member positions beat ~1 s)


class ReinforcePhase:
    def _push_stalled(self, now: float) -> bool:
        """Ours (``reinforce_when_stalled_s``): whether the cage has stalled while pushing, seen by a spare.
        The watch starts when the members' settling time after closure is over, restarts whenever the cage
        comes STALL_PROGRESS_M nearer its waypoint, a new leg begins or the cage is not pushing (rotating,
        or at the barrier), and is not kept within ``push_tolerance_m`` of the waypoint, where a cage that
        waits at a barrier is arriving, not stalled. Once stalled, the object is heavy: it stays so."""
        stall_s = self.params.reinforce_when_stalled_s
        if self.push_stalled or stall_s <= 0.0:
            return self.push_stalled
        if self.closed_seen_at is None:
            self.closed_seen_at = now
        if now < self.next_stall_check or now < self.closed_seen_at + self.params.settle_time_s:
            return False
        self.next_stall_check = now + STALL_CHECK_S
        members = self._member_positions(now)
        path = self.space.get("path") or self.params.path
        needed = self._barrier_needed(len(members))
        leg = self._cage_leg(needed, path) if self._enough_members(len(members)) and path else None
        if leg is None or not self._cage_pushing(leg, needed):
            self.stall_watch.clear()
            return False
        centre = self._cage_centre(now)
        distance = math.hypot(float(path[leg][0]) - centre[0], float(path[leg][1]) - centre[1])
        if distance < self.params.push_tolerance_m:
            self.stall_watch.restart(leg, now, distance)
        elif self.stall_watch.waited(leg, now, distance) >= stall_s:
            self.push_stalled = True
        return self.push_stalled

    def _reinforce(self, now: float) -> None:
        """One step of an idle robot helping the cage push (called from idle once the cage has closed)."""
        members = self._member_positions(now)                # every live member has a heartbeat
        ring = list(members.values())
        path = self.space.get("path") or self.params.path
        if not self._enough_members(len(ring)) or not path:
            self._keep_clear()
            return
        centre = self._cage_centre(now)
        needed = self._barrier_needed(len(ring))
        leg = self._cage_leg(needed, path)
        if leg is None:
            self._keep_clear()
            return
        target = (float(path[leg][0]), float(path[leg][1]))
        to_target = c.sub(target, centre)
        if c.norm(to_target) < ARRIVED_M or not self._cage_pushing(leg, needed):
            self._hold()
            return
        self._drive(self._reinforce_input(centre, c.unit(to_target), ring))

    def _enough_members(self, count: int) -> bool:
        """Three live members, or two once the cage has lost one since it began to push: its members estimate
        on with two (estimation.py), and it still pushes. With "three" the spares stopped helping a 3-robot
        cage of the 4.3 kg box that lost a member mid-push, and it never moved again (lab-6-payload seed 2).
        A cage that never lost one (heartbeats that arrive late) is left as it was."""
        return count >= 3 or (count == 2 and self.filter is not None and len(self.reference_ring) > count)

    def _cage_centre(self, now: float) -> Vec:
        """Ours: the object's centroid as the members estimate it (estimation.py), from the same heartbeats,
        started when this spare first needs it (with the stall watch, as the members begin to push).
        The members' bare ring centroid leads a pushed box: the members at the front stand off its face, and
        those at its sides slide forward. Round a 0.6 m box of 4 kg the spares that judged by it saw the cage
        arrive 0.13 m short of each waypoint and stopped pushing; the rear member alone could not move the
        box, and the swarm's estimate crept on to the waypoint while the box stood still. A member that died
        is counted as the members count it (``_live_members_offset``)."""
        if self.filter is None:
            self._start_estimate(now)
            self.estimated_at = now
        pose = self._estimate_object(now)
        return (pose[0], pose[1])

    def _cage_leg(self, needed: int, path: List) -> Optional[int]:
        """The first waypoint whose last barrier the cage has not passed (None once all are done)."""
        for k in range(len(path)):
            if len(self.board.arrivals(k, self._final_phase(path, k))) < needed:
                return k
        return None

    def _cage_pushing(self, leg: int, needed: int) -> bool:
        """The cage pushes toward ``leg`` until its push barrier passed (then it rotates there)."""
        return "done" not in self.space and len(self.board.arrivals(leg, "p")) < needed

    def _reinforce_input(self, centre: Vec, direction: Vec, ring: List[Tuple[float, float]]) -> Vec:
        me = self.percept.position
        offset = c.sub(me, centre)
        along = offset[0] * direction[0] + offset[1] * direction[1]          # < 0: behind the centroid
        lateral = c.sub(offset, c.scale(direction, along))                    # from the line of travel
        ring_radius = max(math.hypot(q[0] - centre[0], q[1] - centre[1]) for q in ring)
        if along >= 0.0:
            self.reinforcing = False
        if along > -(ring_radius + BEHIND_MARGIN_M / 2) and not self.reinforcing:
            # Not behind the cage yet: go round it to the queueing point, keeping clear of the members.
            queue = c.sub(centre, c.scale(direction, ring_radius + BEHIND_MARGIN_M))
            return c.add(c.unit(c.sub(queue, me)), self._avoid(), c.scale(self.percept.obstacle_vector, -1.0))
        # Behind: line up with the centroid first (sideways), then push along the direction of travel;
        # pushing off the line would turn the object, or only shove a cage member along its side.
        self.reinforcing = True
        if self.percept.object_peak >= NEAR_OBJECT_READING:
            # At the object already (beside the rear member, say): straight on. Sliding sideways to the line
            # here shoved the rear member along the face, round the corner, and the box spun.
            return direction
        forward = max(0.0, 1.0 - c.norm(lateral) / LINE_UP_M)
        return c.add(c.scale(direction, forward), c.scale(lateral, -LATERAL_GAIN))
