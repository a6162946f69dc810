"""A run's samples (``Recording``), and the arrays of trajectory.npz (docs/outputs.md) made of them: one builder
for ``khepri sim run`` and ``khepri sil``, so that both keep the documented shapes, also for a run that crashed
before its first sample (``np.asarray([])`` alone would give ``object_pose`` the shape (0,) instead of (0, 3))."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List

import numpy as np


@dataclass
class Recording:
    """Samples at the control rate; see docs/outputs.md for the trajectory file."""

    t: List[float] = field(default_factory=list)
    robot_pose: List[np.ndarray] = field(default_factory=list)
    robot_alive: List[np.ndarray] = field(default_factory=list)
    object_pose: List[np.ndarray] = field(default_factory=list)
    centroid_estimate: List[np.ndarray] = field(default_factory=list)

    def trim(self, has_object: bool) -> None:
        """Drop a sample left half-written by a run stopped from outside (between two of its appends)."""
        lists = [self.t, self.robot_pose, self.robot_alive, self.centroid_estimate]
        if has_object:
            lists.append(self.object_pose)
        complete = min(len(samples) for samples in lists)
        for samples in lists:
            del samples[complete:]


def trajectory_arrays(samples, scenario, world) -> Dict[str, np.ndarray]:
    """``samples`` has the lists ``t``, ``robot_pose``, ``robot_alive``, ``object_pose`` and
    ``centroid_estimate``, one entry per control step (``Recording``, ``hub.sil_report.SilRecording``)."""
    count = len(world.robots)
    walls = scenario.arena.walls
    arrays: Dict[str, np.ndarray] = {
        "t": np.asarray(samples.t, dtype=float).reshape(-1),
        "robot_pose": np.asarray(samples.robot_pose, dtype=float).reshape(-1, count, 3),
        "robot_alive": np.asarray(samples.robot_alive, dtype=bool).reshape(-1, count),
        "path": np.asarray(scenario.path, dtype=float).reshape(-1, 3),
        "robot_radius": np.asarray(world.spec.radius_m, dtype=float),
        "arena_walls": np.asarray(walls if walls is not None else [np.nan] * 4, dtype=float),
    }
    estimate = np.asarray(samples.centroid_estimate, dtype=float).reshape(-1, 2)
    if np.isfinite(estimate).any():
        arrays["centroid_estimate"] = estimate
    if world.geometry is not None:
        rings = world.geometry.outline_polygons()
        arrays["object_pose"] = np.asarray(samples.object_pose, dtype=float).reshape(-1, 3)
        arrays["object_outline"] = np.vstack(rings)
        arrays["object_outline_index"] = np.cumsum([0] + [len(r) for r in rings])
    return arrays
