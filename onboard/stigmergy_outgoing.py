"""The sending half of a tuple space (:class:`onboard.stigmergy.TupleSpace`): what each ``outgoing()`` carries,
and when an entry accepted from a peer is relayed (after a delay, or not at all once enough copies were heard).

Runs on the robots: standard library only, Python 3.9.
"""
from __future__ import annotations

from typing import Any, List, Optional

from .stigmergy_entries import Gossip, _empty_gossip


class Outgoing:
    """Mixed into TupleSpace, whose ``__init__`` sets the state these methods share with its merging half:
    ``_entries``, ``_wire`` and ``_order`` (the replica), ``_dirty`` (key -> sends left), ``_cursor``,
    ``_calls``, ``_pending``, ``_pending_wires`` and ``_next_due`` (relays waiting), and the settings."""

    def outgoing(self) -> Gossip:
        """This step's broadcast: dirty keys newest first, then round-robin over the others (anti-entropy,
        every ``anti_entropy_period`` calls). Empty when there is nothing to say: a caller may skip it."""
        calls = self._calls = self._calls + 1
        if self._pending and self._next_due < calls:
            self._release_relays(calls)
        if not self._dirty and self.anti_entropy_period != 1 and (calls + self.owner) % self.anti_entropy_period:
            return _empty_gossip()                 # nothing changed and no anti-entropy turn (most calls)
        chosen: List[str] = []
        size = self._take_dirty(chosen)
        if size is not None and (self.anti_entropy_period == 1 or (calls + self.owner) % self.anti_entropy_period == 0):
            self._take_round_robin(chosen, size)
        entries = self._entries
        return Gossip([[key, entries[key].value, entries[key].timestamp, entries[key].writer] for key in chosen],
                      [self._wire[key] for key in chosen])

    def _release_relays(self, calls: int) -> None:
        """Accepted entries whose wait is over (and that nobody relayed often enough meanwhile) become dirty."""
        due = [key for key, waiting in self._pending.items() if waiting[0] < calls]
        for key in due:
            self._drop_pending(key)
            self._dirty[key] = self.relay_rounds
            self._dirty.move_to_end(key)
        # The earliest call at which a waiting entry falls due, so that outgoing() skips this scan until then.
        self._next_due = min((waiting[0] for waiting in self._pending.values()), default=0)

    def _take_dirty(self, chosen: List[str]) -> Optional[int]:
        """Fill ``chosen`` with dirty keys; return the message size so far, None if the byte budget is spent."""
        size, blocked = 2, False                   # 2: the enclosing "[]"
        for key in reversed(self._dirty):
            if len(chosen) >= self.max_entries_per_message:
                break
            extra = len(self._wire[key]) + (1 if chosen else 0)   # one comma between items
            if size + extra > self.max_bytes:
                blocked = True                     # keep priority: older dirty keys wait for the next message
                break
            chosen.append(key)
            size += extra
        for key in chosen:                         # after the loop: no mutation while iterating
            left = self._dirty[key] - 1
            if left:
                self._dirty[key] = left            # assignment keeps the key's place in the order
            else:
                del self._dirty[key]
        return None if blocked else size

    def _take_round_robin(self, chosen: List[str], size: int) -> None:
        picked = set(chosen)
        count = len(self._order)
        for _ in range(count):                     # at most one lap: never the same key twice
            if len(chosen) >= self.max_entries_per_message:
                return
            key = self._order[self._cursor]
            length = len(self._wire[key])
            if key not in picked and length + 2 <= self.max_bytes:   # oversized keys are skipped for good
                extra = length + (1 if chosen else 0)
                if size + extra > self.max_bytes:
                    return                         # cursor stays: this key opens the next message's share
                chosen.append(key)
                size += extra
            self._cursor = (self._cursor + 1) % count


    def _heard(self, versions: Any, sender: Optional[int]) -> None:
        """Copies of versions waiting to be relayed arrived: count them, and drop those heard often enough.
        (Each waiting version belongs to its own key, so the order they are counted in does not matter.)"""
        pending_wires = self._pending_wires
        for wire in versions.intersection(pending_wires):   # dropping one leaves the others' entries in place
            key = pending_wires[wire]
            waiting = self._pending[key]
            if sender != waiting[3]:               # the writer's own resends say nothing about other relays
                waiting[1] += 1
                if self.relay_quorum and waiting[1] >= self.relay_quorum:
                    self._drop_pending(key)

    def _heard_plain(self, raw: Any, sender: Optional[int]) -> None:
        """The same for an entry of a plain list that ``_known`` found held already (or stale)."""
        key = raw[0] if type(raw) is list and len(raw) == 4 else None
        waiting = self._pending.get(key) if type(key) is str else None
        local = self._entries.get(key) if waiting is not None else None
        if local is not None and raw[2] == local.timestamp and raw[3] == local.writer:
            self._count_copy(key, sender)

    def _count_copy(self, key: str, sender: Optional[int]) -> None:
        waiting = self._pending[key]
        if sender == waiting[3]:
            return                                 # the writer's own resends say nothing about other relays
        waiting[1] += 1
        if self.relay_quorum and waiting[1] >= self.relay_quorum:
            self._drop_pending(key)

    def _drop_pending(self, key: str) -> None:
        waiting = self._pending.pop(key, None)
        if waiting is not None:
            del self._pending_wires[waiting[2]]
