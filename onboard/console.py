"""Console lines of a long-running process (an agent, the hub), which must never stop it.

An agent or a hub started by hand over ssh leaves when its terminal closes (SIGHUP), and from then on a write
to that terminal fails (EIO; a closed pipe, EPIPE). A failing line in the middle of the way out would skip
what comes after it: an agent's wheel stop and its last word to the hub, the hub's stop to the robots and its
log's footer. So a line that cannot be written is dropped, and the stream is pointed at /dev/null, so that
later lines and the interpreter's flush at exit write nowhere instead of failing again (a flush that fails at
exit turns exit code 0 into 120).
"""
from __future__ import annotations

import os
import signal
import sys
from typing import Optional, TextIO, Tuple


def stop_signals() -> Tuple[int, ...]:
    """The signals that end an agent or the hub as Ctrl-C does (wheels stopped, robots told, log closed):
    SIGINT, SIGTERM, and SIGHUP, the terminal or ssh session it was started from closing, which would otherwise
    kill it on the spot. Not SIGHUP when it is ignored already: `nohup khepri ...` is meant to outlive its
    terminal. Ask before installing the handlers (afterwards SIGHUP is no longer ignored)."""
    names = ["SIGINT", "SIGTERM"]
    if hasattr(signal, "SIGHUP") and signal.getsignal(signal.SIGHUP) != signal.SIG_IGN:
        names.append("SIGHUP")
    return tuple(getattr(signal, name) for name in names if hasattr(signal, name))


# Control characters but newline and tab, written as \xNN: a file name with \x01 printed as a name that exists
# ("no such file: c.yaml"), and a robot's text could carry terminal escape sequences onto the operator's console.
_VISIBLE = {code: f"\\x{code:02x}" for code in (*range(0, 9), *range(11, 32), 127)}


# One line of another's text (a robot's error, its behaviour's state) must stay one line, as it is: every C0
# character (newline, carriage return and tab too), DEL and C1, Unicode's line and paragraph separators, and
# the bidirectional controls that make a terminal show the characters after them in another order. A robot's
# "\n" put a line of its own making ("hub: run ... completed") on the hub's console and in its log.
_ONE_LINE = {code: f"\\x{code:02x}" for code in (*range(0, 32), *range(127, 160))}
_ONE_LINE.update({code: f"\\u{code:04x}" for code in (0x200E, 0x200F, 0x2028, 0x2029, *range(0x202A, 0x202F),
                                                      *range(0x2066, 0x206A))})


def drop_span(seconds: float) -> str:
    """How long the drops a line counts were hidden, for "(+3 more in the last second)": the hub's drop lines
    (hub/links.py) and the agent's (onboard/agent/bad_messages.py) say it alike."""
    return "second" if seconds < 2.0 else f"{seconds:.0f} s"


def one_line(text: str) -> str:
    """``text`` with each control character written as its escape (``\\x0a``, ``\\u2028``): shown on one line,
    never acting on the terminal."""
    return text.translate(_ONE_LINE)


def say(line: str, stream: Optional[TextIO] = None) -> None:
    """Print ``line`` to ``stream`` (stderr), flushed, control characters escaped; if the console is gone, drop
    it and silence the stream."""
    stream = sys.stderr if stream is None else stream
    line = line.translate(_VISIBLE)
    try:
        print(line, file=stream, flush=True)
    except BlockingIOError:                # a non-blocking stream that is full for now: this line only is lost
        pass
    except UnicodeEncodeError:             # a lone surrogate from a robot's text: the line escaped, not the console
        encoding = getattr(stream, "encoding", None) or "utf-8"
        say(line.encode(encoding, "backslashreplace").decode(encoding), stream)
    except (OSError, ValueError):          # ValueError: the stream was closed
        silence(stream)


def flush_quietly() -> None:
    """Flush stdout and stderr now, silencing a dead one, so that the interpreter's own flush at exit finds
    nothing to fail on (a behaviour's print() leaves lines in stdout's buffer)."""
    for stream in (sys.stdout, sys.stderr):
        if stream is None:
            continue
        try:
            stream.flush()
        except (OSError, ValueError):
            silence(stream)


def silence(stream: TextIO) -> None:
    """Point ``stream``'s file descriptor at /dev/null and drop what its buffer still holds for the dead
    console. A stream without a descriptor (a test's capture) is left as it is."""
    try:
        fd = stream.fileno()
        devnull = os.open(os.devnull, os.O_WRONLY)
    except (OSError, ValueError, AttributeError):
        return
    try:
        os.dup2(devnull, fd)
    except OSError:
        pass
    finally:
        os.close(devnull)
    try:
        stream.flush()                     # the kept bytes now go to /dev/null
    except (OSError, ValueError):
        pass
