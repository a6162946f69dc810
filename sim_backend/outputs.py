"""Writing a finished run to disk: result.json, trajectory.npz, trajectory.png and an optional video."""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Dict, Optional

import numpy as np

from .metrics import result_text
from .runner import Simulation


def write_run(sim: Simulation, result: Dict[str, Any], out_dir: Path, video: Optional[Path] = None,
              plot: bool = True) -> Dict[str, Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    files = {"result": out_dir / "result.json", "trajectory": out_dir / "trajectory.npz"}
    arrays = sim.trajectory_arrays()
    np.savez_compressed(files["trajectory"], **arrays)
    files["result"].write_text(result_text(result))
    if not plot:     # an earlier run's plot in this folder must not pass for this run's
        (out_dir / "trajectory.png").unlink(missing_ok=True)
    if plot or video is not None:
        from . import plots  # matplotlib only when drawing

        title = f"{result['scenario']} (seed {result['seed']})"
        if plot:
            files["plot"] = out_dir / "trajectory.png"
            plots.plot_trajectory(arrays, files["plot"], title=title)
        if video is not None:
            video.parent.mkdir(parents=True, exist_ok=True)
            files["video"] = video
            plots.write_video(arrays, video, title=title)
    return files


class ProgressBar:
    """A one-line progress bar on stderr; silent when stderr is not a terminal."""

    def __init__(self, label: str, stream=None):
        self.stream = stream or sys.stderr
        self.enabled = self.stream.isatty()
        self.label = label

    def __call__(self, done: float, total: float) -> None:
        if not self.enabled or total <= 0:
            return
        fraction = min(done / total, 1.0)
        width = 30
        filled = int(width * fraction)
        self.stream.write(f"\r{self.label} [{'#' * filled}{'.' * (width - filled)}] {done:7.1f}/{total:.0f} s")
        self.stream.flush()

    def say(self, line: str) -> None:
        """A line above the bar (the bar is drawn again at the next update)."""
        if self.enabled:
            self.stream.write("\r\033[K")
        self.stream.write(line + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.enabled:
            self.stream.write("\n")
            self.stream.flush()
