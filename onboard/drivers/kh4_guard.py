"""The wheel guard: a second process that stops a KheperaIV's wheels when the agent dies without doing so.

The agent stops the wheels on every way out it can see (SIGINT, SIGTERM, an exception, its watchdog), but a
process killed with SIGKILL, or by the kernel's out-of-memory killer, runs none of its own code: the dsPic
keeps the last speed it was given, and the hub's e-stop, which travels through the agent, reaches nobody.
So the agent starts this guard next to it. The guard holds the read end of a pipe whose write end only the
agent holds; when the agent dies, for whatever reason, the kernel closes its end and the guard's read
returns. If the agent said ``clean`` first (it closed the driver, wheels stopped, motors idle), the guard
just exits; otherwise it opens libkhepera itself (the dead process's hold on the I2C bus is gone with it),
stops the wheels, idles the motors and exits.

The guard runs in its own session, so a Ctrl-C in the agent's terminal does not reach it, and it needs
nothing but this package and libkhepera.

    python -m onboard.drivers.kh4_guard LIBRARY_PATH PARENT_PID     (started by the agent, not by hand)
"""
from __future__ import annotations

import os
import subprocess
import sys
from typing import IO, List, Optional

CLEAN = b"clean\n"


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


def _child_environment() -> dict:
    """This process's environment, with the folder holding ``onboard`` on the guard's import path."""
    here = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env = dict(os.environ)
    env["PYTHONPATH"] = here + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def guard(library_path: str, parent_pid: int, stream: IO[bytes]) -> int:
    from onboard.drivers.kh4 import LibkheperaError, stop_robot  # loaded now: react at once

    said = stream.read()          # returns when the agent closes the pipe, or dies
    if said.endswith(CLEAN):
        return 0
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


def main(argv: Optional[List[str]] = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2 or not args[1].isdigit():
        print("usage: python -m onboard.drivers.kh4_guard LIBRARY_PATH PARENT_PID (the agent starts it)",
              file=sys.stderr)
        return 2
    return guard(args[0], int(args[1]), sys.stdin.buffer)


if __name__ == "__main__":
    sys.exit(main())
