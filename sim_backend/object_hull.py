"""The object's convex hull and what the transport preflight reads off it: perimeter, faces, narrowest width,
and the ring a cage lies on. Pure geometry of the scenario's object, no robots."""
from __future__ import annotations

import math
from typing import List, Tuple

import numpy as np

from .shapes import Geometry

CAGE_GAP_M = 0.02               # caging robots hold about this far off the surface (keep_gap_while_caging)
FACE_SHARE = 0.1                # a hull edge is a face (its normal an axis to push along) from this share of the hull


def hull_width(hull: np.ndarray) -> float:
    """The narrowest width of a convex polygon: over its edges, the farthest vertex from the edge's line."""
    if len(hull) < 3:
        return 0.0
    edges = np.roll(hull, -1, axis=0) - hull
    lengths = np.hypot(*edges.T)
    keep = lengths > 1e-12
    edges, starts, lengths = edges[keep], hull[keep], lengths[keep]
    offsets = hull[None, :, :] - starts[:, None, :]                       # every vertex from every edge's start
    distances = np.abs(edges[:, None, 0] * offsets[:, :, 1] - edges[:, None, 1] * offsets[:, :, 0])
    return float(np.min(distances.max(axis=1) / lengths))


def face_normals(hull: np.ndarray) -> List[float]:
    """Outward normal angles (degrees, object frame) of the hull's long edges: the directions a push along
    which keeps a face square to it. Empty for a round object: no edge is long."""
    normals, lengths = hull_edges(hull)
    return [normal for normal, length in zip(normals, lengths) if length >= FACE_SHARE * sum(lengths)]


def hull_edges(hull: np.ndarray) -> Tuple[List[float], List[float]]:
    """Each hull edge's outward normal angle (degrees, object frame) and its length."""
    edges = np.roll(hull, -1, axis=0) - hull
    return [math.degrees(math.atan2(-ex, ey)) for ex, ey in edges.tolist()], np.hypot(*edges.T).tolist()


def cage_ring(hull: np.ndarray, robot_radius: float) -> float:
    """The length of the ring the cage lies on: the convex hull grown by a robot's radius and its gap."""
    return perimeter(hull) + 2.0 * math.pi * (robot_radius + CAGE_GAP_M)


def object_hull(geometry: Geometry) -> np.ndarray:
    """The convex hull of the object's outline (circles included as polygons), counter-clockwise."""
    return convex_hull(np.vstack(geometry.outline_polygons()))


def hull_perimeter(geometry: Geometry) -> float:
    """Perimeter of the convex hull of the object's outline."""
    return perimeter(object_hull(geometry))


def perimeter(hull: np.ndarray) -> float:
    return float(np.sum(np.hypot(*(np.roll(hull, -1, axis=0) - hull).T)))


def convex_hull(points: np.ndarray) -> np.ndarray:
    """Andrew's monotone chain: the hull's vertices in counter-clockwise order."""
    ordered = sorted(set(map(tuple, np.round(points, 9).tolist())))
    if len(ordered) < 3:
        return np.asarray(ordered, dtype=float)

    def half(seq):
        chain: List[tuple] = []
        for p in seq:
            while len(chain) >= 2 and _cross(chain[-2], chain[-1], p) <= 0:
                chain.pop()
            chain.append(p)
        return chain[:-1]

    return np.asarray(half(ordered) + half(reversed(ordered)), dtype=float)


def _cross(o: tuple, a: tuple, b: tuple) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
