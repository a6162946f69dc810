"""Whether a polygon's outline is simple, and its signed area: plain 2-D geometry on vertex lists.

Scenario validation refuses a polygon whose outline meets itself (a repeated vertex, a spike of no width, two
edges that cross or touch) and one of no area; ``shapes.py`` uses the signed area to orient rings. Plain
Python, no numpy: a scenario's polygon has a few vertices, and validation imports this.
"""
from __future__ import annotations

import math
from typing import List, Optional, Tuple

# Closer than this (m), two edges of an outline that are not neighbours count as touching: a micron, far below
# any robot's sensing, far above float noise for coordinates within MAX_EXTENT_M (scenario.py).
TOUCH_M = 1e-6


def outline_fault(vertices: List[Tuple[float, float]]) -> Optional[str]:
    """Why a polygon's outline is not simple (a vertex repeated, an edge folding back on the one before, two
    edges that cross or touch), or None. Each of these made an object of several pieces, or a zero-width
    spike, that the simulator built without a word."""
    n = len(vertices)
    edges = [(vertices[i], vertices[(i + 1) % n]) for i in range(n)]
    for i, (a, b) in enumerate(edges):
        if math.dist(a, b) < TOUCH_M:
            if i == n - 1:
                return "the last vertex repeats the first (leave it out: the outline closes by itself)"
            return f"vertices {i} and {i + 1} are the same point ({math.dist(a, b):.2g} m apart): leave one out"
    for i in range(n):
        (a, b), (_, c) = edges[i - 1], edges[i]
        if abs(_orient(a, b, c)) < TOUCH_M * math.dist(a, b) and (b[0] - a[0]) * (c[0] - b[0]) + \
                (b[1] - a[1]) * (c[1] - b[1]) < 0:
            return f"the outline turns back on itself at vertex {i} (a spike of no width)"
    for i in range(n):
        for j in range(i + 2, n):
            if i == 0 and j == n - 1:
                continue   # adjacent through the closing vertex
            if _crosses(*edges[i], *edges[j]):
                return f"edges {i} and {j} cross"
            if _segment_distance(*edges[i], *edges[j]) < TOUCH_M:
                return f"edges {i} and {j} touch"
    return None


def _orient(a, b, c) -> float:
    return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])


def _crosses(p1, p2, q1, q2) -> bool:
    return _orient(p1, p2, q1) * _orient(p1, p2, q2) < 0 and _orient(q1, q2, p1) * _orient(q1, q2, p2) < 0


def _point_segment_distance(p, a, b) -> float:
    dx, dy = b[0] - a[0], b[1] - a[1]
    t = max(0.0, min(1.0, ((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / (dx * dx + dy * dy)))
    return math.hypot(p[0] - a[0] - t * dx, p[1] - a[1] - t * dy)


def _segment_distance(p1, p2, q1, q2) -> float:
    """Between two segments that do not cross: the least of the end-to-segment distances."""
    return min(_point_segment_distance(p1, q1, q2), _point_segment_distance(p2, q1, q2),
               _point_segment_distance(q1, p1, p2), _point_segment_distance(q2, p1, p2))


def polygon_area(vertices: List[Tuple[float, float]]) -> float:
    """Signed area (shoelace); positive when counter-clockwise."""
    total = 0.0
    for (x0, y0), (x1, y1) in zip(vertices, vertices[1:] + vertices[:1]):
        total += x0 * y1 - x1 * y0
    return total / 2.0
