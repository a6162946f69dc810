"""Virtual stigmergy: a tuple space replicated on every robot, after Buzz (Pinciroli et al. 2016).

Robots share state (bids, task claims, positions) over a lossy, range-limited, delayed radio. Every write
carries a per-key Lamport timestamp and the writer's id; each step a robot broadcasts ``outgoing()`` and
``merge()``s what it hears. The merge picks the same winner whatever the order, loss or duplication of
messages, and accepted entries are gossiped on, so a connected swarm converges once writes stop.

Wire format: a list of ``[key, value, timestamp, writer]`` lists, ready for JSON. With values of a few dozen
bytes a 24-entry message is around 1-3 KB; the radio refuses more than 8192 bytes, so ``outgoing()`` also stops
before the compact JSON (``payload_bytes``) exceeds ``max_bytes``. An entry too big alone is never sent.

Runs on the robots: standard library only, Python 3.9; no randomness, no clock, so simulations reproduce.
"""
from __future__ import annotations

import json
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Optional, Tuple


@dataclass(frozen=True)
class Entry:
    """One replicated value. Treat ``value`` as read-only: it is the replica's own copy."""

    value: Any
    timestamp: int
    writer: int


ConflictRule = Callable[[str, Entry, Entry], Entry]
"""``(key, local, remote) -> winner``; must return one of its two entries, the same one in either order."""


def payload_bytes(entries: Any) -> int:
    """Size in bytes of the compact JSON of a message, as the radio counts it."""
    return len(json.dumps(entries, separators=(",", ":")).encode("utf-8"))


def default_rule(key: str, local: Entry, remote: Entry) -> Entry:
    """Higher writer id wins; same writer: greater canonical JSON wins. A total order, so replicas agree."""
    if local.writer != remote.writer:
        return local if local.writer > remote.writer else remote
    local_json = json.dumps(local.value, sort_keys=True)
    return local if local_json >= json.dumps(remote.value, sort_keys=True) else remote


def lowest_field(field: str, tie_field: Optional[str] = None) -> ConflictRule:
    """Rule for bids: lower ``value[field]`` wins, then lower ``value[tie_field]``, then ``default_rule``.

    Only numbers count; a value without the field (or not a dict, or a non-number there) loses to one with it.
    """

    def rule(key: str, local: Entry, remote: Entry) -> Entry:
        local_rank = (_rank(local.value, field), _rank(local.value, tie_field))
        remote_rank = (_rank(remote.value, field), _rank(remote.value, tie_field))
        if local_rank != remote_rank:
            return local if local_rank < remote_rank else remote
        return default_rule(key, local, remote)

    return rule


def lowest_writer(key: str, local: Entry, remote: Entry) -> Entry:
    """Rule for claims such as two task positions under one key: the lower robot id wins."""
    if local.writer != remote.writer:
        return local if local.writer < remote.writer else remote
    return default_rule(key, local, remote)


def _rank(value: Any, field: Optional[str]) -> Tuple[int, Any]:
    # (0, number) sorts before (1, 0): having the field beats missing it. NaN counts as missing (unordered).
    found = value.get(field) if field is not None and isinstance(value, dict) else None
    if isinstance(found, (int, float)) and not isinstance(found, bool) and found == found:
        return (0, found)
    return (1, 0)


def _parse(raw: Any) -> Optional[Tuple[str, Any, int, int]]:
    """``[key, value, timestamp, writer]`` checked field by field, or None if malformed."""
    if not isinstance(raw, (list, tuple)) or len(raw) != 4:
        return None
    key, value, timestamp, writer = raw
    # ``type(...) is int`` also refuses True/False, which Python counts as ints.
    if type(key) is not str or type(timestamp) is not int or type(writer) is not int or timestamp < 0:
        return None
    return key, value, timestamp, writer


def _same(a: Any, b: Any) -> bool:
    """Equal as JSON values, strictly: unlike ``==``, 1, 1.0 and True differ (their JSON texts do)."""
    if type(a) is not type(b):
        return False
    if type(a) is dict:
        return a.keys() == b.keys() and all(_same(item, b[key]) for key, item in a.items())
    if type(a) is list:
        return len(a) == len(b) and all(map(_same, a, b))
    return a == b


# Compact and sorted: one text per JSON value, so equal values are equal strings on every replica.
# Built once: json.dumps with non-default options would build a new encoder on every call.
_canonical = json.JSONEncoder(separators=(",", ":"), sort_keys=True).encode


def _wire(key: str, canonical: str, timestamp: int, writer: int) -> str:
    # Same text as json.dumps([key, value, timestamp, writer], compact), built without re-encoding the value.
    return f"[{json.dumps(key)},{canonical},{timestamp},{writer}]"


class TupleSpace:
    """One robot's replica of the shared tuple space."""

    def __init__(self, owner: int, max_entries_per_message: int = 24, resend_rounds: int = 3,
                 conflict_rules: Optional[Dict[str, ConflictRule]] = None, max_bytes: int = 6000) -> None:
        if max_entries_per_message < 1 or resend_rounds < 1 or max_bytes < 3:
            raise ValueError("max_entries_per_message and resend_rounds must be >= 1, max_bytes >= 3")
        self.owner = owner
        self.max_entries_per_message = max_entries_per_message
        self.resend_rounds = resend_rounds
        self.max_bytes = max_bytes
        # Longest prefix first, so the first match is the most specific rule.
        self._rules = sorted((conflict_rules or {}).items(), key=lambda item: -len(item[0]))
        self._entries: Dict[str, Entry] = {}
        self._wire: Dict[str, str] = {}            # cached compact JSON of each entry: sizes and duplicates
        self._dirty: OrderedDict[str, int] = OrderedDict()   # key -> sends left; last = most recently changed
        self._order: List[str] = []                # round-robin order; keys are never removed, only appended
        self._cursor = 0
        self.rejected = 0
        self.last_rejected_sender: Optional[int] = None
        self.oversized = 0
        self.rule_errors = 0

    def get(self, key: str, default: Any = None) -> Any:
        found = self._entries.get(key)
        return default if found is None else found.value

    def entry(self, key: str) -> Optional[Entry]:
        return self._entries.get(key)

    def keys(self, prefix: str = "") -> List[str]:
        return sorted(key for key in self._entries if key.startswith(prefix))

    def items(self, prefix: str = "") -> List[Tuple[str, Any]]:
        return [(key, self._entries[key].value) for key in self.keys(prefix)]

    def __contains__(self, key: object) -> bool:
        return key in self._entries

    def __len__(self) -> int:
        return len(self._entries)

    def put(self, key: str, value: Any) -> None:
        """Local write. Raises TypeError/ValueError for a non-str key or a value JSON cannot encode."""
        if not isinstance(key, str):
            raise TypeError(f"key must be str, not {type(key).__name__}")
        canonical = _canonical(value)
        current = self._entries.get(key)
        timestamp = (current.timestamp if current is not None else 0) + 1
        # Store a decoded copy: the caller may mutate its object later, and every replica holds the same JSON.
        entry = Entry(json.loads(canonical), timestamp, self.owner)
        self._store(key, entry, _wire(key, canonical, timestamp, self.owner))

    def merge(self, entries: Any, sender: Optional[int] = None) -> List[str]:
        """Apply a peer's ``outgoing()``; return the keys whose entry changed. Never raises on bad input."""
        if not isinstance(entries, (list, tuple)):
            self._reject(sender)
            return []
        changed: Dict[str, None] = {}              # ordered set: a key may come twice in one message
        for raw in entries:
            key = self._merge_one(raw, sender)
            if key is not None:
                changed[key] = None
        return list(changed)

    def _merge_one(self, raw: Any, sender: Optional[int]) -> Optional[str]:
        parsed = _parse(raw)
        if parsed is None:
            self._reject(sender)
            return None
        key, value, timestamp, writer = parsed
        local = self._entries.get(key)
        if local is not None and timestamp < local.timestamp:
            return None                            # stale: we already hold a newer write
        tie = local is not None and timestamp == local.timestamp
        if tie and writer == local.writer and _same(value, local.value):
            return None                            # duplicate, the common case: decided without encoding
        try:
            canonical = _canonical(value)
        except (TypeError, ValueError):
            self._reject(sender)
            return None
        wire = _wire(key, canonical, timestamp, writer)
        if tie and wire == self._wire[key]:
            return None                            # duplicate after all (e.g. a tuple for a list)
        remote = Entry(json.loads(canonical), timestamp, writer)
        if tie and self._resolve(key, local, remote) is local:
            return None
        self._store(key, remote, wire)             # dirty again, so the entry travels on: multi-hop gossip
        return key

    def _resolve(self, key: str, local: Entry, remote: Entry) -> Entry:
        rule = next((rule for prefix, rule in self._rules if key.startswith(prefix)), default_rule)
        try:
            winner = rule(key, local, remote)
        except Exception:  # a peer's odd value must not crash the robot; default_rule is total
            self.rule_errors += 1
            return default_rule(key, local, remote)
        return winner if winner is local or winner is remote else default_rule(key, local, remote)

    def _store(self, key: str, entry: Entry, wire: str) -> None:
        if key not in self._entries:
            self._order.append(key)
        self._entries[key] = entry
        self._wire[key] = wire
        if len(wire) + 2 > self.max_bytes:
            self.oversized += 1                    # alone it would break the radio's limit: keep it local
            self._dirty.pop(key, None)
            return
        self._dirty[key] = self.resend_rounds
        self._dirty.move_to_end(key)               # most recently changed goes out first

    def _reject(self, sender: Optional[int]) -> None:
        self.rejected += 1
        self.last_rejected_sender = sender

    def outgoing(self) -> List[list]:
        """This step's broadcast: dirty keys newest first, then round-robin over the others (anti-entropy)."""
        chosen: List[str] = []
        size = self._take_dirty(chosen)
        if size is not None:
            self._take_round_robin(chosen, size)
        return [[key, self._entries[key].value, self._entries[key].timestamp, self._entries[key].writer]
                for key in chosen]

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
