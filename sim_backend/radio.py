"""Simulated radio: range-limited broadcast with per-receiver loss and latency.

A message broadcast at control step k reaches receivers within d_C (at send time) no earlier than step k+1,
plus ``latency_s`` rounded up to whole control periods; each receiver independently loses it with
probability ``drop``. A robot keeps at most ``Radio.INBOX_LIMIT`` messages between two of its steps, as the
agent on a robot does: beyond, the oldest are dropped (``dropped_overflow``), so a behaviour that floods its
neighbours loses messages here as it would in the lab.
"""
from __future__ import annotations

import math
from collections import deque
from typing import Any, Deque, Dict, List, Tuple

import numpy as np

from onboard.hal import Message, Radio

_new_instance = object.__new__


class RadioNetwork:
    def __init__(self, count: int, drop: float, latency_s: float, period_s: float, rng: np.random.Generator):
        self.count = count
        self.drop = drop
        self.delay_steps = 1 + math.ceil(latency_s / period_s - 1e-9)
        self.rng = rng
        # (due step, message, receivers) in sending order. Every message waits the same number of steps, so
        # this is also the order they fall due in, and each inbox fills in sending order.
        self._queue: Deque[Tuple[int, Message, List[int]]] = deque()
        self.sent = 0
        self.delivered = 0
        self.dropped = 0
        self.dropped_overflow = 0

    def send(self, step: int, sender: int, payload: Dict[str, Any], sent_s: float, receivers: np.ndarray) -> None:
        self.sent += 1
        if len(receivers) == 0:
            return
        if self.drop > 0.0:
            keep = self.rng.random(len(receivers)) >= self.drop
            self.dropped += int(len(receivers) - keep.sum())
            receivers = receivers[keep]
        message = _new_instance(Message)             # Message(sender, payload, sent_s), minus the frozen
        message.__dict__.update(sender=sender, payload=payload, sent_s=sent_s)   # dataclass's setattr calls
        self._queue.append((step + self.delay_steps, message, receivers.tolist()))

    def deliver(self, step: int, inboxes: List[List[Message]], alive: np.ndarray) -> None:
        """Move every message due by ``step`` into its receiver's inbox (dead receivers get nothing)."""
        queue = self._queue
        living = alive.tolist()
        while queue and queue[0][0] <= step:
            _, message, receivers = queue.popleft()
            for receiver in receivers:
                if living[receiver]:
                    inboxes[receiver].append(message)
                    self.delivered += 1
        limit = Radio.INBOX_LIMIT
        for inbox in inboxes:
            if len(inbox) > limit:        # the oldest go, as from the agent's inbox (onboard/agent/devices.py)
                excess = len(inbox) - limit
                del inbox[:excess]
                self.delivered -= excess
                self.dropped_overflow += excess

    def stats(self) -> Dict[str, int]:
        return {"sent": self.sent, "delivered": self.delivered, "dropped": self.dropped,
                "dropped_overflow": self.dropped_overflow}
