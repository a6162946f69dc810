"""The radio relay: what robot i broadcasts reaches only the robots within d_C of i.

Each receiver has a bounded queue (the oldest message is dropped when it is full); each delivery is lost
with probability ``drop``; payloads above ``max_bytes`` and messages from unknown senders never enter.
Queued messages ride on the receiver's next downlink frames.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any, Deque, Dict, Iterable, List, Tuple

import numpy as np

Queued = Tuple[int, float, Dict[str, Any], int]   # sender, sent_s, payload, encoded size


@dataclass
class RelayStats:
    sent: int = 0              # broadcasts accepted
    delivered: int = 0         # messages handed to a downlink frame
    dropped_random: int = 0    # lost to the configured drop rate
    dropped_overflow: int = 0  # pushed out of a full receiver queue
    refused: int = 0           # too large or from an unknown sender

    def as_dict(self) -> Dict[str, int]:
        return dict(self.__dict__)


class RadioRelay:
    def __init__(self, robot_ids: Iterable[int], drop: float, queue_len: int, max_bytes: int,
                 rng: np.random.Generator):
        self.queues: Dict[int, Deque[Queued]] = {rid: deque() for rid in robot_ids}
        self.drop = drop
        self.queue_len = queue_len
        self.max_bytes = max_bytes
        self.rng = rng
        self.stats = RelayStats()

    def submit(self, sender: int, sent_s: float, payload: Dict[str, Any], size: int,
               receivers: Iterable[int]) -> bool:
        """Queue a broadcast for its receivers; False (and counted) when refused."""
        if sender not in self.queues or size > self.max_bytes:
            self.stats.refused += 1
            return False
        self.stats.sent += 1
        for receiver in receivers:
            queue = self.queues.get(receiver)
            if queue is None or receiver == sender:
                continue
            if self.drop > 0.0 and self.rng.random() < self.drop:
                self.stats.dropped_random += 1
                continue
            if len(queue) >= self.queue_len:
                queue.popleft()
                self.stats.dropped_overflow += 1
            queue.append((sender, sent_s, payload, size))
        return True

    def pending(self, receiver: int) -> bool:
        """Whether messages wait for this receiver (cheap: the frame path asks before building a tail)."""
        return bool(self.queues.get(receiver))

    def take(self, receiver: int, budget_bytes: int) -> List[list]:
        """Messages for one frame, oldest first, as ``[sender, sent_s, payload]``, up to ``budget_bytes``."""
        queue = self.queues.get(receiver)
        out: List[list] = []
        while queue:
            sender, sent_s, payload, size = queue[0]
            cost = size + 32   # sender, stamp, brackets
            if out and cost > budget_bytes:
                break           # the rest waits for the next frame
            budget_bytes -= cost
            queue.popleft()
            out.append([sender, sent_s, payload])
        self.stats.delivered += len(out)
        return out

    def clear(self, receiver: int) -> None:
        queue = self.queues.get(receiver)
        if queue is not None:
            queue.clear()
