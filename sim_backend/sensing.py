"""Vectorised IR proximity: one ray per sensor, against circles (robots, round object parts) and segments
(object outlines, walls), with a broad phase so only nearby pairs are tested.

Response curve: onboard/hal/ir_curve.py (ARGoS's KheperaIV model), shared with the behaviours.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from onboard.hal import PROXIMITY_ANGLES_RAD
from onboard.hal.ir_curve import IR_RANGE_M, ir_response

SENSOR_ANGLES = np.asarray(PROXIMITY_ANGLES_RAD)


def ray_circle(origins: np.ndarray, dirs: np.ndarray, centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Distance along each ray (paired row by row with a circle) to the circle; 0 if inside, inf if missed."""
    f = origins - centres
    b = np.einsum("ij,ij->i", f, dirs)
    c = np.einsum("ij,ij->i", f, f) - radii * radii
    disc = b * b - c
    hit = np.full(len(origins), np.inf)
    outside = c > 0.0
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(disc)
    ok = outside & (disc >= 0.0) & (t >= 0.0)
    hit[ok] = t[ok]
    hit[~outside] = 0.0
    return hit


def ray_segment(origins: np.ndarray, dirs: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Distance along each ray (paired row by row with a segment) to the segment; inf if missed."""
    edge = ends - starts
    rel = starts - origins
    denom = dirs[:, 0] * edge[:, 1] - dirs[:, 1] * edge[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (rel[:, 0] * edge[:, 1] - rel[:, 1] * edge[:, 0]) / denom
        s = (rel[:, 0] * dirs[:, 1] - rel[:, 1] * dirs[:, 0]) / denom
    ok = (np.abs(denom) > 1e-12) & (t >= 0.0) & (s >= 0.0) & (s <= 1.0)
    return np.where(ok, t, np.inf)


@dataclass
class ObstacleGroup:
    """Non-robot obstacles in world coordinates at this instant: circles (M, 3) as x, y, r and segments
    (K, 4) as x0, y0, x1, y1. ``centre``/``radius`` bound the group so far-away robots skip it."""

    circles: np.ndarray
    segments: np.ndarray
    centre: Optional[np.ndarray] = None
    radius: float = np.inf
    # When the segments are closed outlines (an object's polygons, each ring's edges in a row): the index of
    # each ring's first segment. A sensor inside one then reads 0 m, as one inside a circle does (walls: None).
    outline_starts: Optional[np.ndarray] = None


class ProximityModel:
    """Computes all robots' 8 IR distances at once: against each other and against obstacle groups."""

    def __init__(self, robot_radius: float, ir_range: float = IR_RANGE_M):
        self.robot_radius = robot_radius
        self.ir_range = ir_range

    def distances(self, xy: np.ndarray, yaw: np.ndarray, robot_ranges: np.ndarray, present: np.ndarray,
                  groups: Sequence[ObstacleGroup] = ()) -> np.ndarray:
        """(N, 8) distance from each sensor to the nearest thing along its ray (inf if none within range).

        ``robot_ranges`` (N, N) are centre distances (from the range-and-bearing step); ``present`` masks
        robots that exist physically (a dead robot still blocks light, a removed one does not).
        """
        n = len(xy)
        angles = yaw[:, None] + SENSOR_ANGLES[None, :]
        dirs = np.stack([np.cos(angles), np.sin(angles)], axis=-1)              # (N, 8, 2)
        origins = xy[:, None, :] + self.robot_radius * dirs                      # sensors on the rim
        best = np.full((n, 8), np.inf)
        reach = 2.0 * self.robot_radius + self.ir_range
        close = (robot_ranges < reach) & present[None, :]
        np.fill_diagonal(close, False)
        i, j = np.nonzero(close)
        if len(i):
            o = origins[i].reshape(-1, 2)
            d = dirs[i].reshape(-1, 2)
            centres = np.repeat(xy[j], 8, axis=0)
            t = ray_circle(o, d, centres, np.full(len(o), self.robot_radius)).reshape(-1, 8)
            np.minimum.at(best, i, t)
        for group in groups:
            near = np.ones(n, dtype=bool)
            if group.centre is not None and np.isfinite(group.radius):
                near = np.hypot(*(xy - group.centre).T) < group.radius + reach
            rows = np.nonzero(near)[0]
            if len(rows) and (len(group.circles) or len(group.segments)):
                hits = self._static_hits(origins[rows], dirs[rows], group.circles, group.segments,
                                         group.outline_starts)
                best[rows] = np.minimum(best[rows], hits)
        best[best > self.ir_range] = np.inf
        return best

    def readings(self, xy: np.ndarray, yaw: np.ndarray, robot_ranges: np.ndarray,
                 groups: Sequence[ObstacleGroup], rng: np.random.Generator, noise_std: float) -> np.ndarray:
        """(N, 8) normalised readings as the HAL delivers them: response curve plus sensor noise, in [0, 1].
        Every robot (also a dead one) blocks light."""
        distances = self.distances(xy, yaw, robot_ranges, np.ones(len(xy), dtype=bool), groups)
        return np.clip(ir_response(distances) + rng.normal(0.0, noise_std, (len(xy), 8)), 0.0, 1.0)

    @staticmethod
    def _static_hits(origins: np.ndarray, dirs: np.ndarray, circles: np.ndarray, segments: np.ndarray,
                     outline_starts: Optional[np.ndarray] = None) -> np.ndarray:
        rays_o = origins.reshape(-1, 2)
        rays_d = dirs.reshape(-1, 2)
        r = len(rays_o)
        best = np.full(r, np.inf)
        if len(circles):
            ri = np.repeat(np.arange(r), len(circles))
            ci = np.tile(np.arange(len(circles)), r)
            t = ray_circle(rays_o[ri], rays_d[ri], circles[ci, :2], circles[ci, 2])
            best = np.minimum(best, t.reshape(r, -1).min(axis=1))
        if len(segments):
            ri = np.repeat(np.arange(r), len(segments))
            si = np.tile(np.arange(len(segments)), r)
            t = ray_segment(rays_o[ri], rays_d[ri], segments[si, :2], segments[si, 2:]).reshape(r, -1)
            best = np.minimum(best, t.min(axis=1))
            if outline_starts is not None and len(outline_starts):
                # A sensor pressed a little into the object (pymunk lets shapes overlap by its slop) found only
                # the outline's far side and read 0, "nothing there", on a robot pushing the box: a ray from
                # inside a closed outline crosses it an odd number of times.
                crossings = np.add.reduceat((t > 0.0) & np.isfinite(t), outline_starts, axis=1)
                best[(crossings % 2 == 1).any(axis=1)] = 0.0
        return best.reshape(origins.shape[:2])
