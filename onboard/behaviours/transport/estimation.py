"""How the cage estimates the object it carries: its centroid C_o and yaw from the members' shared positions,
the surface points their IR sees, and the contact normals, filtered (constant-velocity Kalman).

A mixin of :class:`~.behaviour.Transport`, beside :class:`~.transport.TransportPhases`, which drives the cage
by it. Nothing here senses anything the robots do not: every input is a member's heartbeat.
"""
from __future__ import annotations

import math
from collections import deque
from typing import Callable, Dict, Iterable, Optional, Tuple, TypeVar

import numpy as np

from ...hal import wrap_angle
from . import control as c
from .control import Vec
from .estimator import (
    ObjectFilter,
    edge_rotation,
    median_turn,
    normal_displacement,
    offset_of_survivors,
    ring_centroid,
    ring_edges,
    ring_rotation,
    surface_normals,
)

EDGE_FACTOR = 1.5             # edges between cage neighbours longer than 1.5 I_d are gaps, not faces
# A cage of fewer members than this (but not a small one) reads the yaw from its members' contact normals and
# the edges between them together (_sparse_cage).
SPARSE_CAGE_MEMBERS = 10
# A gap this long between two estimates is a pause (the robot was held), not a step: a spare that watches a
# stalled push estimates once a second (reinforce.py STALL_CHECK_S), and those gaps stay predicted as before.
PAUSED_AFTER_S = 3.0
T = TypeVar("T")


class ObjectEstimation:
    def _start_estimate(self, now: float) -> None:
        """When transport begins: the reference ring, edges, contact normals and surface points the estimate
        compares with from here on, and the filter, started at the ring's centroid and the mission's yaw."""
        ring = self._member_positions(now)
        self.reference_ring = ring
        self.reference_ring_centre = ring_centroid(np.asarray(list(ring.values()))) if ring else self.hint
        self.ring_offset = self._dead_members_offset(ring, self.reference_ring_centre, now)
        self.offset_members = frozenset(ring)
        self.yaw_history = deque()
        self.reference_centre = self._whole_ring_centre(self.reference_ring_centre, 0.0)
        self.reference_yaw = self.initial_yaw
        self.reference_edges = ring_edges(ring, self.reference_ring_centre, EDGE_FACTOR * self._spacing())
        self.reference_contacts = self._contact_angles(ring)
        self.reference_surface = self._member_surfaces(ring)
        self.reference_normals = surface_normals(self.reference_surface, ring)
        noise = 0.02
        self.filter = ObjectFilter(self.reference_centre[0], self.reference_centre[1], self.reference_yaw, noise)

    def _dead_members_offset(self, ring: Dict[int, Vec], ring_centre: Vec, now: float) -> Optional[Vec]:
        """Ours (the paper has no failures): from the centroid of the live members' ring to that of the whole
        ring, with the last heartbeat positions of members that died before transport began. Such a member
        stays where it stopped, in its place round the object, but it neither pushes nor reports, so the ring
        centroid of the live members alone is off to the other side: in lab-6 with the first robot of the
        right branch dead before closure, 0.08-0.10 m, and the cage pushed that point, not the object, to the
        waypoints (docs/behaviour.md section 8). The live ring moves with the object, so the whole ring's
        centroid is the live one plus this offset, turned as the object turned; with it two live members are
        enough to follow the object (a 3-member lab-6 cage with one member dead in settle never moved). None
        when every member lives (then nothing changes)."""
        live = set(self._members_alive(now))
        dead = [self._member_position(rid) for rid in self.board.members() if rid not in live]
        dead = [where for where in dead if where is not None]
        if not dead or len(ring) < 2:
            return None
        whole = ring_centroid(np.asarray(list(ring.values()) + dead))
        return c.sub(whole, ring_centre)

    def _live_members_offset(self, ring: Dict[int, Vec]) -> None:
        """Ours (the paper has no failures): when the live members are no longer those ``ring_offset`` is for
        (one died during transport, or one thought dead beats again), the offset from the centroid these
        members had when transport began to the object's centroid then (reference_centre), in the frame of
        the reference yaw like _dead_members_offset's. A member's body stays where it died and the object
        moves away from it, so the live ring's centroid falls to the other side (by up to a third of the
        box in a 3-member cage), and two live members were too few to estimate at all: a 3-member lab-6 cage
        stopped for good, its estimate running on at the filter's last velocity. Taken from when transport
        began, with the cage at rest round the object, not from when the death was seen: the filtered
        estimate then lags a moving object by centimetres, and had followed the dead member's stale
        heartbeat for the liveness timeout. None (three live members needed) when fewer than two live."""
        self.offset_members = frozenset(ring)
        if len(ring) < 2 or any(rid not in self.reference_ring for rid in ring):
            self.ring_offset = None
            return
        self.ring_offset = offset_of_survivors(self.reference_ring, ring, self.reference_centre)

    def _lost_a_member(self) -> bool:
        """Some member that was alive when transport began no longer counts (_live_members_offset)."""
        return not self.offset_members >= set(self.reference_ring)

    def _yaw_before(self, when: float) -> float:
        """The yaw measured last at or before ``when`` (yaw_history), else the filter's now."""
        found = self.filter.pose[2]
        for at, yaw in self.yaw_history:
            if at > when:
                break
            found = yaw
        return found

    def _remember_yaw(self, now: float, yaw: Optional[float]) -> None:
        """Keep the yaws measured over the last liveness timeout plus a second: as far back as a dead member's
        stale heartbeat can reach (_hold_yaw_of_two)."""
        if yaw is not None:
            self.yaw_history.append((now, yaw))
        while self.yaw_history and self.yaw_history[0][0] < now - self.board.timeout - 1.0:
            self.yaw_history.popleft()

    def _hold_yaw_of_two(self, since: Optional[float]) -> None:
        """Ours: with two live members left by a death during transport, the yaw stays where it was measured
        when the first dead member last beat (``since``; the current estimate while None). Two members do
        not measure it: a side member slides along its face, and the line to the other member turned by up
        to 0.15 rad while the box did not (lab-6 seed 2, R1 dead at 76.7 s); the cage then turned the box
        0.23 rad to match. The stale heartbeat had already thrown the estimate 0.1 rad off before it timed
        out, hence the measured yaw from before it."""
        self.filter.hold_yaw(self.filter.pose[2] if since is None else self._yaw_before(since))

    def _whole_ring_centre(self, live_centre: Vec, turned: float) -> Vec:
        """The object's centroid from the live members' ring centroid (_dead_members_offset,
        _live_members_offset); the live centroid itself when every member lives."""
        if self.ring_offset is None:
            return live_centre
        return c.add(live_centre, c.rotate(self.ring_offset, turned))

    def _member_positions(self, now: float) -> Dict[int, Vec]:
        positions = {}
        for rid in self._members_alive(now):
            where = self._member_position(rid)
            if where is not None:
                positions[rid] = where
        return positions

    def _member_surfaces(self, members: Dict[int, Vec]) -> Dict[int, Vec]:
        """The object's surface points that ``members`` last saw with their IR (those that saw it), as
        published: this robot's own too, so that every member estimates from the same points."""
        return published(members, self.board.surface_point)

    def _rotation_since_reference(self, ring: Dict[int, Vec], centre: Vec) -> Optional[float]:
        """How far the object turned since transport began: in a small cage whose path turns, from how the
        members' contact normals turned (params.small_cage_yaw); in a sparse cage, from them and the edges
        between neighbouring members together (_sparse_cage); else from the edges alone
        (estimator.edge_rotation), else from how the ring turned about the centroid."""
        if len(ring) < 3 and self._lost_a_member():
            return None         # _hold_yaw_of_two
        if self.yaw_from_normals and self._small_cage():
            turned = edge_rotation(self._contact_angles(ring), self.reference_contacts)
            if turned is not None:
                return turned
        edges = ring_edges(ring, centre, EDGE_FACTOR * self._spacing())
        if self._sparse_cage():
            turned = median_turn((edges, self.reference_edges), (self._contact_angles(ring), self.reference_contacts))
        else:
            turned = edge_rotation(edges, self.reference_edges)
        if turned is not None:
            return turned
        return ring_rotation(ring, self.reference_ring, centre, self._reference_centre_of(ring))

    def _sparse_cage(self) -> bool:
        """Ours: a cage of ``surface_estimate_min_points`` to SPARSE_CAGE_MEMBERS - 1 members, unless
        ``small_cage_yaw`` is "edges". With one or two members per face most edges between neighbours cross a
        corner, and while the object stands still the members shuffle along its faces: round a stalled 0.6 m
        box of 4 kg with 6 members the median of the edges' turns swung by up to 30 degrees, and the cage
        pushed the box askew; the members' contact normals stayed within 5 degrees. Yet the normals alone
        missed the turns of an oblong box pushed along a zigzag. The median of both together served both
        best (docs/behaviour.md section 8)."""
        if self.params.small_cage_yaw == "edges" or self._small_cage():
            return False        # a small cage's yaw: above (lab-6's 4 members: their normals spread more)
        return self.board.member_count() < SPARSE_CAGE_MEMBERS

    def _reference_centre_of(self, ring: Dict[int, Vec]) -> Vec:
        """The centroid, when transport began, of the members in ``ring``: the angles about it compare with
        those about ``ring``'s centroid now only if both are taken over the same members (one died since)."""
        if set(ring) == set(self.reference_ring):
            return self.reference_ring_centre
        common = [self.reference_ring[rid] for rid in ring if rid in self.reference_ring]
        return ring_centroid(np.asarray(common)) if common else self.reference_ring_centre

    def _yaw_from_contact_normals(self) -> bool:
        mode = self.params.small_cage_yaw
        if mode == "auto":      # a path that turns: the sliding members would fool the edges
            tolerance = math.radians(self.params.rotation_tolerance_deg)
            return any(abs(wrap_angle(math.radians(w[2]) - self.initial_yaw)) > tolerance for w in self.path)
        return mode == "contact_normals"

    def _contact_angles(self, ring: Dict[int, Vec]) -> Dict[int, float]:
        """The world angle of each member's contact normal x_o, as its heartbeat publishes it (members that
        touch the object): it turns with the face the member presses on, even while the member slides."""
        return published(ring, self.board.contact_normal)

    def _estimate_object(self, now: float) -> Tuple[float, float, float]:
        """C_o and yaw from the live members' shared positions, filtered (constant-velocity Kalman)."""
        gap = now - self.estimated_at
        if gap > PAUSED_AFTER_S:
            # The robot was held (an e-stop, the hub gone): predicting over the pause at the last velocity
            # carried the estimate 0.3 m ahead for a step after an 11 s e-stop. Its motion since is unknown.
            self.filter.halt()
        self.filter.predict(max(gap, 1e-3))
        self.estimated_at = now
        ring = self._member_positions(now)
        changed = ring.keys() != self.offset_members
        departed = self.offset_members - ring.keys() if changed else frozenset()
        if changed:
            self._live_members_offset(ring)
        if len(ring) >= (2 if self.ring_offset is not None else 3):    # 2: plus the dead (_dead_members_offset)
            centre = ring_centroid(np.asarray(list(ring.values())))
            turned = self._rotation_since_reference(ring, centre)
            centre = self._whole_ring_centre(centre, turned or 0.0)
            yaw = None if turned is None else self.reference_yaw + turned
            surface = self._surface_centre(ring, turned)
            if surface is not None:
                centre = surface
            elif changed:   # the last seconds followed a dead member's stale heartbeat: start from here
                self.filter.move_to(centre[0], centre[1])
            self.filter.update(centre[0], centre[1], yaw, len(ring))
            if len(ring) < 3 and self._lost_a_member():
                self._hold_yaw_of_two(self._first_heard(departed) if changed else None)
            self._remember_yaw(now, yaw)
        return self.filter.pose

    def _first_heard(self, members: Iterable[int]) -> Optional[float]:
        """The earliest time any of ``members`` last beat (None: none of them beat)."""
        heard = [self.board.last_heard(rid) for rid in members]
        return min((t for t in heard if t is not None), default=None)

    def _surface_centre(self, ring: Dict[int, Vec], turned: Optional[float]) -> Optional[Vec]:
        """Improvement: the centroid moved as far as the object's IR-seen surface points moved along its
        normals since transport began (estimator.normal_displacement). Robots sliding along a face, falling
        back from it or closing in on it drag the ring centroid; they do not move this. None (use the ring)
        when it is off or fewer than ``surface_estimate_min_points`` members see the object now and did then:
        with 3 or 4 points one odd reading (a corner, a neighbour) carries the whole fit."""
        p = self.params
        if not p.surface_estimate:
            return None
        surfaces = self._member_surfaces(ring)
        if sum(1 for k in surfaces if k in self.reference_surface) < p.surface_estimate_min_points:
            return None
        moved = normal_displacement(surfaces, self.reference_surface, self.reference_normals,
                                    self.reference_centre, turned or 0.0)
        return None if moved is None else c.add(self.reference_centre, moved)


def published(members: Iterable[int], read: Callable[[int], Optional[T]]) -> Dict[int, T]:
    """``read(rid)`` for each of ``members`` whose heartbeat carries it (None: it published none)."""
    found = {}
    for rid in members:
        value = read(rid)
        if value is not None:
            found[rid] = value
    return found
