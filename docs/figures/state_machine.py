"""Draw docs/state-machine.png: the transport behaviour's states and transitions as the code implements them.

Run from anywhere: ``.venv/bin/python docs/figures/state_machine.py``. Matplotlib only (Agg backend), no
graphviz. The states and transition labels follow the ``_on_<state>`` handlers in
onboard/behaviours/transport/behaviour.py and transport.py; the table in docs/behaviour.md lists the
same transitions with their code locations. Keep the two in step when the handlers change.
"""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import FancyArrowPatch, FancyBboxPatch  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "state-machine.png"

BOX_W, BOX_H = 1.9, 0.8

# state -> (x, y) centre, caption under the name
STATES = {
    "idle": ((0.0, 2.0), "bid for the nearest\nopen task, keep clear"),
    "seed": ((3.4, 3.7), "drive to C_o(0)\nuntil IR contact"),
    "travel": ((3.4, 0.3), "edge-follow the cage\ntoward the target"),
    "attach": ((7.0, 0.3), "touch the object,\nslide to I_d of pred."),
    "caged": ((7.0, 3.7), "hold place, try closure,\nre-open / grow I_d"),
    "settle": ((10.6, 3.7), "even out spacing\nfor settle_time_s"),
    "push": ((10.6, 0.3), "u_fp = u_t + u_f + u_cp"),
    "rotate": ((14.2, 0.3), "u_fr = u_r + u_f + u_cr"),
    "done": ((14.2, 3.7), "stop"),
}

COLOURS = {
    "idle": "#eeeeee", "seed": "#dbe9f6", "travel": "#dbe9f6", "attach": "#dbe9f6", "caged": "#dbe9f6",
    "settle": "#e3f1dc", "push": "#e3f1dc", "rotate": "#e3f1dc", "done": "#f6e3c8",
}

# (from, to, label, arc radius (connectionstyle rad), label offset (dx, dy) from the chord midpoint, style)
TRANSITIONS = [
    ("idle", "seed", "won task S:\nlowest bid stored\nfor T_a", 0.0, (0.55, -0.55), "-"),
    ("idle", "travel", "won task L_k / R_k:\nlowest bid stored\nfor T_a", 0.0, (0.55, 0.55), "-"),
    ("seed", "caged", "IR peak >= prox. thres.:\njoin cage, open L1 and R1", 0.0, (0.0, 0.32), "-"),
    ("travel", "attach", "|target - x_i| < 0.25 m\n(improved: open next target)", 0.0, (0.0, -0.45), "-"),
    ("attach", "caged", "in contact and\n|d_pred - I_d| < d_tol\nfor 10 steps: join cage,\n"
     "close (Prop. 1) or\nopen next target", 0.0, (0.95, 0.0), "-"),
    ("caged", "settle", "'closed' in tuple space\n(path not empty)", 0.0, (0.0, 0.32), "-"),
    ("settle", "push", "settle_time_s after\nclosure: start filter,\nrecord formation", 0.0, (0.95, 0.0), "-"),
    ("push", "rotate", "barrier (k, push)", -0.25, (0.0, 0.42), "-"),
    ("rotate", "push", "barrier (k, rotate),\nk not last: k = k + 1", -0.25, (0.0, -0.5), "-"),
    ("rotate", "done", "barrier (k, rotate),\nk last: put 'done'", 0.0, (0.95, 0.0), "-"),
    ("caged", "done", "'closed' and no path (caging only)", -0.3, (0.0, 1.05), "-"),
    ("seed", "idle", "task lost", 0.55, (-0.45, 0.45), "--"),
    ("travel", "idle", "task lost", -0.55, (-0.45, -0.45), "--"),
]

# Drawn as a polyline below the bottom row: (points, label, label position)
ROUTED = [
    ([(7.0, -0.1), (7.0, -1.05), (0.0, -1.05), (0.0, 1.6)],
     "task lost (_still_mine: task cancelled or re-opened, another owner, or the cage closed)", (3.5, -1.05)),
]


def edge_point(centre, towards):
    """Where the line from a box's centre toward ``towards`` leaves the box."""
    (cx, cy), (tx, ty) = centre, towards
    dx, dy = tx - cx, ty - cy
    if dx == 0 and dy == 0:
        return centre
    sx = (BOX_W / 2) / abs(dx) if dx else float("inf")
    sy = (BOX_H / 2) / abs(dy) if dy else float("inf")
    s = min(sx, sy)
    return cx + dx * s, cy + dy * s


def draw() -> None:
    fig, ax = plt.subplots(figsize=(15, 8.2))
    ax.set_xlim(-1.4, 15.6)
    ax.set_ylim(-2.35, 5.0)
    ax.set_aspect("equal")
    ax.axis("off")

    for name, ((x, y), caption) in STATES.items():
        box = FancyBboxPatch((x - BOX_W / 2, y - BOX_H / 2), BOX_W, BOX_H, boxstyle="round,pad=0.04,rounding_size=0.12",
                             facecolor=COLOURS[name], edgecolor="black", linewidth=1.4, zorder=2)
        ax.add_patch(box)
        ax.text(x, y + 0.17, name, ha="center", va="center", fontsize=12, fontweight="bold", zorder=3)
        ax.text(x, y - 0.16, caption, ha="center", va="center", fontsize=7.5, zorder=3, linespacing=1.05)

    for src, dst, label, rad, (ox, oy), style in TRANSITIONS:
        a, b = STATES[src][0], STATES[dst][0]
        start, end = edge_point(a, b), edge_point(b, a)
        arrow = FancyArrowPatch(start, end, arrowstyle="-|>", mutation_scale=16, linewidth=1.3,
                                linestyle=style, color="#333333" if style == "-" else "#a33",
                                connectionstyle=f"arc3,rad={rad}", zorder=1, shrinkA=2, shrinkB=2)
        ax.add_patch(arrow)
        mx, my = (start[0] + end[0]) / 2 + ox, (start[1] + end[1]) / 2 + oy
        ax.text(mx, my, label, ha="center", va="center", fontsize=8, zorder=4, linespacing=1.05,
                color="black" if style == "-" else "#a33",
                bbox={"boxstyle": "round,pad=0.15", "facecolor": "white", "edgecolor": "none", "alpha": 0.9})

    for points, label, (lx, ly) in ROUTED:
        xs, ys = zip(*points[:-1])
        ax.plot(xs, ys, linestyle="--", color="#a33", linewidth=1.3, zorder=1)
        ax.add_patch(FancyArrowPatch(points[-2], points[-1], arrowstyle="-|>", mutation_scale=16, linewidth=1.3,
                                     linestyle="--", color="#a33", zorder=1, shrinkA=0, shrinkB=2))
        ax.text(lx, ly, label, ha="center", va="center", fontsize=8, color="#a33", zorder=4,
                bbox={"boxstyle": "round,pad=0.15", "facecolor": "white", "edgecolor": "none", "alpha": 0.9})

    notes = ("Also: from idle, caged, settle, push and rotate, a robot goes to done as soon as 'done' is in its "
             "tuple space (_finish_if_done); idle also goes to done when 'closed' is there and the path is empty.\n"
             "Every step, before the handler: merge received tuples, refresh liveness; without a fresh pose "
             "(none, or older than 1 s) the robot stops and no handler runs.\n"
             "Non-members stay in idle after closure (keeping clear of the cage) until 'done' arrives.")
    ax.text(-1.3, -1.85, notes, ha="left", va="center", fontsize=8.5, linespacing=1.4)
    ax.set_title("transport behaviour: states and transitions (onboard/behaviours/transport)", fontsize=13)
    fig.tight_layout()
    fig.savefig(OUT, dpi=110, bbox_inches="tight", pad_inches=0.15)
    plt.close(fig)


if __name__ == "__main__":
    draw()
    print(f"wrote {OUT}")
