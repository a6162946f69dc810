"""The paper's figures for a study, ours next to the paper's: times, errors per waypoint, effective robots,
object trajectories against the path. PNG files, drawn with matplotlib's Agg backend.

Cells are grouped the way the paper groups them: one *panel* per path (straight, zigzag, straight_rot; any
other scenario is its own panel) and one *series* per robot count (or per parameter override) inside it.
"""
from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Dict, List, Optional

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (the backend must be chosen first)
import numpy as np  # noqa: E402

from . import paper_reference as paper  # noqa: E402
from .aggregate import Cell, StudyResults, overrides_text, paper_time_s  # noqa: E402

ERROR_ROWS = (("centroid_estimation_error_m", "centroid estimation error (m)"),
              ("position_error_m", "position error (m)"),
              ("orientation_error_rad", "orientation error (rad)"))
EFFECTIVE_ROWS = (("effective_pushers", "effective pushers"), ("effective_rotators", "effective rotators"))
PAPER_STYLE = {"hatch": "///", "alpha": 0.35}
DPI = 110
FEW_RUNS = 10
SYMLOG_BELOW = 0.01    # errors.png: linear below this (m or rad), logarithmic above


def panel_of(cell: Cell) -> str:
    return cell.case.path if cell.case.path else cell.scenario


def series_label(cell: Cell) -> str:
    robots = f"{cell.robots} robots" if cell.robots is not None else cell.scenario
    extra = overrides_text(cell.overrides)
    return f"{robots} {extra}".strip()


def panels(cells: List[Cell]) -> Dict[str, List[Cell]]:
    grouped: Dict[str, List[Cell]] = {}
    for cell in cells:
        grouped.setdefault(panel_of(cell), []).append(cell)
    return grouped


def colour(index: int):
    return plt.get_cmap("tab10")(index % 10)


def write_figures(results: StudyResults, folder: Path) -> Dict[str, Path]:
    """Draw every figure the study has data for; returns {title: file}."""
    folder.mkdir(parents=True, exist_ok=True)
    # Every transport cell gets its panel, even one whose runs reached no waypoint: an empty panel says so.
    path_cells = [c for c in results.cells if c.has_path]
    drawn: Dict[str, Path] = {}
    # Also when nothing caged: the paper's medians alone still say where the runs should have been.
    if any(c.values("time_to_cage_s") or c.values("time_to_complete_s")
           or paper_time_s(c, "time_to_cage_s") is not None for c in results.cells):
        drawn["Time to cage and to complete"] = plot_times(results.cells, folder / "times.png")
    if path_cells:
        drawn["Errors per waypoint"] = plot_waypoint_rows(path_cells, ERROR_ROWS, folder / "errors.png", True)
        drawn["Effective pushers and rotators per waypoint"] = plot_waypoint_rows(
            path_cells, EFFECTIVE_ROWS, folder / "effective.png", False)
        drawn["Object trajectories against the path"] = plot_trajectories(path_cells, results.root,
                                                                          folder / "trajectories.png")
    return drawn


def short_label(cell: Cell) -> str:
    if cell.case.robots is not None:
        label = f"{cell.case.robots}\n{cell.case.path}"
    else:
        label = cell.scenario
    extra = overrides_text(cell.overrides)
    return f"{label}\n{extra}" if extra else label


def plot_times(cells: List[Cell], target: Path) -> Path:
    figure, axes = plt.subplots(1, 2, figsize=(max(8, 1.3 * len(cells) + 4), 5), squeeze=False)
    for ax, key, title in ((axes[0, 0], "time_to_cage_s", "time to cage"),
                           (axes[0, 1], "time_to_complete_s", "time to complete (after caging)")):
        shown = [c for c in cells if c.values(key) or paper_time_s(c, key) is not None]
        if key == "time_to_complete_s":     # a cell whose runs all failed keeps the paper's diamond
            shown = [c for c in shown if c.has_path or paper_time_s(c, key) is not None]
        for i, cell in enumerate(shown):
            values = cell.values(key)
            if values:     # one colour: a colour per cell, with no legend, read as a meaning it did not have
                ax.boxplot([values], positions=[i], widths=0.5, patch_artist=True,
                           boxprops={"facecolor": colour(0), "alpha": 0.6}, medianprops={"color": "black"})
            reference = paper_time_s(cell, key)
            if reference is not None:
                ax.plot([i], [reference], "D", color="red", markersize=8,
                        label="paper (median)" if "paper (median)" not in ax.get_legend_handles_labels()[1] else None)
        # Slanted, right-aligned labels: cell names such as "irregular-box_rotation" overlap when level.
        ax.set_xticks(range(len(shown)), [short_label(c) for c in shown], fontsize=8, rotation=30, ha="right")
        ax.set_xlim(-0.7, max(len(shown), 1) - 0.3)
        ax.set_title(title)
        ax.set_ylabel("simulated time (s)")
        ax.grid(axis="y", alpha=0.3)
        handles, labels = ax.get_legend_handles_labels()
        if any(cell.values(key) for cell in shown):
            handles.insert(0, plt.Rectangle((0, 0), 1, 1, color=colour(0), alpha=0.6))
            labels.insert(0, "ours (median, quartiles, whiskers)")
        if handles:
            ax.legend(handles, labels, loc="best", fontsize=8)
    return save(figure, target)


def plot_waypoint_rows(cells: List[Cell], rows, target: Path, with_paper: bool) -> Path:
    """Rows = metrics, columns = paths; per waypoint one box per series, the paper's hatched beside ours."""
    grouped = panels(cells)
    figure, axes = plt.subplots(len(rows), len(grouped), figsize=(6.5 * len(grouped), 3.4 * len(rows)),
                                squeeze=False)
    for column, (panel, members) in enumerate(grouped.items()):
        width = 0.8 / (len(members) * (2 if with_paper else 1))
        for row, (metric, label) in enumerate(rows):
            ax = axes[row, column]
            for s, cell in enumerate(members):
                draw_series(ax, cell, metric, s, len(members), width, with_paper)
            set_waypoint_axis(ax, members, with_paper)
            if with_paper:
                # Linear to 1 cm, logarithmic above: the paper's 100-robot errors (2-6 m) set a linear axis that
                # flattened ours (1-40 mm) onto its zero line.
                ax.set_yscale("symlog", linthresh=SYMLOG_BELOW)
                ax.set_ylim(0.0, ax.get_ylim()[1] * 1.5)     # errors are never negative; room above the top box
                label = f"{label}\n(log scale above {SYMLOG_BELOW:g})"
            else:       # counts of robots: from 0, or a 1 % drift (12.68 to 12.82) looked steep
                ax.set_ylim(0.0, max(1.0, ax.get_ylim()[1] * 1.1))
            ax.set_ylabel(label)
            ax.set_xlabel("waypoint")
            ax.grid(axis="y", alpha=0.3)
            if row == 0:
                ax.set_title(panel)
        # Only the series that have a box here: a cell that reached no waypoint has nothing to point at.
        shown = [s for s, c in enumerate(members) if plotted_waypoints(c, with_paper)]
        handles = [plt.Rectangle((0, 0), 1, 1, color=colour(s), alpha=0.6) for s in shown]
        labels = [series_label(members[s]) for s in shown]
        if with_paper and any(c.case.robots for c in members):
            handles.append(plt.Rectangle((0, 0), 1, 1, facecolor="white", edgecolor="grey", **PAPER_STYLE))
            labels.append("paper (hatched)")
        if handles:
            axes[0, column].legend(handles, labels, fontsize=8, loc="best")
    return save(figure, target)


def draw_series(ax, cell: Cell, metric: str, s: int, count: int, width: float, with_paper: bool) -> None:
    slots = 2 if with_paper else 1
    indices = plotted_waypoints(cell, with_paper)
    for index in indices:
        left = index - 0.4 + (s * slots) * width + width / 2
        values = cell.waypoint_values(index, metric)
        if values:
            ax.boxplot([values], positions=[left], widths=width * 0.9, patch_artist=True, showfliers=False,
                       boxprops={"facecolor": colour(s), "alpha": 0.6}, medianprops={"color": "black"})
            if len(values) < FEW_RUNS:   # a box of two or three runs hides them: show the runs themselves
                ax.plot([left] * len(values), values, "k.", markersize=4)
        reference = paper.error_values(cell.case, index, metric) if with_paper else ()
        if reference:
            ax.boxplot([list(reference)], positions=[left + width], widths=width * 0.9, patch_artist=True,
                       showfliers=False, boxprops={"facecolor": colour(s), **PAPER_STYLE},
                       medianprops={"color": "black"})


def plotted_waypoints(cell: Cell, with_paper: bool) -> List[int]:
    """The waypoints a cell has boxes at: those its runs reached, and beside the paper's, those it gives."""
    return cell.compared_waypoints() if with_paper else cell.waypoint_indices()


def set_waypoint_axis(ax, members: List[Cell], with_paper: bool) -> None:
    last = max((i for cell in members for i in plotted_waypoints(cell, with_paper)), default=None)
    if not any(cell.waypoint_indices() for cell in members):
        ax.text(0.5, 0.9, "no waypoint reached", transform=ax.transAxes, ha="center", color="grey")
    if last is None:
        return
    ax.set_xticks(list(range(last + 1)), [str(t) for t in range(last + 1)])
    ax.set_xlim(-0.6, last + 0.6)


def plot_trajectories(cells: List[Cell], root: Path, target: Path) -> Path:
    """Rows = series (robot counts), columns = paths: each run's object centroid against the waypoints."""
    grouped = panels(cells)
    rows = max(len(members) for members in grouped.values())
    figure, axes = plt.subplots(rows, len(grouped), figsize=(5.5 * len(grouped), 4.5 * rows), squeeze=False)
    for ax in axes.flat:
        ax.set_visible(False)
    for column, members in enumerate(grouped.values()):
        for row, cell in enumerate(members):
            ax = axes[row, column]
            ax.set_visible(True)
            draw_cell_trajectories(ax, cell, root)
    return save(figure, target)


def draw_cell_trajectories(ax, cell: Cell, root: Path) -> None:
    path, start, drawn = None, None, 0
    for seed in sorted(cell.results):
        arrays = load_object_track(root / cell.name / f"seed-{seed}" / "trajectory.npz")
        if arrays is None or not len(arrays[0]):
            continue
        track, path = arrays
        start = track[0]
        ax.plot(track[:, 0], track[:, 1], lw=1.0, alpha=0.8, color=colour(seed), zorder=3,
                label="object centroid (a colour per run)" if not drawn else None)
        drawn += 1
    if path is not None and len(path):
        # The desired path runs from where the object starts through the waypoints.
        # Under the runs (zorder): on a straight path a good run's line lies right on it.
        ax.plot([start[0], *path[:, 0]], [start[1], *path[:, 1]], "--", color="grey", lw=0.8, zorder=1,
                label="desired path")
        ax.plot(path[:, 0], path[:, 1], "o", color="grey", markersize=4, zorder=2)
        for i, (x, y, _) in enumerate(path):
            ax.annotate(str(i), (x, y), textcoords="offset points", xytext=(3, 3), fontsize=7)
        ax.legend(fontsize=7, loc="best")
    ax.set_aspect("equal", adjustable="datalim")
    title = textwrap.fill(cell.name.replace("@", " @"), 48)     # long override cells wrap, not overlap
    ax.set_title(f"{title} ({drawn} of {len(cell.results)} runs drawn)", fontsize=9)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.3)


def load_object_track(path: Path) -> Optional[tuple]:
    """(object x, y over time, waypoints) from a run's trajectory.npz, or None without one."""
    try:
        with np.load(path) as data:
            if "object_pose" not in data:
                return None
            return np.asarray(data["object_pose"])[:, :2], np.asarray(data["path"])
    except (OSError, ValueError, KeyError):
        return None   # no file (a remote worker's run, or a failed start) or an unreadable one


def save(figure, target: Path) -> Path:
    figure.tight_layout()
    figure.savefig(target, dpi=DPI)
    plt.close(figure)
    return target
