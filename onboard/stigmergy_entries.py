"""The tuple space's entries (:mod:`onboard.stigmergy`): the record, the conflict rules that pick a winner
between two versions of a key, and their wire form (canonical JSON texts, :class:`Gossip`).

Runs on the robots: standard library only, Python 3.9.
"""
from __future__ import annotations

import itertools
import json
import marshal
from dataclasses import dataclass
from typing import Any, Callable, Dict, Optional, Tuple


@dataclass(frozen=True)
class Entry:
    """One replicated value. Treat ``value`` as read-only: it is the replica's own copy."""

    value: Any
    timestamp: int
    writer: int


_new_instance = object.__new__


def _entry(value: Any, timestamp: int, writer: int) -> Entry:
    # Entry(value, timestamp, writer) without the frozen dataclass's per-field __setattr__ (merges make many).
    entry = _new_instance(Entry)
    entry.__dict__.update(value=value, timestamp=timestamp, writer=writer)
    return entry


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


#: Lists or mappings inside one another in an entry's value beyond this are malformed (_too_deep).
MAX_VALUE_DEPTH = 64


def _parse(raw: Any) -> Optional[Tuple[str, Any, int, int]]:
    """``[key, value, timestamp, writer]`` checked field by field, or None if malformed."""
    if not isinstance(raw, (list, tuple)) or len(raw) != 4:
        return None
    key, value, timestamp, writer = raw
    # ``type(...) is int`` also refuses True/False, which Python counts as ints.
    if type(key) is not str or type(timestamp) is not int or type(writer) is not int or timestamp < 0:
        return None
    if _too_deep(value):
        return None
    return key, value, timestamp, writer


def _too_deep(value: Any, limit: int = MAX_VALUE_DEPTH) -> bool:
    """Whether ``value`` nests lists or mappings more than ``limit`` deep, found level by level, without
    recursion. Comparing, encoding or copying such a value recurses, and fails with RecursionError some
    hundreds of levels down, wherever the stack then is: a peer's entry 950 deep raised it out of merge."""
    level = [value]
    for _ in range(limit):
        level = [child for item in level if type(item) in (list, dict)
                 for child in (item.values() if type(item) is dict else item)]
        if not level:
            return False
    return any(type(item) in (list, dict) for item in level)


def _same(a: Any, b: Any) -> bool:
    """Equal as JSON values, strictly: unlike ``==``, 1, 1.0 and True differ (their JSON texts do)."""
    if type(a) is not type(b):
        return False
    if type(a) is dict:
        return a.keys() == b.keys() and all(_same(item, b[key]) for key, item in a.items())
    if type(a) is list:
        return len(a) == len(b) and all(map(_same, a, b))
    return a == b


def _fingerprint(value: Any) -> bytes:
    """Type-exact bytes of a value: equal bytes mean equal JSON values (1, 1.0 and True differ, as in
    ``_same``). Unequal bytes prove nothing (dict order, -0.0), so callers fall back to the full check.
    marshal version 2 has no back-references, whose presence would depend on reference counts."""
    return marshal.dumps(value, 2)


def _copy(decoded: Any) -> Any:
    """Deep copy of a freshly decoded JSON value, types kept (equal to decoding its text again, faster)."""
    return marshal.loads(marshal.dumps(decoded, 2))


# Compact and sorted: one text per JSON value, so equal values are equal strings on every replica.
# Built once: json.dumps with non-default options would build a new encoder on every call. NaN and infinities
# are refused (ValueError): they are not JSON, and a robot's radio refuses them, so a put() of one failed only
# at the robot's next broadcast, and never in the simulator, whose radio passes the replica's own texts on.
_canonical = json.JSONEncoder(separators=(",", ":"), sort_keys=True, allow_nan=False).encode


def _wire(key: str, canonical: str, timestamp: int, writer: int) -> str:
    # Same text as json.dumps([key, value, timestamp, writer], compact), built without re-encoding the value.
    return f"[{json.dumps(key)},{canonical},{timestamp},{writer}]"


class Gossip(list):
    """What ``outgoing()`` returns: a plain list of ``[key, value, timestamp, writer]`` entries (JSON encodes
    it as a list) that also carries ``wires``, each entry's compact JSON text, which the sender already has.

    A backend may use it to size and copy the message without encoding it again (``json_text``,
    ``decoded_copy``). A replica that merges a Gossip skips, with one set operation, every entry whose exact
    version it has seen before. Over a real wire it arrives as a plain list, merged entry by entry with the
    same result. Treat it as read-only: ``wires`` must keep describing the entries.
    """

    __slots__ = ("wires", "versions", "_positions")

    def __init__(self, entries: Any = (), wires: Any = ()) -> None:
        super().__init__(entries)
        self.wires: Tuple[str, ...] = tuple(wires)
        self.versions = frozenset(self.wires)
        self._positions: Optional[Dict[str, int]] = None

    def position(self, wire: str) -> int:
        """Index of the first entry with this text (built once, shared by every replica merging this copy)."""
        if self._positions is None:
            self._positions = {}
            for index, text in enumerate(self.wires):
                self._positions.setdefault(text, index)
        return self._positions[wire]

    def json_text(self) -> str:
        """The compact JSON of this list, from the entries' texts (the radio's size check counts these bytes)."""
        return "[" + ",".join(self.wires) + "]"

    def decoded_copy(self, text: Optional[str] = None) -> Gossip:
        """An independent copy, decoded from the JSON text exactly as a receiver of the wire would get it."""
        return Gossip(json.loads(self.json_text() if text is None else text), self.wires)


_EMPTY_VERSIONS: frozenset = frozenset()
_ZEROS = itertools.repeat(0)                       # endless defaults for map(dict.get, keys, _ZEROS)


def _empty_gossip() -> Gossip:
    # Gossip() without the constructor's tuple and frozenset calls: outgoing() returns one on most calls.
    gossip = Gossip.__new__(Gossip)
    gossip.wires, gossip.versions, gossip._positions = (), _EMPTY_VERSIONS, None
    return gossip
