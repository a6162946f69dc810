"""Loop timing for the agent's telemetry and `khepri ctl status`: measured rate, step duration, deadline misses."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict


@dataclass
class LoopStats:
    """Loop timing for telemetry: measured rate, step duration, deadline misses."""

    steps: int = 0
    misses: int = 0
    total_step_s: float = 0.0
    max_step_s: float = 0.0
    last_step_s: float = 0.0
    window_start: float = 0.0
    window_steps: int = 0
    hz: float = 0.0

    def record(self, started: float, finished: float, deadline: float) -> None:
        duration = finished - started
        self.last_step_s = duration
        self.steps += 1
        self.total_step_s += duration
        self.max_step_s = max(self.max_step_s, duration)
        if finished > deadline:
            self.misses += 1
        self.window_steps += 1
        if finished - self.window_start >= 1.0:
            self.hz = self.window_steps / (finished - self.window_start) if self.window_start else 0.0
            self.window_start, self.window_steps = finished, 0

    def idle(self, now: float) -> None:
        """A tick without a step (idle, hold, e-stop, watchdog): the rate falls to what was stepped, so that a
        held robot does not keep reporting the 10 Hz of its last run. A window with no step at all closes,
        and the next step opens a fresh one, as at start-up."""
        if self.window_start and now - self.window_start >= 1.0:
            self.hz = self.window_steps / (now - self.window_start)
            self.window_start = now if self.window_steps else 0.0
            self.window_steps = 0

    def as_dict(self) -> Dict[str, Any]:
        mean = self.total_step_s / self.steps if self.steps else 0.0
        return {"hz": round(self.hz, 2), "steps": self.steps, "misses": self.misses,
                "mean_ms": round(mean * 1000.0, 3), "max_ms": round(self.max_step_s * 1000.0, 3)}
