"""Object geometry: a scenario's ``object`` -> convex pieces for physics, outlines and circles for sensing.

Everything is expressed in the object's frame with the origin at the object's area centroid, so the
body's position *is* the centroid the transport path refers to.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import List, Sequence, Tuple

import numpy as np
import pymunk.autogeometry
from matplotlib.path import Path as MplPath

from .object_spec import ObjectPart, ObjectSpec
from .outline import polygon_area

Point = Tuple[float, float]
CIRCLE_OUTLINE_SEGMENTS = 32


@dataclass
class Geometry:
    """Primitives in the object frame (origin at the area centroid)."""

    convex_pieces: List[np.ndarray] = field(default_factory=list)  # (k, 2) CCW convex polygons, for physics
    outlines: List[np.ndarray] = field(default_factory=list)        # (k, 2) closed-ring vertices, for IR + plots
    circles: List[Tuple[float, float, float]] = field(default_factory=list)   # (cx, cy, r)
    area_m2: float = 0.0
    mean_radius_m: float = 0.0       # mean distance of the footprint from the centroid (friction torque)
    radius_of_gyration_m: float = 0.0
    bounding_radius_m: float = 0.0   # farthest point from the centroid

    def outline_polygons(self) -> List[np.ndarray]:
        """Outlines plus circles as polygons (for drawing)."""
        rings = list(self.outlines)
        for cx, cy, r in self.circles:
            a = np.linspace(0.0, 2.0 * math.pi, CIRCLE_OUTLINE_SEGMENTS, endpoint=False)
            rings.append(np.column_stack([cx + r * np.cos(a), cy + r * np.sin(a)]))
        return rings

    def segments(self) -> np.ndarray:
        """All outline edges as (K, 4) rows x0, y0, x1, y1."""
        rows = [np.hstack([ring, np.roll(ring, -1, axis=0)]) for ring in self.outlines]
        return np.vstack(rows) if rows else np.zeros((0, 4))


def build_geometry(spec: ObjectSpec) -> Geometry:
    raw = Geometry()
    for part in parts_of(spec):
        _add_part(raw, part)
    return _recentre(raw)


def dimension_field(spec: ObjectSpec) -> str:
    """The scenario field that sets the object's size, for an error about its size."""
    if spec.shape in ("box", "circle"):
        return "object.radius" if spec.radius is not None else "object.size"
    return {"polygon": "object.vertices", "compound": "object.parts"}.get(spec.shape, "object.scale")


def parts_of(spec: ObjectSpec) -> List[ObjectPart]:
    """The object as a list of simple parts (box / circle / polygon) in its own frame."""
    s = spec.scale
    if spec.shape == "compound":
        return list(spec.parts or [])
    if spec.shape in ("box", "circle", "polygon"):
        return [ObjectPart(shape=spec.shape, size=spec.size, radius=spec.radius, vertices=spec.vertices)]
    if spec.shape == "cloud":
        # A 2 x 2 m square with three r = 0.3 m cylinders centred on each side at -0.5, 0, +0.5 along it.
        parts = [ObjectPart(shape="box", size=(2.0 * s, 2.0 * s))]
        for along in (-0.5, 0.0, 0.5):
            for cx, cy in ((along, 1.0), (along, -1.0), (1.0, along), (-1.0, along)):
                parts.append(ObjectPart(shape="circle", radius=0.3 * s, offset=(cx * s, cy * s)))
        return parts
    if spec.shape == "box_rotation":
        # Eight 0.8 x 0.8 m squares rotated 45 degrees, centred on a 1 m circle every 45 degrees.
        return [ObjectPart(shape="box", size=(0.8 * s, 0.8 * s), yaw_deg=45.0,
                           offset=(s * math.cos(k * math.pi / 4), s * math.sin(k * math.pi / 4)))
                for k in range(8)]
    if spec.shape == "clover":
        # A 0.5 x 0.5 m square with four r = 0.6 m cylinders centred 0.7 m from the middle every 90 degrees.
        parts = [ObjectPart(shape="box", size=(0.5 * s, 0.5 * s))]
        for k in range(4):
            a = k * math.pi / 2
            centre = (0.7 * s * math.cos(a), 0.7 * s * math.sin(a))
            parts.append(ObjectPart(shape="circle", radius=0.6 * s, offset=centre))
        return parts
    raise ValueError(f"unknown shape {spec.shape}")


def _add_part(geom: Geometry, part: ObjectPart) -> None:
    yaw = math.radians(part.yaw_deg)
    c, s = math.cos(yaw), math.sin(yaw)
    rot = np.array([[c, -s], [s, c]])
    offset = np.asarray(part.offset, dtype=float)
    if part.shape == "circle":
        radius = part.radius if part.radius is not None else part.size
        geom.circles.append((float(offset[0]), float(offset[1]), float(radius)))
        return
    if part.shape == "box":
        w, h = part.size
        ring = np.array([[-w / 2, -h / 2], [w / 2, -h / 2], [w / 2, h / 2], [-w / 2, h / 2]])
    else:
        ring = np.asarray(part.vertices, dtype=float)
        if polygon_area([tuple(v) for v in ring]) < 0:
            ring = ring[::-1]
    ring = ring @ rot.T + offset
    geom.outlines.append(ring)
    geom.convex_pieces.extend(convex_pieces(ring))


def convex_pieces(ring: np.ndarray) -> List[np.ndarray]:
    """Split a CCW simple polygon into convex pieces (pymunk's approximate decomposition)."""
    if _is_convex(ring):
        return [ring]
    closed = [tuple(p) for p in ring] + [tuple(ring[0])]
    pieces = pymunk.autogeometry.convex_decomposition(closed, 1e-4)
    return [np.array([(v.x, v.y) for v in piece[:-1]]) for piece in pieces]


def _is_convex(ring: np.ndarray) -> bool:
    edges = np.roll(ring, -1, axis=0) - ring
    cross = edges[:, 0] * np.roll(edges, -1, axis=0)[:, 1] - edges[:, 1] * np.roll(edges, -1, axis=0)[:, 0]
    return bool(np.all(cross >= -1e-12))


def contains(geom: Geometry, points: np.ndarray) -> np.ndarray:
    """Which points (M, 2) lie inside the union of the object's parts."""
    inside = np.zeros(len(points), dtype=bool)
    for ring in geom.outlines:
        inside |= MplPath(ring).contains_points(points)
    for cx, cy, r in geom.circles:
        inside |= (points[:, 0] - cx) ** 2 + (points[:, 1] - cy) ** 2 <= r * r
    return inside


def _recentre(geom: Geometry, resolution: int = 240) -> Geometry:
    """Measure area, centroid and spread by sampling the footprint, then move the origin to the centroid.

    Sampling handles overlapping parts (compound, cloud, clover) without polygon boolean operations. The
    samples are the centres of a grid of cells over the bounding box, so none lies on the outline (where
    inside-tests disagree from edge to edge: sampling the corners made a box's centroid half a cell low) and
    the grid is symmetric: a box's centroid and area come out exact.
    """
    points = _extent_points(geom)
    lo, hi = points.min(axis=0), points.max(axis=0)
    step = (hi - lo) / resolution
    xs = lo[0] + (np.arange(resolution) + 0.5) * step[0]
    ys = lo[1] + (np.arange(resolution) + 0.5) * step[1]
    grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    inside = grid[contains(geom, grid)]
    cell = step[0] * step[1]
    centroid = inside.mean(axis=0)
    shifted = inside - centroid
    dist = np.hypot(shifted[:, 0], shifted[:, 1])
    moved = Geometry(
        convex_pieces=[p - centroid for p in geom.convex_pieces],
        outlines=[p - centroid for p in geom.outlines],
        circles=[(cx - centroid[0], cy - centroid[1], r) for cx, cy, r in geom.circles],
        area_m2=float(len(inside) * cell),
        mean_radius_m=float(dist.mean()),
        radius_of_gyration_m=float(np.sqrt(np.mean(dist ** 2))),
    )
    moved.bounding_radius_m = float(np.max(np.hypot(*(_extent_points(moved).T))))
    return moved


def _extent_points(geom: Geometry) -> np.ndarray:
    points: List[Sequence[float]] = [p for ring in geom.outlines for p in ring]
    for cx, cy, r in geom.circles:
        points += [(cx - r, cy - r), (cx + r, cy + r), (cx - r, cy + r), (cx + r, cy - r)]
    return np.asarray(points, dtype=float)


def extent_at(geom: Geometry, x: float, y: float, yaw_rad: float) -> Tuple[float, float, float, float]:
    """The axis-aligned box ``(xmin, ymin, xmax, ymax)`` the object covers with its centroid at (x, y) and
    turned by ``yaw_rad``."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    xs: List[float] = []
    ys: List[float] = []
    for ring in geom.outlines:
        xs += list(x + c * ring[:, 0] - s * ring[:, 1])
        ys += list(y + s * ring[:, 0] + c * ring[:, 1])
    for cx, cy, r in geom.circles:
        px, py = x + c * cx - s * cy, y + s * cx + c * cy
        xs += [px - r, px + r]
        ys += [py - r, py + r]
    return min(xs), min(ys), max(xs), max(ys)
