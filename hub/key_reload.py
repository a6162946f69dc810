"""The keys a running hub accepts follow its key folder, as sshd's ``authorized_keys`` does: a robot or operator
key added with ``khepri keys add`` is accepted, and one whose ``.key`` was deleted is refused, from the next
connection on, without a restart.

The folder is re-read when a peer's CURVE handshake asks the hub for its verdict (at most every
``CHECK_EVERY_S``, so a flood of handshakes cannot keep the hub reading files), and only when the public key
files changed. A folder that cannot be read as a whole (a key file half written, two files with one key) leaves
the keys as they were, says why once, and is tried again at the next handshake. Connections already open keep
going: a revoked robot's agent runs on until it reconnects (``khepri ctl estop``, or switch the robot off, to stop
it at once). The hub's own pair is read at start only.
"""
from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

from onboard.config import ConfigError

from .keyfiles import KeyRing, load_keyring

CHECK_EVERY_S = 0.5
PEER_FOLDERS = ("robots", "operators")


def peer_key_files(folder: Path) -> Tuple[Tuple[str, str, bytes], ...]:
    """What decides which peers the hub accepts: every public key file of the peers, with its contents."""
    found: List[Tuple[str, str, bytes]] = []
    for sub in PEER_FOLDERS:
        try:
            paths = sorted((folder / sub).glob("*.key"))
        except OSError:
            continue
        for path in paths:
            try:
                found.append((sub, path.name, path.read_bytes()))
            except OSError as err:       # unreadable now: changed, and load_keyring will say why
                found.append((sub, path.name, repr(err).encode()))
    return tuple(found)


class KeyReload:
    """Keeps ``ring.robots`` and ``ring.operators`` as the folder holds them. Called from the authenticator's
    thread only, the one thread that reads them while the hub runs."""

    def __init__(self, ring: KeyRing, log: Callable[[str], None], clock: Callable[[], float] = time.monotonic):
        self.ring, self.log, self.clock = ring, log, clock
        self.files = peer_key_files(ring.folder)
        self.checked_at = -math.inf
        self.problem: Optional[str] = None       # why the folder could not be re-read, once said

    def refresh(self) -> None:
        now = self.clock()
        if now - self.checked_at < CHECK_EVERY_S:
            return
        self.checked_at = now
        files = peer_key_files(self.ring.folder)
        if files == self.files:
            return
        try:
            fresh = load_keyring(self.ring.folder, need_robots=False)
        except ConfigError as err:
            if str(err) != self.problem:
                self.log(f"hub: the key folder changed, but cannot be read ({err}): the hub goes on accepting the "
                         "keys it had; it tries again at the next connection")
                self.problem = str(err)
            return
        self.files, self.problem = files, None
        self._take(fresh)

    def _take(self, fresh: KeyRing) -> None:
        ring = self.ring
        added = _names(fresh.robots, ring.robots, "robot") + _names(fresh.operators, ring.operators, "operator")
        gone = _names(ring.robots, fresh.robots, "robot") + _names(ring.operators, fresh.operators, "operator")
        ring.robots.clear()
        ring.robots.update(fresh.robots)
        ring.operators.clear()
        ring.operators.update(fresh.operators)
        if added:
            self.log(f"hub: accepting the keys of {', '.join(added)} (added to {ring.folder})")
        if gone:
            self.log(f"hub: no longer accepting the keys of {', '.join(gone)} (gone from {ring.folder}); a "
                     "connection open already goes on until it closes (`khepri ctl estop` stops every robot at once)")
        if fresh.public != ring.public:
            self.log(f"hub: {ring.folder / 'hub.key_secret'} changed: the hub keeps the key it started with until "
                     "it restarts")


def _names(keys: Dict[bytes, object], other: Dict[bytes, object], kind: str) -> List[str]:
    """Who holds a key in ``keys`` that ``other`` lacks: ``robot 3``, ``operator alice``."""
    return [f"{kind} {keys[key]}" for key in keys if key not in other]
