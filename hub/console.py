"""The hub's console: each line it prints is also recorded in its log, as ``/hub/log``.

A lab's evening is told by the hub's console (robots connecting, agents restarting, e-stops, geofence stops,
refused keys), and a terminal's scrollback is gone by Monday. The log keeps every line with its time, in
the form Foxglove's Log panel shows (``foxglove.Log``), and ``khepri log console FILE`` prints them again.
"""
from __future__ import annotations

import time
from typing import Any, Callable, Dict, List, Optional, Tuple

from onboard.console import one_line

from .log_format import HUB_LOG

FOXGLOVE_INFO = 2          # foxglove.Log's level: 1 debug, 2 info, 3 warning, 4 error, 5 fatal
EARLY_LINES_KEPT = 500     # said while the hub was built, before its log was open: recorded once it is


def console_record(line: str, stamp_s: float) -> Dict[str, Any]:
    """A ``/hub/log`` message: foxglove.Log's fields. The hub's lines carry no level of their own: all info."""
    sec = int(stamp_s)
    return {"timestamp": {"sec": sec, "nsec": int(round((stamp_s - sec) * 1e9)) % 1_000_000_000},
            "level": FOXGLOVE_INFO, "message": line, "name": "hub", "file": "", "line": 0}


class HubConsole:
    """Prints a line (``print_line``) and records it in the hub's log once there is one (:meth:`record_to`).
    Callable like the ``log`` function it wraps; safe from any thread (the recorder only queues)."""

    def __init__(self, print_line: Callable[[str], None] = print) -> None:
        self.print_line = print_line
        self.recorder: Optional[Any] = None
        self.early: Optional[List[Tuple[float, str]]] = []     # None once record_to was told (log or none)

    def __call__(self, line: str) -> None:
        stamp = time.time()
        # Escaped here, where every line passes on its way to the console and the log: many quote a robot's
        # text (its error, driver, run id), whose newline made a second line, which read as the hub's own.
        line = one_line(line)
        self.print_line(line)
        recorder = self.recorder
        if recorder is not None:
            recorder.write(HUB_LOG, console_record(line, stamp), stamp)
        elif self.early is not None and len(self.early) < EARLY_LINES_KEPT:
            self.early.append((stamp, line))

    def record_to(self, recorder: Optional[Any]) -> None:
        """From now on each line goes into ``recorder`` too, after the lines said before (None: none are)."""
        self.recorder = recorder
        if recorder is not None:
            for stamp, line in self.early or []:
                recorder.write(HUB_LOG, console_record(line, stamp), stamp)
        self.early = None       # a hub that does not record keeps no lines either


def as_console(log: Callable[[str], None]) -> HubConsole:
    return log if isinstance(log, HubConsole) else HubConsole(log)
