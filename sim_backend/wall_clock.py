"""Stopping a simulation that takes too long in wall-clock time, e.g. because a behaviour's ``step()`` never
returns (a loop waiting for a message that only the next step could bring).

:class:`WallClockLimit` is a context manager around the run's loop. When the limit passes, a timer thread
raises :class:`WallClockLimitReached` in the thread that runs the loop, wherever it is (CPython's
``PyThreadState_SetAsyncExc``): between two bytecodes of the user's loop, so a ``while True`` in a behaviour
is stopped as surely as a slow run. It works in any thread (a Dask worker runs runs in threads, where no
signal can reach them). A call that blocks inside C (``time.sleep(3600)``) is stopped only when it returns.
"""
from __future__ import annotations

import ctypes
import threading
from typing import Any, Optional


def _raise_in(thread_id: int, exc_type: Optional[type]) -> None:
    """Raise ``exc_type`` in the thread at its next bytecode; None takes back one not yet raised."""
    exc = None if exc_type is None else ctypes.py_object(exc_type)     # None is passed as NULL
    ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(thread_id), exc)


class WallClockLimitReached(BaseException):
    """The run outlived its wall-clock limit. A BaseException, as KeyboardInterrupt is, so that a behaviour's
    own ``except Exception`` cannot swallow it."""


class WallClockLimit:
    """``with WallClockLimit(seconds):`` raises WallClockLimitReached in this thread once ``seconds`` of wall
    time have passed inside the block (None: no limit). Once the block is left, nothing is raised any more."""

    def __init__(self, seconds: Optional[float]):
        self.seconds = seconds
        self.reached = False
        self._lock = threading.Lock()
        self._armed = False
        self._thread_id = 0
        self._timer: Optional[threading.Timer] = None

    def __enter__(self) -> WallClockLimit:
        if self.seconds is not None:
            self._thread_id = threading.get_ident()
            self._armed = True
            self._timer = threading.Timer(self.seconds, self._expire)
            self._timer.daemon = True
            self._timer.start()
        return self

    def _expire(self) -> None:
        with self._lock:
            if self._armed:
                self.reached = True
                _raise_in(self._thread_id, WallClockLimitReached)

    def __exit__(self, *exc: Any) -> None:
        if self._timer is None:
            return
        self._timer.cancel()
        with self._lock:
            if self._armed and self.reached:
                # Raised into this thread but not yet delivered (the run ended just then): take it back, so it
                # does not go off later in code that has nothing to do with the run.
                _raise_in(self._thread_id, None)
            self._armed = False
