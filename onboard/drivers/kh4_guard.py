"""The wheel guard: a second process that stops a KheperaIV's wheels when the agent dies without doing so.

The agent stops the wheels on every way out it can see (SIGINT, SIGTERM, an exception, its watchdog), but a
process killed with SIGKILL, or by the kernel's out-of-memory killer, runs none of its own code: the dsPic
keeps the last speed it was given, and the hub's e-stop, which travels through the agent, reaches nobody.
So the agent starts this guard next to it. The guard holds the read end of a pipe whose write end only the
agent holds; when the agent dies, for whatever reason, the kernel closes its end and the guard's read
returns. If the agent said ``clean`` first (it closed the driver, wheels stopped, motors idle), the guard
just exits; otherwise it opens libkhepera itself (the dead process's hold on the I2C bus is gone with it),
stops the wheels, idles the motors and exits. An agent whose close() stopped the wheels by one of the two
ways only (``WheelsStoppedPartly``) says so first (``partly ...``): the guard still tries both again, but
does not say the agent left the wheels turning.

The guard runs in its own session, so a Ctrl-C in the agent's terminal does not reach it, and it ignores
SIGTERM, SIGINT and SIGHUP: ``pkill -f khepri`` (or a service stop) sends SIGTERM to every process, and a
guard that died of it left an agent stuck in a libkhepera call, then killed by hand, with nobody to stop its
wheels.
It ends when the agent does (SIGKILL still ends it). It needs nothing but this package and libkhepera.

    python -m onboard.drivers.kh4_guard LIBRARY_PATH PARENT_PID     (started by the agent, not by hand)
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
from typing import IO, List, Optional

CLEAN = b"clean\n"
PARTLY = b"partly "     # then what close() managed, as _stop_and_idle says it, and a newline


def stopped_partly_note(partly: str) -> bytes:
    """What the agent tells the guard when its close() stopped the wheels but one of its two calls failed."""
    return PARTLY + " ".join(partly.split()).encode("utf-8", "replace") + b"\n"


def _stopped_partly(said: bytes) -> Optional[str]:
    """The agent's note from :func:`stopped_partly_note`, or None if it said none (or died writing it)."""
    if not (said.startswith(PARTLY) and said.endswith(b"\n")):
        return None
    return said[len(PARTLY):-1].decode("utf-8", "replace")


class WheelGuard:
    """The agent's side: the guard process and the pipe to it."""

    def __init__(self, process: subprocess.Popen):
        self.process = process
        self.pipe: Optional[IO[bytes]] = process.stdin

    @classmethod
    def start(cls, library_path: str) -> WheelGuard:
        command = [sys.executable, "-m", "onboard.drivers.kh4_guard", library_path, str(os.getpid())]
        process = subprocess.Popen(command, stdin=subprocess.PIPE, start_new_session=True,
                                   env=_child_environment())
        return cls(process)

    def release(self) -> None:
        """The agent stopped the wheels itself: tell the guard, which then exits without touching them."""
        if self.pipe is None:
            return
        try:
            self.pipe.write(CLEAN)
            self.pipe.close()
        except OSError:
            pass            # the guard is gone already: nothing to tell
        self.pipe = None

    def tell_stopped_partly(self, partly: str) -> None:
        """The agent's close() stopped the wheels, ``partly`` (one of its two calls failed). The guard stays
        armed: once the agent ends, it tries both again, and says the agent had stopped the wheels."""
        if self.pipe is None:
            return
        try:
            self.pipe.write(stopped_partly_note(partly))
            self.pipe.flush()       # kept open: closing it would tell the guard the agent is gone
        except OSError:
            pass


def _child_environment() -> dict:
    """This process's environment, with the folder holding ``onboard`` on the guard's import path."""
    here = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env = dict(os.environ)
    env["PYTHONPATH"] = here + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def guard(library_path: str, parent_pid: int, stream: IO[bytes]) -> int:
    from onboard.drivers.libkhepera import LibkheperaError, stop_robot  # loaded now: react at once

    said = stream.read()          # returns when the agent closes the pipe, or dies
    if said.endswith(CLEAN):
        return 0
    agent_stopped = _stopped_partly(said)
    if agent_stopped is not None:
        return _guard_after_partial_stop(library_path, parent_pid, agent_stopped)
    try:
        # Opens the dsPic, stops, idles, releases; no motor set-up to fail first.
        partly = stop_robot(library_path)
    except (LibkheperaError, OSError) as err:
        print(f"kh4 wheel guard: agent {parent_pid} ended without stopping the wheels, and they could not be "
              f"stopped: {err}",
              file=sys.stderr, flush=True)
        return 1
    print(f"kh4 wheel guard: agent {parent_pid} ended without stopping the wheels; they are stopped now"
          + (f", {partly}" if partly else ""), file=sys.stderr, flush=True)
    return 0


def _guard_after_partial_stop(library_path: str, parent_pid: int, agent_stopped: str) -> int:
    """The agent stopped the wheels as it closed the driver, by one way only: try both again, and say what the
    agent did, then what this did. The wheels stand still whatever this manages: exit code 0."""
    from onboard.drivers.libkhepera import LibkheperaError, stop_robot

    try:
        partly = stop_robot(library_path)
        after = (f"the guard tried both again: the wheels are stopped, {partly}" if partly
                 else "the guard tried both again, and both passed")
    except (LibkheperaError, OSError) as err:
        after = f"the guard tried both again, and failed: {err}"
    print(f"kh4 wheel guard: agent {parent_pid} stopped the wheels before it ended, {agent_stopped}; {after}",
          file=sys.stderr, flush=True)
    return 0


def ignore_stop_signals() -> None:
    """The guard outlives the agent whatever asks the agent's processes to stop (see the module's docstring)."""
    for name in ("SIGTERM", "SIGINT", "SIGHUP"):
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), signal.SIG_IGN)


def main(argv: Optional[List[str]] = None) -> int:
    ignore_stop_signals()
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2 or not args[1].isdigit():
        print("usage: python -m onboard.drivers.kh4_guard LIBRARY_PATH PARENT_PID (the agent starts it)",
              file=sys.stderr)
        return 2
    return guard(args[0], int(args[1]), sys.stdin.buffer)


if __name__ == "__main__":
    sys.exit(main())
