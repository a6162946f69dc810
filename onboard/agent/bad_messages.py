"""The agent's account of the hub's messages it drops, as the hub gives its own (docs/protocol.md): each is
counted, at most one line a second says one, and the drops that second hid are said too, with the next line or
once the second is over. The agent said only its first line: ten junk frames, a bad mode and a NaN pose were
"dropped a bad message (1 so far)", and eleven more went unsaid but for its telemetry's ``frames_bad``."""
from __future__ import annotations

import math
from typing import Callable

from ..console import drop_span

LINE_EVERY_S = 1.0     # at most one line a second: a hub gone wrong must not bury the agent's log


class BadMessages:
    """Counts the hub's bad messages (``count``: the telemetry's ``frames_bad``) and says them to ``log``."""

    def __init__(self, robot_id: int, log: Callable[[str], None]):
        self.robot_id, self.log = robot_id, log
        self.count = 0
        self.hidden = 0                     # dropped since the last line, and not said yet
        self.last_line = -math.inf

    def drop(self, detail: str, now: float) -> None:
        self.count += 1
        since = now - self.last_line
        if since < LINE_EVERY_S:
            self.hidden += 1
            return
        more = f" (+{self.hidden} more in the last {drop_span(since)})" if self.hidden else ""
        self.hidden, self.last_line = 0, now
        self.log(f"agent {self.robot_id}: dropped a bad message ({self.count} so far): {detail}{more}")

    def flush(self, now: float) -> None:
        """Say the drops a burst hid once its second is over, not only with the hub's next bad message, which may
        never come."""
        since = now - self.last_line
        if not self.hidden or since < LINE_EVERY_S:
            return
        more, self.hidden, self.last_line = self.hidden, 0, now
        self.log(f"agent {self.robot_id}: dropped {more} more bad message{'s' if more > 1 else ''} from the hub in "
                 f"the last {drop_span(since)} ({self.count} so far; the telemetry's frames_bad counts them)")

