"""Virtual stigmergy: a tuple space replicated on every robot, after Buzz (Pinciroli et al. 2016).

Robots share state (bids, task claims, positions) over a lossy, range-limited, delayed radio. Every write
carries a per-key Lamport timestamp and the writer's id; each step a robot broadcasts ``outgoing()`` and
``merge()``s what it hears. The merge picks the same winner whatever the order, loss or duplication of
messages, and accepted entries are gossiped on, so a connected swarm converges once writes stop.

Wire format: a list of ``[key, value, timestamp, writer]`` lists, ready for JSON. With values of a few dozen
bytes a 24-entry message is around 1-3 KB; the radio refuses more than 8192 bytes, so ``outgoing()`` also stops
before the compact JSON (``payload_bytes``) exceeds ``max_bytes``. An entry too big alone is never sent.

Speed (a swarm of N robots merges N - 1 messages per robot per step): every replica remembers the JSON text
of each entry version it holds or has outgrown, and ``outgoing()`` returns a :class:`Gossip`, a list that
carries its entries' texts. A simulator that hands receivers a Gossip lets them dismiss a message of known
versions with one set operation; over a real wire it arrives as a plain list and the same merge runs entry
by entry. Both give identical replicas (tests/test_performance_equivalence.py).

Runs on the robots: standard library only, Python 3.9; no randomness, no clock, so simulations reproduce.
"""
from __future__ import annotations

import bisect
import json
from collections import OrderedDict
from typing import Any, Callable, Dict, Iterable, List, Optional, Tuple

# The entries, their conflict rules and wire form live in stigmergy_entries; the public ones are imported
# from here too (behaviours write `from onboard.stigmergy import TupleSpace, lowest_field`).
from .stigmergy_entries import (
    _ZEROS,
    MAX_VALUE_DEPTH,
    ConflictRule,
    Entry,
    Gossip,
    _canonical,
    _copy,
    _entry,
    _fingerprint,
    _parse,
    _same,
    _too_deep,
    _wire,
    default_rule,
    lowest_field,
    lowest_writer,
    payload_bytes,
)

# What outgoing() sends, and when an accepted entry is relayed: the sending half, mixed into TupleSpace.
from .stigmergy_outgoing import Outgoing

#: ``check(key, value)``: what is wrong with a peer's entry, or None (``TupleSpace(check=...)``).
ValueCheck = Callable[[str, Any], Optional[str]]

__all__ = ["ConflictRule", "Entry", "Gossip", "TupleSpace", "default_rule", "lowest_field", "lowest_writer",
           "payload_bytes"]


class TupleSpace(Outgoing):
    """One robot's replica of the shared tuple space. Writing, reading and merging are here; what it broadcasts,
    and when it relays, in :class:`~onboard.stigmergy_outgoing.Outgoing`."""

    def __init__(self, owner: int, max_entries_per_message: int = 24, resend_rounds: int = 3,
                 conflict_rules: Optional[Dict[str, ConflictRule]] = None, max_bytes: int = 6000,
                 relay_rounds: Optional[int] = None, relay_delay_steps: int = 0, relay_quorum: int = 0,
                 anti_entropy_period: int = 1, check: Optional[ValueCheck] = None) -> None:
        """``resend_rounds``: how many messages carry an entry this robot wrote. The rest tunes traffic in
        dense swarms; the defaults keep the plain protocol (every accepted entry relayed ``resend_rounds``
        times at once, anti-entropy in every message):

        - ``relay_rounds``: how many messages carry an entry accepted from a peer (default
          ``resend_rounds``).
        - ``relay_delay_steps`` and ``relay_quorum`` (counter-based flooding): an accepted entry waits 0 to
          ``relay_delay_steps`` calls of ``outgoing()`` (spread over robots and entries, deterministically),
          and is not relayed at all if meanwhile ``relay_quorum`` copies of the same version arrived from
          robots other than its writer (0: never suppressed). Among 99 robots in range of each other a new
          version is then relayed by a handful of them instead of by all 99; where few robots hear it,
          nobody else relays it and they do.
        - ``anti_entropy_period``: the round-robin share (repairs losses, informs newcomers) rides along in
          one ``outgoing()`` of this many (staggered by owner); the others carry only changed entries, and
          are empty when nothing changed.

        ``check(key, value)`` says what is wrong with a peer's entry (a text), or None: an entry it finds wrong
        is refused, neither stored nor relayed, and counted (``refused``, ``last_refusal``). Without it any
        JSON value is taken; a behaviour gives one so that its readers may trust the shapes they read.
        """
        if max_entries_per_message < 1 or resend_rounds < 1 or max_bytes < 3:
            raise ValueError("max_entries_per_message and resend_rounds must be >= 1, max_bytes >= 3")
        relay_rounds = resend_rounds if relay_rounds is None else relay_rounds
        if relay_rounds < 1 or relay_delay_steps < 0 or relay_quorum < 0 or anti_entropy_period < 1:
            raise ValueError("relay_rounds and anti_entropy_period must be >= 1, relay delay and quorum >= 0")
        self.owner = owner
        self.max_entries_per_message = max_entries_per_message
        self.resend_rounds = resend_rounds
        self.relay_rounds = relay_rounds
        self.relay_delay_steps = relay_delay_steps
        self.relay_quorum = relay_quorum
        self.anti_entropy_period = anti_entropy_period
        self.max_bytes = max_bytes
        self._calls = 0                            # outgoing() calls so far: this replica's clock for relays
        # Accepted entries waiting to be relayed: key -> [due call, copies heard, wire, writer]; and the
        # wires of those versions, to spot copies in incoming Gossip with one set test.
        self._pending: Dict[str, list] = {}
        self._pending_wires: Dict[str, str] = {}
        self._next_due = 0                         # no waiting entry falls due before this outgoing() call
        # Longest prefix first, so the first match is the most specific rule.
        self._rules = sorted((conflict_rules or {}).items(), key=lambda item: -len(item[0]))
        self._rule_of: Dict[str, ConflictRule] = {}   # key -> its rule, found on the key's first conflict
        self._entries: Dict[str, Entry] = {}
        self._wire: Dict[str, str] = {}            # cached compact JSON of each entry: sizes and duplicates
        self._fingerprints: Dict[str, bytes] = {}  # cached _fingerprint of each value, made on first need
        # Wire texts of entry versions this replica holds or has outgrown (merging them again changes nothing),
        # so that a Gossip message is mostly dismissed with one set operation. Reset to the held versions when
        # it grows past _seen_limit(): a forgotten old version just takes the full path once more.
        self._seen: set = set()
        self._keys_by_prefix: Dict[str, List[str]] = {}
        self._revisions: Dict[str, int] = {"": 0}   # family -> changes so far ("" counts every change)
        self._journals: Dict[str, Dict[str, None]] = {}   # family -> keys changed since changed_keys(family)
        self._dirty: OrderedDict[str, int] = OrderedDict()   # key -> sends left; last = most recently changed
        self._order: List[str] = []                # round-robin order; keys are never removed, only appended
        self._cursor = 0
        self._check = check
        self.rejected = 0
        self.last_rejected_sender: Optional[int] = None
        self.refused = 0                           # well-formed entries that ``check`` refused...
        self.last_refusal: Optional[str] = None    # ...and the last one: "robot 7's bid/S/0: bid is not ..."
        self.oversized = 0
        self.rule_errors = 0

    def get(self, key: str, default: Any = None) -> Any:
        found = self._entries.get(key)
        return default if found is None else found.value

    def entry(self, key: str) -> Optional[Entry]:
        return self._entries.get(key)

    def keys(self, prefix: str = "") -> List[str]:
        found = self._keys_by_prefix.get(prefix)
        if found is None:
            # Behaviours ask for the same few prefixes many times per step; keys are never removed, so a
            # prefix's sorted list only changes when a new key arrives (_store inserts it then).
            found = self._keys_by_prefix[prefix] = sorted(key for key in self._entries if key.startswith(prefix))
        return list(found)

    def items(self, prefix: str = "") -> List[Tuple[str, Any]]:
        entries = self._entries
        return [(key, entries[key].value) for key in self.keys(prefix)]

    def revision(self, family: str = "") -> int:
        """A count that grows whenever an entry of ``family`` is stored or replaced (the family of "task/L1"
        is "task"); without a family, whenever any entry changes. Callers cache what they derive from the
        space (parsed tasks, member lists) and rebuild it only when this number moves."""
        return self._revisions.get(family, 0)

    def revisions(self, families: Tuple[str, ...]) -> Tuple[int, ...]:
        """``revision`` of each family, as a tuple: one call for a view that depends on several families."""
        return tuple(map(self._revisions.get, families, _ZEROS))

    def changed_keys(self, family: str) -> List[str]:
        """Keys of ``family`` stored or replaced since the previous call for the same family, in the order
        they last changed; the first call returns every key of the family held so far. For a consumer that
        follows a busy family (such as position heartbeats) without rescanning it every step. Each call
        consumes the changes, so give each family one consumer."""
        journal = self._journals.get(family)
        if journal is None:
            self._journals[family] = {}
            return [key for key in self._entries if key.partition("/")[0] == family]
        self._journals[family] = {}
        return list(journal)

    def __contains__(self, key: object) -> bool:
        return key in self._entries

    def __len__(self) -> int:
        return len(self._entries)

    def put(self, key: str, value: Any) -> None:
        """Local write. Raises TypeError/ValueError for a non-str key, a value JSON cannot encode, or one nested
        deeper than peers take (MAX_VALUE_DEPTH)."""
        if not isinstance(key, str):
            raise TypeError(f"key must be str, not {type(key).__name__}")
        try:
            canonical = _canonical(value)
            decoded = json.loads(canonical)
            too_deep = _too_deep(decoded)
        except RecursionError:      # hundreds of levels deep: json's own limit
            too_deep = True
        except ValueError as err:   # NaN or an infinity (not JSON), a circular reference
            raise ValueError(f"{key}: the value is not JSON, and peers could not read it ({err})") from None
        if too_deep:                # every peer would refuse it (_parse): say so here, where it is written
            raise ValueError(f"{key}: the value nests lists or mappings more than {MAX_VALUE_DEPTH} deep, and "
                             "peers refuse such entries")
        current = self._entries.get(key)
        timestamp = (current.timestamp if current is not None else 0) + 1
        # Store a decoded copy: the caller may mutate its object later, and every replica holds the same JSON.
        entry = _entry(decoded, timestamp, self.owner)
        self._store(key, entry, _wire(key, canonical, timestamp, self.owner))

    def merge(self, entries: Any, sender: Optional[int] = None) -> List[str]:
        """Apply a peer's ``outgoing()``; return the keys whose entry changed. Never raises on bad input."""
        if type(entries) is Gossip and len(entries.wires) == len(entries):
            versions = entries.versions
            if self._pending_wires and not versions.isdisjoint(self._pending_wires):
                self._heard(versions, sender)
            if versions <= self._seen:
                return []                          # the usual case in a chatty swarm: nothing new at all
            return self._merge_gossip(entries, sender)
        if not isinstance(entries, (list, tuple)):
            self._reject(sender)
            return []
        changed: Dict[str, None] = {}              # ordered set: a key may come twice in one message
        for raw in entries:
            if not self._known(raw):
                key = self._merge_one(raw, sender)
                if key is not None:
                    changed[key] = None
            elif self._pending:
                self._heard_plain(raw, sender)
        return list(changed)

    def merge_messages(self, messages: Iterable[Any], field: str) -> None:
        """``merge(message.payload.get(field), message.sender)`` for every radio message (anything with
        ``payload`` and ``sender``, such as the HAL's Message) whose payload is a dict, in order: the same
        as that loop, with the usual case (a Gossip of versions seen before) handled inline. A robot among
        a hundred others gets a dozen or more such messages per step."""
        pending_wires = self._pending_wires        # never replaced (unlike _seen, which _store may reset)
        for message in messages:
            payload = message.payload
            if not isinstance(payload, dict):
                continue
            entries = payload.get(field)
            if type(entries) is Gossip and len(entries.wires) == len(entries):
                versions = entries.versions
                if pending_wires and not versions.isdisjoint(pending_wires):
                    self._heard(versions, message.sender)
                if not versions <= self._seen:
                    self._merge_gossip(entries, message.sender)
            else:
                self.merge(entries, message.sender)

    def _merge_gossip(self, entries: Gossip, sender: Optional[int]) -> List[str]:
        """Merge only the entries whose exact version this replica has not seen, found with set operations
        (``merge`` has dismissed the message already if it holds no unseen version)."""
        unseen = entries.versions - self._seen
        wires = entries.wires
        changed: Dict[str, None] = {}
        for index in sorted(entries.position(version) for version in unseen):   # in message order
            rejected = self.rejected
            key = self._merge_one(entries[index], sender, wires[index])
            if key is not None:
                changed[key] = None
            if self.rejected == rejected:          # held now, or outgrown by what is held: settled for good
                self._seen.add(wires[index])       # (not a local: _store may have replaced the set)
        return list(changed)

    def _known(self, raw: Any) -> bool:
        """Fast path for the common case, a well-formed entry that is stale or that we hold already. False
        means "not sure": ``_merge_one`` then decides (and validates) in full."""
        if type(raw) is not list or len(raw) != 4:
            return False
        key, value, timestamp, writer = raw
        local = self._entries.get(key) if type(key) is str else None
        if local is None or type(timestamp) is not int or type(writer) is not int or timestamp < 0:
            return False
        if timestamp != local.timestamp:
            return timestamp < local.timestamp
        if writer != local.writer or value != local.value:
            return False
        fingerprint = self._fingerprints.get(key)
        if fingerprint is None:
            fingerprint = self._fingerprints[key] = _fingerprint(local.value)
        return _fingerprint(value) == fingerprint

    def _merge_one(self, raw: Any, sender: Optional[int], wire: Optional[str] = None) -> Optional[str]:
        """Merge one entry. ``wire`` is its compact JSON when known (from a Gossip, whose values are fresh JSON
        decodes): then nothing is encoded, and the replica's own copy is decoded only if the entry wins."""
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
        canonical: Optional[str] = None
        if wire is None:
            try:
                canonical = _canonical(value)
            except ValueError:      # NaN or an infinity: the simulator's radio passes a peer's objects on
                self._refuse(sender, key, "the value holds NaN or an infinity, which JSON cannot carry")
                return None
            except TypeError as err:
                self._refuse(sender, key, f"the value is not JSON ({err})")
                return None
            wire = _wire(key, canonical, timestamp, writer)
        if tie and wire == self._wire[key]:
            return None                            # duplicate after all (e.g. a tuple for a list)
        # Rules judge exactly what a replica would hold, a fresh JSON decode (a Gossip's values already are).
        judged = value if canonical is None else json.loads(canonical)
        if self._check is not None:
            problem = self._check(key, judged)
            if problem is not None:
                self._refuse(sender, key, problem)
                return None
        if tie and self._resolve(key, local, _entry(judged, timestamp, writer)) is local:
            return None
        own = judged if canonical is not None else _copy(value)   # never the message's shared copy
        self._store(key, _entry(own, timestamp, writer), wire, relay=True)   # travels on: multi-hop gossip
        return key

    def _resolve(self, key: str, local: Entry, remote: Entry) -> Entry:
        rule = self._rule_of.get(key)
        if rule is None:                           # rules are fixed: look a key's rule up once
            rule = self._rule_of[key] = next((rule for prefix, rule in self._rules if key.startswith(prefix)),
                                             default_rule)
        try:
            winner = rule(key, local, remote)
        except Exception:  # a peer's odd value must not crash the robot; default_rule is total
            self.rule_errors += 1
            return default_rule(key, local, remote)
        return winner if winner is local or winner is remote else default_rule(key, local, remote)

    def _store(self, key: str, entry: Entry, wire: str, relay: bool = False) -> None:
        if key not in self._entries:
            self._order.append(key)
            if len(self._keys_by_prefix) > 32:
                self._keys_by_prefix.clear()       # many prefixes asked once: rebuild on demand instead
            for prefix, keys in self._keys_by_prefix.items():   # keep the cached sorted lists up to date
                if key.startswith(prefix):
                    bisect.insort(keys, key)
        self._entries[key] = entry
        self._wire[key] = wire
        self._fingerprints.pop(key, None)
        family = key.partition("/")[0]
        self._revisions[family] = self._revisions.get(family, 0) + 1
        journal = self._journals.get(family)
        if journal is not None:
            journal.pop(key, None)                 # re-inserted: the journal keeps the order of last change
            journal[key] = None
        self._revisions[""] += 1
        if len(self._seen) > 4 * len(self._entries) + 4096:
            self._seen = set(self._wire.values())
        self._seen.add(wire)
        if self._pending:
            self._drop_pending(key)                # an older version waiting to be relayed is outdated
        if len(wire) + 2 > self.max_bytes:
            self.oversized += 1                    # alone it would break the radio's limit: keep it local
            self._dirty.pop(key, None)
            return
        if relay and (self.relay_delay_steps or self.relay_quorum):
            self._dirty.pop(key, None)
            delay = (self.owner * 7919 + entry.timestamp * 31 + entry.writer) % (self.relay_delay_steps + 1)
            due = self._calls + delay
            self._pending[key] = [due, 0, wire, entry.writer]
            self._pending_wires[wire] = key
            if due < self._next_due or len(self._pending) == 1:
                self._next_due = due
            return
        self._dirty[key] = self.relay_rounds if relay else self.resend_rounds
        self._dirty.move_to_end(key)               # most recently changed goes out first

    def _reject(self, sender: Optional[int]) -> None:
        self.rejected += 1
        self.last_rejected_sender = sender

    def _refuse(self, sender: Optional[int], key: str, problem: str) -> None:
        self._reject(sender)
        self.refused += 1
        who = "a peer" if sender is None else f"robot {sender}"
        self.last_refusal = f"{who}'s {key}: {problem}"
