"""Estimating the object's pose from where the cage robots are, and filtering it over time.

The robots never see the object's true pose. Once the cage is closed they sit around the object at a
roughly constant offset, so the area centroid of the polygon through their positions approximates the
object's centroid (exactly, for symmetric objects and even spacing). While they push, robots slide along
the faces and open or close their gap to the object, which drags that centroid; how far the points of the
surface their IR sees moved along the object's normals (normal_displacement) does not follow them.
How far the object turned comes from how the edges between neighbouring members turned (edge_rotation):
robots on the same face stay on a line parallel to it. The ring's angular displacement about the centroid
(ring_rotation) is the fallback.
A constant-velocity Kalman filter (filterpy) smooths both: measurement noise comes from the positioning
noise, process noise from how fast a pushed object can plausibly accelerate.
"""
from __future__ import annotations

import math
from typing import Any, Dict, Optional, Sequence, Tuple

import numpy as np
from filterpy.kalman import KalmanFilter

from ...hal import wrap_angle


def offset_of_survivors(reference: Dict[int, Tuple[float, float]], members, centre_then: Tuple[float, float]
                        ) -> Tuple[float, float]:
    """From the ring centroid that ``members`` had in ``reference`` (their positions at some earlier moment) to
    ``centre_then``, the centre they surrounded at that moment. Added to those members' ring centroid now, it
    gives that centre now (turned by the object's turn since, where known): what a cage that lost members to
    a death counts on (estimation.py:_live_members_offset, which the spares run too)."""
    then = ring_centroid(np.asarray([reference[rid] for rid in members]))
    return (centre_then[0] - then[0], centre_then[1] - then[1])


def ring_centroid(points: np.ndarray) -> Tuple[float, float]:
    """Area centroid of the polygon through ``points`` (n, 2) taken in angular order around their mean.

    Falls back to the mean for fewer than 3 points or a degenerate polygon.
    """
    mean = points.mean(axis=0)
    if len(points) < 3:
        return float(mean[0]), float(mean[1])
    order = np.argsort(np.arctan2(points[:, 1] - mean[1], points[:, 0] - mean[0]))
    ring = points[order] - mean
    nxt = np.roll(ring, -1, axis=0)
    cross = ring[:, 0] * nxt[:, 1] - nxt[:, 0] * ring[:, 1]
    area = cross.sum() / 2.0
    if abs(area) < 1e-9:
        return float(mean[0]), float(mean[1])
    cx = ((ring[:, 0] + nxt[:, 0]) * cross).sum() / (6.0 * area)
    cy = ((ring[:, 1] + nxt[:, 1]) * cross).sum() / (6.0 * area)
    return float(cx + mean[0]), float(cy + mean[1])


def surrounds(points: Sequence[Sequence[float]], centre: Sequence[float]) -> bool:
    """True if ``points`` lie all round ``centre``: no gap of half a turn or more between their directions
    seen from it. Points along one face of a large object do not surround its centre; their ring centroid
    lies on that face."""
    if len(points) < 3:
        return False
    angles = sorted(math.atan2(q[1] - centre[1], q[0] - centre[0]) for q in points)
    gaps = [b - a for a, b in zip(angles, angles[1:])]
    gaps.append(angles[0] + 2.0 * math.pi - angles[-1])
    return max(gaps) < math.pi


def encloses(polygon: Sequence[Sequence[float]], point: Sequence[float]) -> bool:
    """True if ``point`` lies inside the polygon through ``polygon``'s vertices in order (ray casting)."""
    inside = False
    x, y = point[0], point[1]
    for i in range(len(polygon)):
        (x0, y0), (x1, y1) = polygon[i - 1][:2], polygon[i][:2]
        if (y0 > y) != (y1 > y) and x < x0 + (y - y0) * (x1 - x0) / (y1 - y0):
            inside = not inside
    return inside


def ring_rotation(now: Dict[int, Sequence[float]], reference: Dict[int, Sequence[float]],
                  centre_now: Sequence[float], centre_ref: Sequence[float]) -> Optional[float]:
    """Circular mean of how far each member turned around the centroid since the reference (rad)."""
    common = [k for k in now if k in reference]
    if len(common) < 2:
        return None
    s = c = 0.0
    for k in common:
        a_now = math.atan2(now[k][1] - centre_now[1], now[k][0] - centre_now[0])
        a_ref = math.atan2(reference[k][1] - centre_ref[1], reference[k][0] - centre_ref[0])
        d = a_now - a_ref
        s, c = s + math.sin(d), c + math.cos(d)
    return math.atan2(s, c)


def ring_edges(points: Dict[int, Sequence[float]], centre: Sequence[float], max_length: float) -> Dict[tuple, float]:
    """Direction (rad) of each edge between robots adjacent around ``centre`` and at most ``max_length``
    apart, keyed by the (from, to) ids in counter-clockwise order."""
    ids = sorted(points, key=lambda k: math.atan2(points[k][1] - centre[1], points[k][0] - centre[0]))
    edges = {}
    for a, b in zip(ids, ids[1:] + ids[:1]):
        dx, dy = points[b][0] - points[a][0], points[b][1] - points[a][1]
        if a != b and math.hypot(dx, dy) <= max_length:
            edges[(a, b)] = math.atan2(dy, dx)
    return edges


def edge_rotation(now: Dict[tuple, float], reference: Dict[tuple, float]) -> Optional[float]:
    """How far the object turned, from how the edges between neighbouring cage robots turned.

    Two robots pressed against the same flat face stay on a line parallel to it even when they slide
    along it, so their edge turns exactly as the object does; an edge across a corner does not, and the
    median rejects those. Needs at least two edges seen both now and at the reference.
    """
    return median_turn((now, reference))


def median_turn(*pairs: Tuple[Dict[Any, float], Dict[Any, float]]) -> Optional[float]:
    """The median of how far every angle turned since its reference, over all ``(now, reference)`` pairs of
    dicts together (keys seen in both), or None for fewer than two."""
    turns = sorted(wrap_angle(now[k] - reference[k]) for now, reference in pairs for k in now if k in reference)
    if len(turns) < 2:
        return None
    if turns[-1] - turns[0] > math.pi:
        # Spread over more than half a turn: about half a turn from the reference (a box turned twice by 90
        # degrees), some edges read +179 degrees and others -179, and the median of the sorted values fell
        # between them, near 0 (paper-25-straight_rot seed 7 then pushed with its estimate 0.35 m off). Each
        # turn is taken about their circular mean instead; turns within half a turn are left as they were.
        mean = math.atan2(sum(map(math.sin, turns)), sum(map(math.cos, turns)))
        turns = sorted(mean + wrap_angle(turn - mean) for turn in turns)
        middle = len(turns) // 2
        return wrap_angle(turns[middle] if len(turns) % 2 else (turns[middle - 1] + turns[middle]) / 2.0)
    middle = len(turns) // 2          # the median of the sorted turns (np.median's value, without numpy)
    return turns[middle] if len(turns) % 2 else (turns[middle - 1] + turns[middle]) / 2.0


def surface_normals(surfaces: Dict[int, Sequence[float]], positions: Dict[int, Sequence[float]]
                    ) -> Dict[int, Tuple[float, float]]:
    """Outward unit normal of the object at each surface point: from the point back to the robot that saw it
    (the IR's direction to the object is the face's inward normal, to within how the readings spread)."""
    normals = {}
    for k, point in surfaces.items():
        if k in positions:
            nx, ny = positions[k][0] - point[0], positions[k][1] - point[1]
            length = math.hypot(nx, ny)
            if length > 1e-9:
                normals[k] = (nx / length, ny / length)
    return normals


def normal_displacement(now: Dict[int, Sequence[float]], reference: Dict[int, Sequence[float]],
                        normals: Dict[int, Sequence[float]], centre_ref: Sequence[float], rotation: float,
                        min_information: float = 0.5) -> Optional[Tuple[float, float]]:
    """The object's translation since the reference, from how far its surface points moved along the
    object's normals (least squares over the points seen both now and then, after turning the reference
    points and normals by ``rotation`` about ``centre_ref``).

    A robot that slides along a face -- a side robot running ahead of a heavy object, a rear pusher pushed
    sideways -- sees a point that moves along the face, not across it, so it does not drag this estimate;
    the centroid of the robots' positions follows it. And a surface point does not move when its robot
    falls back from the object or closes in on it. None when the normals do not pin both axes
    (``min_information``: the smallest eigenvalue of sum n n^T, about half a point's worth of normals
    along the weaker axis).
    """
    c, s = math.cos(rotation), math.sin(rotation)
    rows = []       # per point: its normal now and how far it moved along it
    for k, p in now.items():
        if k not in reference or k not in normals:
            continue
        qx, qy = reference[k][0] - centre_ref[0], reference[k][1] - centre_ref[1]
        nx, ny = c * normals[k][0] - s * normals[k][1], s * normals[k][0] + c * normals[k][1]
        along = nx * (p[0] - centre_ref[0] - (c * qx - s * qy)) + ny * (p[1] - centre_ref[1] - (s * qx + c * qy))
        rows.append((nx, ny, along))
    moved = _fit_along_normals(rows, min_information)
    if moved is None or len(rows) <= MIN_POINTS_TO_DROP_ONE:
        return moved
    # One point far off the fit is a robot that no longer sees the face it saw (it slid round a corner, or
    # sees a neighbour): on paper-25-zigzag one such point of 18 pulled the estimate 0.13 m behind the box.
    residuals = [abs(along - nx * moved[0] - ny * moved[1]) for nx, ny, along in rows]
    worst = max(range(len(rows)), key=residuals.__getitem__)
    if residuals[worst] <= OUTLIER_M:
        return moved
    return _fit_along_normals(rows[:worst] + rows[worst + 1:], min_information) or moved


# normal_displacement leaves out the one point farthest off the fit when it is off by more than OUTLIER_M, and
# more than MIN_POINTS_TO_DROP_ONE points were seen: a surface point's own noise is about a centimetre.
OUTLIER_M = 0.05
MIN_POINTS_TO_DROP_ONE = 5


def _fit_along_normals(rows: Sequence[Tuple[float, float, float]],
                       min_information: float) -> Optional[Tuple[float, float]]:
    """Least squares: the translation d with n . d closest to each row's distance along its normal n."""
    a11 = a12 = a22 = b1 = b2 = 0.0
    for nx, ny, along in rows:
        a11, a12, a22 = a11 + nx * nx, a12 + nx * ny, a22 + ny * ny
        b1, b2 = b1 + nx * along, b2 + ny * along
    half_trace, det = (a11 + a22) / 2.0, a11 * a22 - a12 * a12
    weaker = half_trace - math.sqrt(max(half_trace * half_trace - det, 0.0))
    if weaker < min_information:
        return None
    return (a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det


class ObjectFilter:
    """Constant-velocity Kalman filter on the object's pose: state [x, y, yaw, vx, vy, omega]."""

    def __init__(self, x: float, y: float, yaw: float, position_noise_m: float = 0.02,
                 yaw_noise_rad: float = 0.05, accel_noise: float = 0.05):
        kf = KalmanFilter(dim_x=6, dim_z=3)
        kf.x = np.array([x, y, yaw, 0.0, 0.0, 0.0])
        kf.H = np.hstack([np.eye(3), np.zeros((3, 3))])
        kf.P = np.diag([0.5, 0.5, 0.3, 0.05, 0.05, 0.05]) ** 2
        kf.R = np.diag([position_noise_m, position_noise_m, yaw_noise_rad]) ** 2
        self.kf = kf
        self.accel_noise = accel_noise
        self._model_dt: Optional[float] = None   # the dt that kf.F and kf.Q were built for

    def predict(self, dt: float) -> None:
        kf = self.kf
        if dt != self._model_dt:                 # robots step at a fixed rate: build F and Q once per dt
            self._model_dt = dt
            F = np.eye(6)
            F[0, 3] = F[1, 4] = F[2, 5] = dt
            # Piecewise-constant white acceleration: an object pushed by robots speeds up and stops gently.
            q = self.accel_noise ** 2
            block = np.array([[dt ** 4 / 4, dt ** 3 / 2], [dt ** 3 / 2, dt ** 2]]) * q
            Q = np.zeros((6, 6))
            for i in range(3):
                Q[np.ix_([i, i + 3], [i, i + 3])] = block
            kf.F, kf.Q = F, Q
        kf.predict()

    def update(self, x: float, y: float, yaw: Optional[float], members: int) -> None:
        kf = self.kf
        # Yaw is an angle: measure it as the nearest equivalent of the current estimate.
        yaw_state = kf.x[2]
        measured_yaw = yaw_state if yaw is None else yaw_state + wrap_angle(yaw - yaw_state)
        scale = 1.0 / max(1.0, math.sqrt(members))     # more members, better average
        r = np.diag(np.diag(kf.R)) * scale ** 2
        if yaw is None:
            r[2, 2] = 1e6
        kf.update(np.array([x, y, measured_yaw]), R=r)

    def halt(self) -> None:
        """Forget the velocities (keeping the pose and the covariance): after a pause whose motion is unknown."""
        self.kf.x[3:6] = 0.0

    def move_to(self, x: float, y: float) -> None:
        """Put the position at (x, y), keeping the yaw, the velocities and the covariance."""
        self.kf.x[0], self.kf.x[1] = x, y

    def hold_yaw(self, yaw: float) -> None:
        """Put the yaw at ``yaw`` and stop it turning: with no yaw measured it would run on at its last rate."""
        self.kf.x[2], self.kf.x[5] = yaw, 0.0

    def reset(self, x: float, y: float, yaw: float) -> None:
        self.kf.x = np.array([x, y, yaw, 0.0, 0.0, 0.0])

    @property
    def pose(self) -> Tuple[float, float, float]:
        x, y, yaw = self.kf.x[:3]
        return float(x), float(y), float(wrap_angle(yaw))
