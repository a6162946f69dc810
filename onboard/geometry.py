"""Pose geometry shared by the simulator and the hub: poses -> range and bearing for all pairs.

Vectorised over all pairs with numpy; the hub runs it per motion-capture frame, the simulator per
control step. Keep it free of anything but numpy.
"""
from __future__ import annotations

from typing import Tuple

import numpy as np

TWO_PI = 2.0 * np.pi


def pairwise_range_bearing(xy: np.ndarray, yaw: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Range (m) and bearing (rad, observer's frame) from every robot i to every robot j.

    ``xy`` is (N, 2) world positions, ``yaw`` (N,) headings. Returns ``(ranges, bearings)``, both (N, N);
    ``bearings[i, j]`` is where j appears to i, wrapped to (-pi, pi]. The diagonal is range 0, bearing 0.
    """
    xy = np.asarray(xy, dtype=float)
    x, y = xy[:, 0], xy[:, 1]
    dx = x[None, :] - x[:, None]                      # dx[i, j] = x_j - x_i; contiguous, unlike a (N, N, 2) delta
    dy = y[None, :] - y[:, None]
    ranges = np.hypot(dx, dy)
    bearings = wrap(np.arctan2(dy, dx) - np.asarray(yaw, dtype=float)[:, None])
    np.fill_diagonal(bearings, 0.0)
    return ranges, bearings


def neighbour_mask(ranges: np.ndarray, d_c: float) -> np.ndarray:
    """True where j is within communication range of i (never i itself)."""
    mask = ranges <= d_c
    np.fill_diagonal(mask, False)
    return mask


def wrap(angles: np.ndarray) -> np.ndarray:
    """Wrap angles to (-pi, pi]."""
    angles = np.asarray(angles, dtype=float)
    # floor() instead of np.mod: several times faster on the (N, N) bearing matrices, same results.
    wrapped = angles - TWO_PI * np.floor((angles + np.pi) / TWO_PI)
    return np.where(wrapped <= -np.pi, wrapped + TWO_PI, wrapped)
