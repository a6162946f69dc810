"""Running a hub process: bind, serve until SIGINT/SIGTERM, say which run the signal ended, tell the robots to
stop, close the log."""
from __future__ import annotations

import signal
import sys
from typing import Callable

from onboard.config import ConfigError
from onboard.console import flush_quietly, say, stop_signals

from .binding import is_loopback
from .config import LabConfig
from .factory import build_hub
from .run_events import end_by_signal

INSECURE_WARNING = """\
************************************************************************
*  WARNING: insecure (--insecure or security.insecure): no encryption  *
*  and no authentication. Anyone who can reach these ports can drive   *
*  the robots and read the lab's traffic. Use it only on loopback or   *
*  an isolated test network.                                           *
************************************************************************"""


def print_now(line: str) -> None:
    """One hub line on stdout, flushed (supervisors and tests read them through a pipe). A terminal that is
    gone (EIO after SIGHUP) drops it: a failing line would end the hub, or skip closing its log mid-shutdown."""
    say(line, sys.stdout)


def discard_log(hub) -> None:
    """A hub that could not start (a port in use, ...) recorded nothing: its new log would only stand in the
    way of the next attempt, since the hub never writes over a log."""
    if hub.recorder is not None:
        try:
            hub.recorder.path.unlink()
        except OSError:
            pass


def check_servable(config: LabConfig) -> None:
    """Refuse what this loop would not do. Only ``khepri sil`` drives the lockstep (``hub.lockstep``): served here,
    physics ran by the wall clock while the agents, told lockstep, stepped once per frame, at downlink_hz (20
    Hz) instead of the scenario's control rate."""
    if config.source.type == "sim" and config.source.lockstep:
        raise ConfigError("source.lockstep", "khepri hub paces the simulation by the wall clock; a lockstep run is "
                          "`khepri sil SCENARIO`, which waits for every agent's answer at each step (remove it)")


def serve_hub(config: LabConfig, log: Callable[[str], None] = print_now) -> int:
    check_servable(config)
    hub = build_hub(config, log=log)
    if config.security.insecure:     # after the config's own errors: a refused config serves nobody
        say(INSECURE_WARNING)
        bind = config.network.bind
        if not is_loopback(bind):       # the banner says "only on loopback": this is not
            where = "every network interface" if bind in ("*", "0.0.0.0", "::") else bind
            say(f"hub: INSECURE and not on loopback: listening on {where} (network.bind {bind}), and "
                "security.keys is not used")
    stop = {"requested": False, "signal": None}

    def request_stop(signum, frame):
        stop["requested"] = True
        stop["signal"] = signal.Signals(signum).name

    previous = {sig: signal.signal(sig, request_stop) for sig in stop_signals()}
    served = False
    said = ""
    try:
        hub.bind()
        served = True
        if config.run.autostart:
            hub.control.execute("start", "config (run.autostart)")
        hub.serve(lambda: stop["requested"])
        if stop["signal"] is not None:     # before close: the log is still open, and the agents not yet told
            said = end_by_signal(hub, stop["signal"])
    finally:
        hub.close()
        if not served:
            discard_log(hub)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    log(f"hub: stopped{said}")
    flush_quietly()          # nothing left for the exit's own flush to fail on, should the terminal be gone
    return 0
