"""Plots and videos of a simulated run, drawn from the trajectory NPZ the simulator writes.

Drawing is kept out of the simulator: it only records arrays, this module turns them into pictures.
Headless (Agg backend). Trajectory NPZ keys (T samples at the 10 Hz control rate, N robots):

=========================  ==========  ===========================================================
key                        shape       meaning
=========================  ==========  ===========================================================
``t``                      (T,)        simulated time in s at each sample
``robot_pose``             (T, N, 3)   x (m), y (m), yaw (rad) of each robot
``robot_alive``            (T, N)      bool, False once a robot has died
``object_pose``            (T, 3)      x, y, yaw of the object's centroid (absent without object)
``object_outline``         (P, 2)      all outline polygons in the object frame, concatenated
                                       (absent without object)
``object_outline_index``   (K+1,)      polygon k is ``object_outline[index[k]:index[k+1]]``
                                       (absent without object)
``path``                   (W, 3)      waypoints x, y, yaw_deg; W may be 0
``robot_radius``           ()          robot radius in m
``arena_walls``            (4,)        xmin, ymin, xmax, ymax; all NaN when there are no walls
``centroid_estimate``      (T, 2)      optional: swarm's mean estimate of the object centroid
                                       (NaN where no robot has one)
=========================  ==========  ===========================================================
"""
from __future__ import annotations

from pathlib import Path
from typing import Dict, List, Optional, Tuple, Union

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib import animation  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.patches import Circle, Polygon, Rectangle  # noqa: E402

Traj = Dict[str, np.ndarray]
PathLike = Union[str, Path]


def load_trajectory(path: PathLike) -> Traj:
    """Load a trajectory NPZ written by the simulator into a dict of numpy arrays."""
    with np.load(path, allow_pickle=False) as data:
        return {key: data[key] for key in data.files}


def _has_object(traj: Traj) -> bool:
    """Whether there is an object with at least one recorded pose to draw it at."""
    keys = ("object_pose", "object_outline", "object_outline_index")
    return all(key in traj for key in keys) and len(traj["object_pose"]) > 0


def _has_samples(traj: Traj) -> bool:
    """False for a run that ended (a behaviour raising at t = 0, say) before its first sample was recorded."""
    return len(traj["t"]) > 0


NO_SAMPLES_NOTE = "no samples: the run ended before its first control step was recorded"


def _note_no_samples(ax: Axes) -> None:
    ax.text(0.5, 0.5, NO_SAMPLES_NOTE, transform=ax.transAxes, ha="center", va="center", fontsize=10,
            bbox={"facecolor": "white", "edgecolor": "0.6"})


def _object_polygons(traj: Traj, pose: np.ndarray) -> List[np.ndarray]:
    """Outline polygons of the object in world coordinates at ``pose`` (x, y, yaw)."""
    outline, index = np.asarray(traj["object_outline"], float), np.asarray(traj["object_outline_index"])
    c, s = np.cos(pose[2]), np.sin(pose[2])
    world = outline @ np.array([[c, s], [-s, c]]) + pose[:2]
    return [world[index[k]:index[k + 1]] for k in range(len(index) - 1) if index[k + 1] > index[k]]


def _walls(traj: Traj) -> Optional[np.ndarray]:
    walls = np.asarray(traj.get("arena_walls", np.full(4, np.nan)), float)
    return walls if walls.shape == (4,) and np.all(np.isfinite(walls)) else None


def _held_poses(traj: Traj) -> np.ndarray:
    """Robot poses with each dead sample replaced by the robot's last live pose (first pose if never)."""
    pose, alive = np.asarray(traj["robot_pose"], float), np.asarray(traj["robot_alive"], bool)
    idx = np.where(alive, np.arange(len(pose))[:, None], 0)
    idx = np.maximum.accumulate(idx, axis=0)
    return np.take_along_axis(pose, idx[:, :, None], axis=0)


def _colours(n: int) -> List[Tuple[float, ...]]:
    cmap = matplotlib.colormaps["tab10" if n <= 10 else "tab20"]
    return [cmap(i % cmap.N) for i in range(n)]


def _waypoint_arrow_len(traj: Traj) -> float:
    return 3.0 * float(traj["robot_radius"])


def _set_limits(ax: Axes, traj: Traj) -> None:
    """Axis limits including robots, object, waypoints (with arrows), walls and estimate, plus a margin."""
    pts = [_held_poses(traj)[..., :2].reshape(-1, 2)]
    if _has_object(traj):
        obj = np.asarray(traj["object_pose"], float)
        pts += [obj[:, :2]] + _object_polygons(traj, obj[0]) + _object_polygons(traj, obj[-1])
    path = np.asarray(traj.get("path", np.zeros((0, 3))), float).reshape(-1, 3)
    yaw = np.radians(path[:, 2])
    tips = path[:, :2] + _waypoint_arrow_len(traj) * np.column_stack([np.cos(yaw), np.sin(yaw)])
    pts += [path[:, :2], tips]
    walls = _walls(traj)
    if walls is not None:
        pts.append(walls.reshape(2, 2))
    if "centroid_estimate" in traj:
        pts.append(np.asarray(traj["centroid_estimate"], float).reshape(-1, 2))
    allp = np.concatenate(pts)
    allp = allp[np.all(np.isfinite(allp), axis=1)]
    if len(allp) == 0:
        allp = np.zeros((1, 2))
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    margin = max(0.05 * float(np.max(hi - lo)), 2.0 * float(traj["robot_radius"]), 0.05)
    ax.set_xlim(lo[0] - margin, hi[0] + margin)
    ax.set_ylim(lo[1] - margin, hi[1] + margin)


def _setup_axes(ax: Axes, traj: Traj, title: str) -> None:
    """Equal aspect, metre labels, grid, walls rectangle, limits and title."""
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, alpha=0.4)
    walls = _walls(traj)
    if walls is not None:
        ax.add_patch(Rectangle(walls[:2], walls[2] - walls[0], walls[3] - walls[1],
                               fill=False, edgecolor="0.2", linewidth=2.0))
    _set_limits(ax, traj)
    if title:
        ax.set_title(title)


def _draw_waypoints(ax: Axes, traj: Traj) -> None:
    """Numbered red markers with a short arrow showing each waypoint's yaw."""
    path = np.asarray(traj.get("path", np.zeros((0, 3))), float).reshape(-1, 3)
    if len(path) == 0:
        return
    length = _waypoint_arrow_len(traj)
    ax.plot(path[:, 0], path[:, 1], "o", color="red", markersize=7, label="waypoints", zorder=5)
    for k, (x, y, yaw_deg) in enumerate(path):
        dx, dy = length * np.cos(np.radians(yaw_deg)), length * np.sin(np.radians(yaw_deg))
        ax.annotate("", xy=(x + dx, y + dy), xytext=(x, y), zorder=5,
                    arrowprops={"arrowstyle": "->", "color": "red", "lw": 1.5})
        away = np.radians(yaw_deg + 180.0)  # number on the side opposite the arrow
        ax.annotate(str(k + 1), (x, y), xytext=(9 * np.cos(away), 9 * np.sin(away)),
                    textcoords="offset points", ha="center", va="center", color="red", fontsize=9,
                    fontweight="bold", zorder=6)


def _draw_robot_paths(ax: Axes, traj: Traj) -> None:
    """Each robot's path (thin line), start marker, end circle, or an 'x' where it died."""
    if not _has_samples(traj):      # nothing to draw a path from (and alive[-1] would not exist)
        return
    pose, alive = _held_poses(traj), np.asarray(traj["robot_alive"], bool)
    radius = float(traj["robot_radius"])
    for i, colour in enumerate(_colours(pose.shape[1])):
        live = np.flatnonzero(alive[:, i])
        last = int(live[-1]) if len(live) else 0
        xy = pose[: last + 1, i, :2]
        ax.plot(xy[:, 0], xy[:, 1], "-", color=colour, linewidth=1.0, alpha=0.7,
                label="robots" if i == 0 else None)
        ax.plot(xy[0, 0], xy[0, 1], "o", color=colour, markersize=3, alpha=0.9)
        if alive[-1, i]:
            ax.add_patch(Circle(xy[-1], radius, facecolor=colour, edgecolor="black", linewidth=0.5,
                                alpha=0.8))
        else:
            ax.plot(xy[-1, 0], xy[-1, 1], "x", color=colour, markersize=9, markeredgewidth=2)


def _draw_object(ax: Axes, traj: Traj) -> None:
    """Object centroid path (thick black), outline at start (dashed grey) and end (filled), estimate."""
    if _has_object(traj):
        obj = np.asarray(traj["object_pose"], float)
        ax.plot(obj[:, 0], obj[:, 1], "-", color="black", linewidth=2.5, label="object centroid", zorder=4)
        for k, poly in enumerate(_object_polygons(traj, obj[0])):
            ax.add_patch(Polygon(poly, closed=True, fill=False, edgecolor="grey", linestyle="--",
                                 linewidth=1.2, label="object start" if k == 0 else None))
        for k, poly in enumerate(_object_polygons(traj, obj[-1])):
            ax.add_patch(Polygon(poly, closed=True, facecolor="wheat", edgecolor="saddlebrown", alpha=0.6,
                                 linewidth=1.5, label="object end" if k == 0 else None))
    if "centroid_estimate" in traj:
        est = np.asarray(traj["centroid_estimate"], float).reshape(-1, 2)
        ax.plot(est[:, 0], est[:, 1], ":", color="blue", linewidth=1.5, label="estimated centroid", zorder=4)


def plot_trajectory(traj: Traj, out_png: PathLike, title: str = "") -> None:
    """Save a PNG of the whole run: robot paths, object path and outlines, waypoints, walls, legend."""
    fig, ax = plt.subplots(figsize=(8, 8))
    try:
        _setup_axes(ax, traj, title)
        _draw_robot_paths(ax, traj)
        _draw_object(ax, traj)
        _draw_waypoints(ax, traj)
        if not _has_samples(traj):
            _note_no_samples(ax)
        if ax.get_legend_handles_labels()[0]:      # an empty legend only draws a warning
            ax.legend(loc="best", fontsize=9, framealpha=0.85)
        fig.savefig(out_png, dpi=120, bbox_inches="tight")
    finally:
        plt.close(fig)


def _video_writer(out_file: Path, fps: int) -> animation.AbstractMovieWriter:
    suffix = out_file.suffix.lower()
    if suffix == ".gif":
        return animation.PillowWriter(fps=fps)
    if suffix == ".mp4":
        if not animation.writers.is_available("ffmpeg"):
            raise ValueError("mp4 needs ffmpeg; use a .gif file name")
        return animation.FFMpegWriter(fps=fps)
    raise ValueError(f"unsupported video file suffix {out_file.suffix!r}; use .gif or .mp4")


def write_video(
    traj: Traj, out_file: PathLike, fps: int = 10, max_frames: int = 300, title: str = ""
) -> None:
    """Animate the run: robots as circles with a heading tick (dead ones grey), the object outline at
    its current pose, waypoints and a time label; frames subsampled evenly down to ``max_frames``. A run
    without samples gets one frame of the arena and waypoints that says so."""
    out_file = Path(out_file)
    writer = _video_writer(out_file, fps)
    fig, ax = plt.subplots(figsize=(6, 6))
    try:
        _setup_axes(ax, traj, title)
        _draw_waypoints(ax, traj)
        run = _AnimatedRun(ax, traj, max_frames) if _has_samples(traj) else None
        if run is None:
            _note_no_samples(ax)
        label = ax.set_title("", loc="right", fontsize=10)
        (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
        fig.set_size_inches(6.0, float(np.clip(6.0 * (y1 - y0) / (x1 - x0), 3.0, 9.0)) + 0.6)
        fig.tight_layout()
        with writer.saving(fig, str(out_file), dpi=80):
            for f in run.frames if run is not None else [None]:
                if run is not None:
                    label.set_text(run.draw(f))
                writer.grab_frame()
    finally:
        plt.close(fig)


class _AnimatedRun:
    """The moving parts of a video: a body and heading tick per robot, and the object's outline."""

    def __init__(self, ax: Axes, traj: Traj, max_frames: int):
        self.traj = traj
        self.t, self.pose = np.asarray(traj["t"], float), _held_poses(traj)
        self.alive, self.radius = np.asarray(traj["robot_alive"], bool), float(traj["robot_radius"])
        count = max(1, min(len(self.t), max_frames))
        self.frames = np.unique(np.linspace(0, len(self.t) - 1, count).round().astype(int))
        self.colours = _colours(self.pose.shape[1])
        self.bodies = [ax.add_patch(Circle((0, 0), self.radius, edgecolor="black", linewidth=0.5, zorder=3))
                       for _ in self.colours]
        self.ticks = [ax.plot([], [], "-", color="black", linewidth=1.0, zorder=4)[0] for _ in self.colours]
        self.polys = []
        if _has_object(traj):
            self.polys = [ax.add_patch(Polygon(p, closed=True, facecolor="wheat", edgecolor="saddlebrown",
                                               alpha=0.7)) for p in _object_polygons(traj, traj["object_pose"][0])]

    def draw(self, f: int) -> str:
        """Move everything to sample ``f``; the time label to show."""
        radius = self.radius
        for i, (body, tick) in enumerate(zip(self.bodies, self.ticks)):
            x, y, yaw = self.pose[f, i]
            body.set_center((x, y))
            body.set_facecolor(self.colours[i] if self.alive[f, i] else "0.6")
            tick.set_data([x, x + radius * np.cos(yaw)], [y, y + radius * np.sin(yaw)])
        if self.polys:
            for patch, poly in zip(self.polys, _object_polygons(self.traj, self.traj["object_pose"][f])):
                patch.set_xy(poly)
        return f"t = {self.t[f]:.1f} s"
