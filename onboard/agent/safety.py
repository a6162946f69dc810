"""What keeps the wheels safe when the agent's own loop cannot: a gate on wheel commands, and a step watchdog.

The agent checks the hub's mode, its watchdog and signals between behaviour steps, on one thread. Two ways
around that were found by trying it:

- a ``step()`` that never returns (a "wait for a message" loop) left the last wheel speeds on, deaf to the
  e-stop, the watchdog and SIGTERM;
- a behaviour that drives from a thread of its own kept sending wheel commands through an e-stop.

:class:`GuardedDriver` wraps the robot's driver: every hardware call takes one lock (the loop and the step
watchdog may both call it), and wheel commands pass only while the gate is open, which the agent keeps so
only in ``run`` mode with live hub frames. :class:`StepWatchdog` is a thread that closes the gate and stops
the wheels once a step has run longer than the watchdog, and ends the process if a stop was asked for (SIGINT,
SIGTERM, SIGHUP) and the step still has not returned a second later.
"""
from __future__ import annotations

import os
import sys
import sysconfig
import threading
import time
from types import FrameType
from typing import Callable, List, Optional

from onboard.drivers import Driver, DriverError
from onboard.hal import WheelOdometry
from onboard.protocol_schema import ProtocolError, battery_reading

STUCK_EXIT_AFTER_S = 1.0     # a stop asked for while a step is stuck: the process ends this long after
# A hardware call takes milliseconds. One stuck this long (a hung I2C bus) holds the driver's lock: nothing can
# stop the wheels or reach the robot, and signals wait for the call too. The process ends, and the wheel guard,
# a process of its own, opens the robot afresh and stops them.
DRIVER_CALL_LIMIT_S = 2.0
STOP_LOCK_WAIT_S = 0.1       # the step watchdog's stop waits this long for a driver call to return
POLL_S = 0.02


class GuardedDriver(Driver):
    """The agent's driver: one lock around the hardware, and wheel commands only through an open gate."""

    def __init__(self, driver: Driver):
        self.inner = driver
        self.name = driver.name
        self.lock = threading.RLock()
        self.gate_open = False
        # A stop from the watchdog thread: safe when the driver talks to its own hardware under our lock
        # (kh4). The sim driver sends over the agent's socket, which only the loop's thread may use; the hub
        # holds the simulated wheels of an agent that goes silent.
        self.stoppable_from_any_thread = driver.name != "sim"
        self.call_started: Optional[float] = None     # the hardware call under way, for the step watchdog
        self.call_name = ""

    def _call(self, name: str, function: Callable, *args):
        with self.lock:
            self.call_started, self.call_name = time.monotonic(), name
            try:
                return function(*args)
            finally:
                self.call_started = None

    def open_gate(self) -> None:
        self.gate_open = True

    def close_gate(self) -> None:
        """No wheel command passes from now on, from any thread, and the wheels stop."""
        with self.lock:
            self.gate_open = False
            self._call("stop", self.inner.stop)

    def close_gate_within(self, wait_s: float) -> bool:
        """close_gate() from another thread, which must not wait for ever on a call that hangs: False when
        the lock stayed busy (the gate is closed all the same; the hung-call check takes it from there)."""
        self.gate_open = False
        if not self.lock.acquire(timeout=wait_s):
            return False
        try:
            self.close_gate()
        finally:
            self.lock.release()
        return True

    def set_wheel_speeds(self, left_m_s: float, right_m_s: float) -> None:
        with self.lock:
            if self.gate_open:        # hold, e-stop, watchdog: a command from anywhere is dropped
                self._call("set_wheel_speeds", self.inner.set_wheel_speeds, left_m_s, right_m_s)

    def stop(self) -> None:
        self._call("stop", self.inner.stop)

    def proximity(self) -> List[float]:
        return self._call("proximity", self.inner.proximity)

    def encoders(self) -> WheelOdometry:
        return self._call("encoders", self.inner.encoders)

    def battery_v(self) -> Optional[float]:
        """The driver's reading, None (no reading, as `ctl status` shows it) for one the hub would drop with the
        whole telemetry: NaN, a string, 1e300 V."""
        value = self._call("battery_v", self.inner.battery_v)
        try:
            battery_reading(value, "battery_v")
        except ProtocolError:
            return None
        return value

    def close(self) -> None:
        with self.lock:
            self.gate_open = False
            self.inner.close()


class StepWatchdog:
    """A daemon thread watching the behaviour's step: ``begin()`` and ``end()`` bracket each call."""

    def __init__(self, driver: GuardedDriver, limit_s: float, stop_requested: Callable[[], bool],
                 log: Callable[[str], None], robot_id: int):
        self.driver, self.limit_s, self.stop_requested = driver, limit_s, stop_requested
        self.log, self.robot_id = log, robot_id
        self.started_at: Optional[float] = None
        self.step_thread: Optional[int] = None
        self.stops_wheels = True
        self.tripped = False
        self._running = threading.Event()
        self._thread: Optional[threading.Thread] = None

    def start(self) -> None:
        if self._thread is None or not self._thread.is_alive():
            self._running.set()
            self._thread = threading.Thread(target=self._watch, name="step-watchdog", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._running.clear()

    def begin(self, stops_wheels: bool = True) -> None:
        """A step starts. ``stops_wheels`` False in lockstep: the simulated wheels wait for the step's answer,
        and a slow step (a loaded machine) that lost its wheel commands made the run depend on the load."""
        self.stops_wheels = stops_wheels
        self.step_thread = threading.get_ident()
        self.tripped = False        # a trip on the step before, after it had ended, must not spare this one
        self.started_at = time.monotonic()

    def end(self) -> None:
        self.started_at = None
        if self.tripped:
            self.tripped = False
            after = "; the wheels stay stopped until the next step commands them" if self.stops_wheels else ""
            self.log(f"agent {self.robot_id}: the behaviour's step() returned{after}")

    def _watch(self) -> None:
        stop_asked_at: Optional[float] = None
        while self._running.is_set():
            time.sleep(POLL_S)
            started = self.started_at
            now = time.monotonic()
            self._end_if_a_driver_call_hangs(now)
            if started is None:
                stop_asked_at = None
                continue
            # started_at read again: the step may have ended since (a trip then stopped wheels for nothing,
            # and its tripped flag, never reset by end(), let the next step hang with its wheels on).
            if not self.tripped and now - started > self.limit_s and self.started_at == started:
                self.tripped = True
                if self.stops_wheels:
                    self._stop_wheels()
                what = "wheels stopped" if self.stops_wheels else "lockstep: its simulated wheels wait for it; " \
                    "a robot's would stop here"
                self.log(f"agent {self.robot_id}: the behaviour's step() has run for {now - started:.2f} s: "
                         f"{what} (e-stop and the hub's watchdog act between steps only: step() must return)"
                         + self._where())
            if self.stop_requested():
                stop_asked_at = stop_asked_at or now
                if now - stop_asked_at > STUCK_EXIT_AFTER_S:
                    self._stop_wheels()
                    self.log(f"agent {self.robot_id}: asked to stop, but step() has not returned for "
                             f"{now - started:.1f} s: exiting without it")
                    os._exit(1)

    def _where(self) -> str:
        """Where the stuck step is, for its author: a bare "has run for 0.26 s" left them to guess which of
        their loops waits for ever."""
        frame = sys._current_frames().get(self.step_thread) if self.step_thread is not None else None
        place = code_place(frame)
        return f"; it is at {place}" if place else ""

    def _end_if_a_driver_call_hangs(self, now: float) -> None:
        called = self.driver.call_started
        if called is not None and now - called > DRIVER_CALL_LIMIT_S:
            self.log(f"agent {self.robot_id}: the driver's {self.driver.call_name}() has not returned for "
                     f"{now - called:.1f} s (a stuck bus?): nothing can stop the wheels or reach the robot from "
                     "here; exiting, so that the wheel guard stops them")
            os._exit(1)

    def _stop_wheels(self) -> None:
        if not self.driver.stoppable_from_any_thread:
            self.driver.gate_open = False    # what the stuck step sends is dropped; the hub holds the wheels
            return
        try:
            self.driver.close_gate_within(STOP_LOCK_WAIT_S)
        except DriverError as err:
            self.log(f"agent {self.robot_id}: cannot stop the wheels: {err}")


_LIBRARY_DIRS = tuple(os.path.normcase(os.path.realpath(path)) + os.sep for path in
                      {sysconfig.get_paths()[name] for name in ("stdlib", "platstdlib", "purelib", "platlib")})


def code_place(frame: Optional[FrameType]) -> str:
    """'wander.py:42, in step()': the innermost frame of code that is not Python's library or an installed
    package (a behaviour waiting in time.sleep() is shown at its own line that called it); the innermost frame
    when all of them are."""
    innermost = frame
    while frame is not None:
        if not os.path.normcase(os.path.realpath(frame.f_code.co_filename)).startswith(_LIBRARY_DIRS):
            break
        frame = frame.f_back
    frame = frame or innermost
    if frame is None:
        return ""
    path = frame.f_code.co_filename
    try:
        shown = os.path.relpath(path) if not os.path.relpath(path).startswith("..") else path
    except ValueError:          # another drive (Windows)
        shown = path
    return f"{shown}:{frame.f_lineno}, in {frame.f_code.co_name}()"
