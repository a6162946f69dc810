"""The paper's control terms, each under its paper name. All vectors are (x, y) tuples in the world frame.

u_fp = u_t + u_f + u_cp   (push, Eq. fpush)        u_fr = u_r + u_f + u_cr   (rotate, Eq. frotate)
Caging uses the edge-following input u = perp(x_n) + (|x_n| - I_d) x_n and the distance correction perp(x_o).
"""
from __future__ import annotations

import math
from typing import Dict, Iterable, Tuple

Vec = Tuple[float, float]
ZERO: Vec = (0.0, 0.0)


def add(*vs: Vec) -> Vec:
    return (sum(v[0] for v in vs), sum(v[1] for v in vs))


def sub(a: Vec, b: Vec) -> Vec:
    return (a[0] - b[0], a[1] - b[1])


def scale(v: Vec, k: float) -> Vec:
    return (v[0] * k, v[1] * k)


def norm(v: Vec) -> float:
    return math.hypot(v[0], v[1])


def unit(v: Vec) -> Vec:
    n = norm(v)
    return (v[0] / n, v[1] / n) if n > 1e-12 else ZERO


def perp(v: Vec) -> Vec:
    """v rotated by +90 degrees (counter-clockwise)."""
    return (-v[1], v[0])


def rotate(v: Vec, angle: float) -> Vec:
    c, s = math.cos(angle), math.sin(angle)
    return (c * v[0] - s * v[1], s * v[0] + c * v[1])


def angle_between(a: Vec, b: Vec) -> float:
    """Unsigned angle between two vectors, in [0, pi]."""
    na, nb = norm(a), norm(b)
    if na < 1e-12 or nb < 1e-12:
        return 0.0
    c = (a[0] * b[0] + a[1] * b[1]) / (na * nb)
    return math.acos(max(-1.0, min(1.0, c)))


# --- pushing and rotating (Eqs. force_push, center_push, force_rot, center_rot, formation) -------------
def u_t(centroid: Vec, tau_p: Vec, k_t: float, d_tol: float) -> Vec:
    """Force toward the local target tau_pl = x_i + (tau_p - C_o): the same direction for every robot."""
    to_target = sub(tau_p, centroid)
    if norm(to_target) <= d_tol:
        return ZERO
    return scale(unit(to_target), k_t)


def is_effective_pusher(x_o: Vec, tau_direction: Vec, theta_p: float) -> bool:
    """A robot pushes effectively when angle(x_o, tau_p) < theta_p: the object lies between it and the target."""
    return angle_between(x_o, tau_direction) < theta_p


def u_cp(x_o: Vec, effective: bool, k_cp_effective: float, k_cp_other: float) -> Vec:
    """Stay in contact with the object while pushing (gain per Table 1: 40 below theta_p, 20 otherwise).

    Deviation: the printed Eq. center_push gives 0 at or above theta_p; we follow Table 1, which gives
    K_cp = 20 there, so every robot keeps contact (docs/behaviour.md section 6, "u_cp never zero")."""
    return scale(unit(x_o), k_cp_effective if effective else k_cp_other)


def u_r(position: Vec, centroid: Vec, yaw_error: float, k_r: float, tolerance: float) -> Vec:
    """Tangential input around the centroid that turns the object toward the target yaw.

    Deviation: the printed Eq. force_rot is K_r perp(unit(x_i - C_o)) in one fixed (counter-clockwise)
    direction, on while angle(tau_p, C_o) < theta_r; here its sign follows the yaw error and it is 0 within
    ``tolerance`` (docs/behaviour.md section 6, "u_r signed by the yaw error")."""
    if abs(yaw_error) <= tolerance:
        return ZERO
    radial = unit(sub(position, centroid))
    return scale(perp(radial), k_r if yaw_error > 0 else -k_r)


def u_cr(x_o: Vec, k_cr: float) -> Vec:
    """Stay in contact with the object while rotating."""
    return scale(unit(x_o), k_cr)


def u_f(current: Dict[int, Vec], reference: Dict[int, Vec], k_f: float, rotation: float = 0.0) -> Vec:
    """Keep the formation recorded when transport began.

    For each neighbour j recorded then (world-frame vector r_j0 from this robot to j, |r_j0| = d_j), pull the
    current vector r_j back to r_j0 turned by the object's estimated ``rotation``: K_f (r_j - R r_j0) / d_j.
    Both the distance and the bearing are corrected (the paper's two terms); see docs/behaviour.md for why
    we use this vector form instead of the paper's printed expression.
    """
    total = ZERO
    for j, r_ref in reference.items():
        r_now = current.get(j)
        if r_now is None:
            continue
        d_ref = norm(r_ref)
        if d_ref < 1e-6:
            continue
        error = sub(r_now, rotate(r_ref, rotation))
        total = add(total, scale(error, k_f / d_ref))
    return total


# --- caging -------------------------------------------------------------------------------------------
def u_edge_follow(x_n: Vec, inter_robot_distance: float, direction: int) -> Vec:
    """Orbit the nearest branch neighbour at I_d: perp(x_n) + (|x_n| - I_d) x_n (direction +1 = CCW)."""
    return add(scale(perp(x_n), -direction), scale(x_n, norm(x_n) - inter_robot_distance))


def u_distance_correction(x_o: Vec, distance_error: float, gain: float) -> Vec:
    """Slide along the object (perp(x_o)) to bring the branch neighbour to distance I_d."""
    return scale(perp(unit(x_o)), gain * distance_error)


def u_keep_gap(x_o: Vec, reading: float, target_reading: float, gain: float) -> Vec:
    """Not in the paper: hold the strongest IR reading of the object at ``target_reading`` -- in when
    farther, out when closer. A robot sliding along the object with the pure tangent perp(x_o) drifts into
    it (x_o is only as good as a few saturated sensors), and the drag turns a light object while the cage
    forms, where no robot can see it."""
    return scale(unit(x_o), gain * (target_reading - reading))


def u_avoid(neighbours: Iterable[Vec], safety_distance: float, gain: float) -> Vec:
    """Local collision avoidance: push away from robots closer than d_s, harder the closer they are."""
    total = ZERO
    near = safety_distance
    # Most of up to 99 neighbours are far: a box test (two comparisons each) drops them before any hypot.
    for r in [r for r in neighbours if -near < r[0] < near and -near < r[1] < near]:
        d = norm(r)
        if 1e-6 < d < safety_distance:
            total = add(total, scale(unit(r), -gain * (safety_distance - d) / safety_distance))
    return total
