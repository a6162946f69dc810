"""Recesses in an object's outline that a robot fits into: room inside the convex hull, off the object.

The swarm estimates the object from where its members are. A member that cages inside a recess (the notch of
a U, the inner corner of an L) sits well inside the ring the others form, and pulls the estimate off the
object's centroid; such runs often end 0.1-0.2 m off (docs/behaviour.md section 8). A recess narrower than
a robot is harmless: no member gets in.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
from matplotlib.path import Path as MplPath

from .shapes import Geometry, contains

GRID_CELLS = 200        # the hull's bounding box is sampled on about this many cells a side
CHUNK = 4096            # points per batch of point-to-segment distances (bounds the memory for long outlines)


def widest_recess(geometry: Geometry, hull: np.ndarray, clearance: float, radius: float) -> Optional[float]:
    """The width (m) of the widest room inside ``hull`` where a robot stands ``clearance`` off the object
    with its whole body (``radius``) inside the hull; None when there is no such room."""
    lo, hi = hull.min(axis=0), hull.max(axis=0)
    step = max(float(np.max(hi - lo)) / GRID_CELLS, 1e-3)
    xs = np.arange(lo[0] + step / 2, hi[0], step)
    ys = np.arange(lo[1] + step / 2, hi[1], step)
    points = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    points = points[MplPath(hull).contains_points(points) & ~contains(geometry, points)]
    if len(points) == 0:
        return None
    hull_edges = np.hstack([hull, np.roll(hull, -1, axis=0)])
    points = points[_distance_to(points, hull_edges) >= radius]
    if len(points) == 0:
        return None
    off_object = _distance_to(points, geometry.segments())
    for cx, cy, r in geometry.circles:
        off_object = np.minimum(off_object, np.hypot(points[:, 0] - cx, points[:, 1] - cy) - r)
    room = off_object[off_object >= clearance]
    return float(2.0 * room.max()) if len(room) else None


def _distance_to(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Each point's distance (M,) to the nearest of the segments (K, 4) rows x0, y0, x1, y1 (inf if none)."""
    if len(segments) == 0:
        return np.full(len(points), np.inf)
    start, delta = segments[:, :2], segments[:, 2:] - segments[:, :2]
    length2 = np.maximum((delta ** 2).sum(axis=1), 1e-18)
    nearest = np.empty(len(points))
    for first in range(0, len(points), CHUNK):
        chunk = points[first:first + CHUNK, None, :] - start[None, :, :]              # (m, K, 2)
        t = np.clip((chunk * delta[None]).sum(axis=2) / length2[None], 0.0, 1.0)
        gap = chunk - t[:, :, None] * delta[None]
        nearest[first:first + CHUNK] = np.sqrt((gap ** 2).sum(axis=2)).min(axis=1)
    return nearest
