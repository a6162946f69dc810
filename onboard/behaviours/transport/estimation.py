"""How the cage estimates the object it carries: its centroid C_o and yaw from the members' shared positions,
the surface points their IR sees, and the contact normals, filtered (constant-velocity Kalman).

A mixin of :class:`~.behaviour.Transport`, beside :class:`~.transport.TransportPhases`, which drives the cage
by it. Nothing here senses anything the robots do not: every input is a member's heartbeat.
"""
from __future__ import annotations

import math
from typing import Callable, Dict, Iterable, Optional, Tuple, TypeVar

import numpy as np

from ...hal import wrap_angle
from . import control as c
from .control import Vec
from .estimator import (
    ObjectFilter,
    edge_rotation,
    normal_displacement,
    ring_centroid,
    ring_edges,
    ring_rotation,
    surface_normals,
)

EDGE_FACTOR = 1.5             # edges between cage neighbours longer than 1.5 I_d are gaps, not faces
T = TypeVar("T")


class ObjectEstimation:
    def _start_estimate(self, now: float) -> None:
        """When transport begins: the reference ring, edges, contact normals and surface points the estimate
        compares with from here on, and the filter, started at the ring's centroid and the mission's yaw."""
        ring = self._member_positions(now)
        self.reference_ring = ring
        self.reference_ring_centre = ring_centroid(np.asarray(list(ring.values()))) if ring else self.hint
        self.ring_offset = self._dead_members_offset(ring, now)
        self.reference_centre = self._whole_ring_centre(self.reference_ring_centre, 0.0)
        self.reference_yaw = self.initial_yaw
        self.reference_edges = ring_edges(ring, self.reference_ring_centre, EDGE_FACTOR * self._spacing())
        self.reference_contacts = self._contact_angles(ring)
        self.reference_surface = self._member_surfaces(ring)
        self.reference_normals = surface_normals(self.reference_surface, ring)
        noise = 0.02
        self.filter = ObjectFilter(self.reference_centre[0], self.reference_centre[1], self.reference_yaw, noise)

    def _dead_members_offset(self, ring: Dict[int, Vec], now: float) -> Optional[Vec]:
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
        return c.sub(whole, ring_centroid(np.asarray(list(ring.values()))))

    def _whole_ring_centre(self, live_centre: Vec, turned: float) -> Vec:
        """The centroid of the whole ring, dead members included, from that of the live ones
        (_dead_members_offset); the live centroid itself when no member died before transport."""
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
        members' contact normals turned (params.small_cage_yaw); else from the edges between neighbouring
        members (estimator.edge_rotation), else from how the ring turned about the centroid."""
        if self.yaw_from_normals and self._small_cage():
            turned = edge_rotation(self._contact_angles(ring), self.reference_contacts)
            if turned is not None:
                return turned
        edges = ring_edges(ring, centre, EDGE_FACTOR * self._spacing())
        turned = edge_rotation(edges, self.reference_edges)
        if turned is not None:
            return turned
        return ring_rotation(ring, self.reference_ring, centre, self.reference_ring_centre)

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
        self.filter.predict(max(now - self.estimated_at, 1e-3))
        self.estimated_at = now
        ring = self._member_positions(now)
        if len(ring) >= (2 if self.ring_offset is not None else 3):    # 2: plus the dead (_dead_members_offset)
            centre = ring_centroid(np.asarray(list(ring.values())))
            turned = self._rotation_since_reference(ring, centre)
            centre = self._whole_ring_centre(centre, turned or 0.0)
            yaw = None if turned is None else self.reference_yaw + turned
            surface = self._surface_centre(ring, turned)
            if surface is not None:
                centre = surface
            self.filter.update(centre[0], centre[1], yaw, len(ring))
        return self.filter.pose

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
