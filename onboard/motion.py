"""Turning a desired planar velocity into differential-drive wheel speeds.

Behaviours (and the paper) reason in terms of a holonomic velocity u in the robot frame; a KheperaIV is
non-holonomic. This is the one place that maps one onto the other.
"""
from __future__ import annotations

import math
from typing import Sequence, Tuple


def vector_to_wheels(ux: float, uy: float, speed_m_s: float, wheel_base_m: float,
                     turn_gain: float = 2.0, allow_reverse: bool = False,
                     turn_on_spot_beyond_rad: float = math.pi / 2) -> Tuple[float, float]:
    """Wheel speeds (left, right) that drive along (ux, uy) given in the robot frame.

    The robot turns toward the vector (angular speed ``turn_gain`` x heading error, rad/s) and moves forward
    with ``speed_m_s`` x cos(heading error) (so it turns on the spot when the target is behind it).
    ``speed_m_s`` is scaled down when the vector is shorter than 1, so small corrections stay small.
    Beyond a heading error of ``turn_on_spot_beyond_rad`` it turns on the spot (default: 90 degrees, where
    cos() reaches 0 anyway); a robot pressed against something turns before it drives on along it.
    With ``allow_reverse`` a target behind the robot is reached by backing up instead of turning round.
    """
    norm = math.hypot(ux, uy)
    if norm < 1e-9:
        return 0.0, 0.0
    heading_error = math.atan2(uy, ux)
    direction = 1.0
    if allow_reverse and abs(heading_error) > math.pi / 2:
        direction = -1.0
        heading_error = math.atan2(-uy, -ux)
    forward = 0.0
    if abs(heading_error) <= turn_on_spot_beyond_rad:
        forward = direction * speed_m_s * min(norm, 1.0) * max(0.0, math.cos(heading_error))
    omega = turn_gain * heading_error
    half_base = wheel_base_m / 2.0
    return forward - omega * half_base, forward + omega * half_base


def proximity_vector(values: Sequence[float], angles: Sequence[float]) -> Tuple[float, float]:
    """Sum of the IR readings as vectors pointing at what they see (robot frame)."""
    x = sum(v * math.cos(a) for v, a in zip(values, angles))
    y = sum(v * math.sin(a) for v, a in zip(values, angles))
    return x, y
