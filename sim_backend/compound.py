"""Whether a compound object's parts make one piece.

A compound object is one rigid body. Parts that do not touch would be held together by nothing a robot can
feel: the cage forms round one part or in the gap between them, and the run reports a cage round empty
floor. So a scenario whose parts fall apart is refused, naming the part that floats free.

Plain Python, no numpy: a compound has a few parts of a few vertices, and scenario validation imports this.
"""
from __future__ import annotations

import math
from typing import List, Optional, Sequence, Tuple

Point = Tuple[float, float]
Circle = Tuple[float, float, float]                  # cx, cy, r

# Parts closer than this (m) count as touching: far below anything a robot's IR or body could pass through,
# far above the float error of offsets computed so that two faces coincide.
JOIN_GAP_M = 1e-3


def placed_outline(part) -> Tuple[Optional[List[Point]], Optional[Circle]]:
    """A part in the object's frame: ``(ring, None)`` for a box or polygon (counter-clockwise vertices),
    ``(None, (cx, cy, r))`` for a circle."""
    ox, oy = part.offset
    if part.shape == "circle":
        radius = part.radius if part.radius is not None else part.size
        return None, (float(ox), float(oy), float(radius))
    if part.shape == "box":
        w, h = part.size
        ring = [(-w / 2, -h / 2), (w / 2, -h / 2), (w / 2, h / 2), (-w / 2, h / 2)]
    else:
        ring = [(float(x), float(y)) for x, y in part.vertices]
        if _signed_area(ring) < 0:
            ring.reverse()
    yaw = math.radians(part.yaw_deg)
    c, s = math.cos(yaw), math.sin(yaw)
    return [(c * x - s * y + ox, s * x + c * y + oy) for x, y in ring], None


def first_loose_part(parts: Sequence) -> Optional[Tuple[int, int, float]]:
    """None when the parts form one piece (each touches another, chained to part 0). Otherwise
    ``(loose, nearest, gap_m)``: the part outside part 0's piece that lies nearest to it, the part of that
    piece it is nearest to, and the gap between them."""
    shapes = [placed_outline(part) for part in parts]
    piece, rest = {0}, set(range(1, len(shapes)))
    gaps = {}
    while rest:
        for i in piece:
            for j in rest:
                if (i, j) not in gaps:
                    gaps[(i, j)] = gap_between(shapes[i], shapes[j])
        joined = [j for j in rest if min(gaps[(i, j)] for i in piece) <= JOIN_GAP_M]
        if not joined:
            gap, nearest, loose = min((gaps[(i, j)], i, j) for i in piece for j in rest)
            return loose, nearest, gap
        piece.update(joined)
        rest.difference_update(joined)
    return None


def gap_between(a: Tuple[Optional[List[Point]], Optional[Circle]],
                b: Tuple[Optional[List[Point]], Optional[Circle]]) -> float:
    """The free space between two placed parts (0 when they touch or overlap)."""
    (ring_a, circle_a), (ring_b, circle_b) = a, b
    if circle_a is not None and circle_b is not None:
        return max(0.0, math.hypot(circle_a[0] - circle_b[0], circle_a[1] - circle_b[1]) - circle_a[2] - circle_b[2])
    if circle_a is not None or circle_b is not None:
        ring, circle = (ring_b, circle_a) if circle_a is not None else (ring_a, circle_b)
        return max(0.0, _point_to_polygon((circle[0], circle[1]), ring) - circle[2])
    if any(_inside(p, ring_b) for p in ring_a) or any(_inside(p, ring_a) for p in ring_b):
        return 0.0
    return min(_segment_distance(p, q, r, s) for p, q in _edges(ring_a) for r, s in _edges(ring_b))


def _edges(ring: List[Point]):
    return zip(ring, ring[1:] + ring[:1])


def _signed_area(ring: List[Point]) -> float:
    return sum(x0 * y1 - x1 * y0 for (x0, y0), (x1, y1) in _edges(ring)) / 2.0


def _inside(point: Point, ring: List[Point]) -> bool:
    """Even-odd ray casting."""
    x, y = point
    inside = False
    for (x0, y0), (x1, y1) in _edges(ring):
        if (y0 > y) != (y1 > y) and x < x0 + (y - y0) * (x1 - x0) / (y1 - y0):
            inside = not inside
    return inside


def _point_to_polygon(point: Point, ring: List[Point]) -> float:
    if _inside(point, ring):
        return 0.0
    return min(_point_to_segment(point, p, q) for p, q in _edges(ring))


def _point_to_segment(point: Point, p: Point, q: Point) -> float:
    dx, dy = q[0] - p[0], q[1] - p[1]
    length2 = dx * dx + dy * dy
    t = 0.0 if length2 == 0.0 else max(0.0, min(1.0, ((point[0] - p[0]) * dx + (point[1] - p[1]) * dy) / length2))
    return math.hypot(point[0] - (p[0] + t * dx), point[1] - (p[1] + t * dy))


def _segment_distance(p: Point, q: Point, r: Point, s: Point) -> float:
    if _segments_cross(p, q, r, s):
        return 0.0
    return min(_point_to_segment(p, r, s), _point_to_segment(q, r, s),
               _point_to_segment(r, p, q), _point_to_segment(s, p, q))


def _segments_cross(p: Point, q: Point, r: Point, s: Point) -> bool:
    def side(a: Point, b: Point, c: Point) -> float:
        return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])

    d1, d2, d3, d4 = side(r, s, p), side(r, s, q), side(p, q, r), side(p, q, s)
    return (d1 > 0) != (d2 > 0) and (d3 > 0) != (d4 > 0) and d1 != 0 and d2 != 0 and d3 != 0 and d4 != 0
