"""Bookkeeping records for the hub: one per robot, drop counters with rate-limited log lines, a rate meter."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional

import zmq

from onboard.console import drop_span

REPEAT_QUIET_MAX_S = 60.0   # the longest a sender repeating one bad message goes unmentioned


# Agents that drive no real wheels: the simulated robot's (sil), and the hub benchmark's clients. Any other
# driver (kh4) moves a robot in the room, and is held when the poses do not come from the room (Hub.mode_for).
VIRTUAL_DRIVERS = ("sim", "bench")

@dataclass
class RobotLink:
    """What the hub knows about one robot and its agent."""

    id: int
    routing: Optional[bytes] = None          # the agent's ZeroMQ routing id (None: never heard from)
    agent: Optional[str] = None              # the token its agent process puts on every message (None: older agents)
    replaced_routing: Optional[bytes] = None     # that agent's previous connection, after it reconnected
    peer: str = ""                           # the agent's network address
    driver: str = ""
    run_id: Optional[str] = None             # the run the agent says it holds
    last_uplink: float = -math.inf           # hub monotonic time of the last valid message
    telemetry: Optional[Dict[str, Any]] = None
    step_answered: int = -1                  # seq of the last frame the agent answered (lockstep)
    seq: int = 0                             # downlink frames sent
    next_due: float = 0.0                    # when the next downlink frame is due
    pending: Optional[Dict[str, Any]] = None     # a command re-sent until acknowledged
    pending_sent_at: float = -math.inf
    estop_ack_s: Optional[float] = None      # e-stop to acknowledgement (wheels already stopped)
    frames_dropped: int = 0                  # downlink frames refused by a full queue (latest-only)
    unresponsive_steps: int = 0              # lockstep: consecutive steps without an answer
    silent_since: float = -math.inf          # lockstep: when the first of those unanswered frames was sent
    silent_since_clock_s: float = 0.0        # ...and the simulated time it carried
    rival_since: float = -math.inf           # a second connection claiming this id: its first message...
    rival_seen: float = -math.inf            # ...and its latest one
    rival_warned: float = -math.inf          # when the hub last said so
    silence_said: bool = False               # the hub said it went silent, and has not yet said it is back

    def connected(self, now: float, timeout_s: float) -> bool:
        return self.routing is not None and now - self.last_uplink <= timeout_s

    def status_row(self, now: float, timeout_s: float, mode: str, reason: str) -> Dict[str, Any]:
        telemetry = self.telemetry or {}
        behaviour = telemetry.get("behaviour") or {}
        loop = telemetry.get("loop") or {}
        connected = self.connected(now, timeout_s)
        return {
            "id": self.id,
            "connected": connected,
            "last_seen_s": None if self.last_uplink == -math.inf else round(now - self.last_uplink, 3),
            "peer": self.peer,
            "driver": self.driver,
            "run_id": self.run_id,
            "mode": mode,
            "reason": reason,
            "agent_mode": telemetry.get("mode"),
            "state": behaviour.get("state"),
            "finished": behaviour.get("finished"),     # the robot considers its job done (None: no run)
            # A silent agent's last rate would read as a loop still running (a SIGKILLed agent showed 10.0 Hz).
            "loop_hz": loop.get("hz") if connected else None,
            "loop_misses": loop.get("misses"),
            "battery_v": telemetry.get("battery_v"),
            "frames_lost": telemetry.get("frames_lost"),
            "frames_dropped": self.frames_dropped,
            "estop_ack_ms": None if self.estop_ack_s is None else round(self.estop_ack_s * 1000.0, 2),
            "error": telemetry.get("error"),
            "refused_run_id": telemetry.get("refused_run_id"),     # the run it said it cannot start
        }


KNOWN_PROBLEMS = 16      # per sender: the problems whose lines count as repeats (a lab's robots, a few kinds)


@dataclass
class DropLog:
    """Counts every dropped message by reason and sender, and says them without flooding the console: at most
    one line per sender per second, and a sender that keeps sending the same bad message (an agent with an id
    not in the lab says hello every second) is said at growing intervals, up to every REPEAT_QUIET_MAX_S."""

    log: Callable[[str], None]
    on_drop: Optional[Callable[[str, str], None]] = None
    counts: Dict[str, int] = field(default_factory=dict)
    _last_line: Dict[str, float] = field(default_factory=dict)
    _last_key: Dict[str, str] = field(default_factory=dict)        # the last problem said, per sender
    _known: Dict[str, List[str]] = field(default_factory=dict)     # the keys a sender's lines said lately
    _quiet_s: Dict[str, float] = field(default_factory=dict)
    _suppressed: Dict[str, int] = field(default_factory=dict)
    _hidden_reasons: Dict[str, Dict[str, int]] = field(default_factory=dict)   # sender -> reason -> count

    def count(self, reason: str, sender: str) -> None:
        """Count a drop without a log line (the caller says it its own way)."""
        self.counts[reason] = self.counts.get(reason, 0) + 1
        if self.on_drop is not None:
            self.on_drop(reason, sender)

    def drop(self, reason: str, sender: str, detail: str, key: Optional[str] = None) -> None:
        """``key``: what makes two drops the same problem, when ``detail`` varies (a size); default ``detail``."""
        self.count(reason, sender)
        now = time.monotonic()
        since = now - self._last_line.get(sender, -math.inf)
        key = detail if key is None else key
        # A new problem from a sender is said within a second, however long its last repeated one made it wait:
        # on loopback every agent is one sender, and one agent's repeats hid another's new mistakes. A problem
        # said lately is not new: four stray agents on one PC, or two kinds of message in turn, are each said
        # once a second for ever when only the last one counts.
        quiet = self._quiet_s.get(sender, 1.0) if key in self._known.get(sender, ()) else 1.0
        if since < quiet:
            self._suppressed[sender] = self._suppressed.get(sender, 0) + 1
            hidden = self._hidden_reasons.setdefault(sender, {})
            hidden[reason] = hidden.get(reason, 0) + 1
            return
        more = self._suppressed.pop(sender, 0)
        self._hidden_reasons.pop(sender, None)
        suffix = f" (+{more} more from this sender in the last {drop_span(since)})" if more else ""
        self._said(sender, now, key)
        self.log(f"hub: dropped {reason}: {detail}{suffix}")
        if len(self._last_line) > 10_000:   # a flood of fake senders must not grow memory without bound
            for table in (self._last_line, self._last_key, self._known, self._quiet_s, self._suppressed,
                          self._hidden_reasons):
                table.clear()

    def _said(self, sender: str, now: float, key: str) -> None:
        """A problem said lately doubles the sender's quiet time; a new one starts it over at a second."""
        known = self._known.setdefault(sender, [])
        again = key in known
        self._quiet_s[sender] = min(REPEAT_QUIET_MAX_S, 2 * self._quiet_s.get(sender, 1.0)) if again else 1.0
        if not again:
            known.append(key)
            del known[:-KNOWN_PROBLEMS]
        self._last_line[sender], self._last_key[sender] = now, key

    def flush(self, now: float) -> None:
        """Say the drops a burst hid once its quiet time is over, not only with that sender's next drop, which
        may never come."""
        if not self._suppressed:
            return
        for sender in list(self._suppressed):
            since = now - self._last_line.get(sender, -math.inf)
            if since < self._quiet_s.get(sender, 1.0):
                continue
            more = self._suppressed.pop(sender)
            hidden = self._hidden_reasons.pop(sender, {})
            reasons = ", ".join(f"{reason} {count}" for reason, count in sorted(hidden.items()))
            self._said(sender, now, self._last_key.get(sender, ""))
            self.log(f"hub: dropped {more} more message{'s' if more > 1 else ''} from {sender} in the last "
                     f"{drop_span(since)} ({reasons}; `khepri ctl status` counts drops by reason)")

    @property
    def total(self) -> int:
        return sum(self.counts.values())


class RateMeter:
    """Events per second over a sliding window."""

    def __init__(self, window_s: float = 1.0):
        self.window_s = window_s
        self.window_start = time.monotonic()
        self.count = 0
        self.hz = 0.0
        self.last = -math.inf

    def tick(self, now: float) -> None:
        if self.last == -math.inf:
            self.window_start = now     # the first event starts the clock: stamps need not be monotonic()
        self.count += 1
        self.last = now
        elapsed = now - self.window_start
        if elapsed >= self.window_s:
            self.hz = self.count / elapsed
            self.count = 0
            self.window_start = now
        elif self.hz == 0.0 and elapsed >= 0.1 * self.window_s:
            self.hz = (self.count - 1) / elapsed     # a provisional rate before the first full window

    def current(self, now: float) -> float:
        """The rate, 0 once three periods have gone by without an event (half a second at least): at 200 Hz the
        last window's rate was shown for 2 s after the source had ended."""
        silent_after = min(2.0 * self.window_s, max(0.5, 3.0 / self.hz)) if self.hz > 0 else 2.0 * self.window_s
        return 0.0 if now - self.last > silent_after else self.hz


def frame_sender(frame: zmq.Frame, default_user: str) -> str:
    """Who sent a frame, as the drop log names them: 'robot:3 at 127.0.0.1' (the key's user, the peer)."""
    return f"{frame_property(frame, 'User-Id') or default_user} at {frame_property(frame, 'Peer-Address') or '?'}"


def frame_property(frame: zmq.Frame, name: str) -> Optional[str]:
    """A ZeroMQ metadata property of a received frame (``User-Id``, ``Peer-Address``), None when absent."""
    try:
        return frame.get(name)
    except zmq.ZMQError:      # no such property (e.g. no authentication: no User-Id)
        return None



class SparseFrames:
    """Says once when motion-capture frames keep coming further apart than ``stale_s``: each pose then goes stale
    before the next arrives, and every robot is held between two frames (a 2 Hz mock with the default 0.1 s did
    so without a word). Only a run of such gaps counts, each under ``silence_s``: one outage is not a rate, and a
    longer silence is said by the hub's own line."""

    RUN = 5

    def __init__(self, stale_s: float, silence_s: float, configured_s: Optional[float] = None):
        """``configured_s``: ``source.stale_s`` as the config gives it, when ``stale_s`` is it stretched (a replay
        slower than real time), so that the line names the value to change."""
        self.stale_s, self.silence_s = stale_s, silence_s
        stretched = configured_s is not None and configured_s != stale_s
        self.stale_text = (f"{configured_s:g} s, {stale_s:g} s at this replay's rate" if stretched
                           else f"{stale_s:g} s")
        self.last: Optional[float] = None
        self.run = 0
        self.said = False

    def tick(self, stamp: float) -> Optional[str]:
        gap = 0.0 if self.last is None else stamp - self.last
        self.last = stamp
        self.run = self.run + 1 if self.stale_s < gap <= self.silence_s else 0
        if self.said or self.run < self.RUN:
            return None
        self.said = True
        return (f"motion-capture frames come {gap:.2f} s apart, further than source.stale_s ({self.stale_text}): "
                "every robot loses its pose between frames and is held; raise source.stale_s above the frame "
                "period, or check the system's frame rate")
