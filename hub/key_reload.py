"""The keys a running hub accepts follow its key folder, as sshd's ``authorized_keys`` does: a robot or operator
key added with ``khepri keys add`` is accepted, and one whose ``.key`` was deleted is refused, from the next
connection on, without a restart.

The folder is re-read when a peer's CURVE handshake asks the hub for its verdict (at most every
``CHECK_EVERY_S``, so a flood of handshakes cannot keep the hub reading files), and only when the public key
files changed. A folder that cannot be read as a whole (a key file half written, two files with one key, a stray
``.key`` file) still loses the keys whose files were deleted, keeps the others, says why (again whenever its
files change) and is tried again at the next handshake. Connections already open keep going: a revoked robot's
agent runs on until it reconnects (``khepri ctl estop``, or switch the robot off, to stop it at once). The hub's
own pair is read at start only.
"""
from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

from onboard.config import ConfigError

from .keyfiles import KeyRing, load_keyring, peer_key_path

CHECK_EVERY_S = 0.5
PEER_FOLDERS = ("robots", "operators")
KeyFiles = Tuple[Tuple[str, str, bytes], ...]


def peer_key_files(folder: Path) -> KeyFiles:
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
        # None: read the folder at the first handshake, whatever it holds. The ring was loaded before the hub
        # connected to its motion capture (seconds, at times), and a key changed meanwhile would be missed.
        self.files: Optional[KeyFiles] = None
        self.checked_at = -math.inf
        self._unread: Optional[Tuple[str, KeyFiles]] = None    # why the folder cannot be read, and its files

    @property
    def problem(self) -> Optional[str]:
        """Why the folder cannot be read as a whole, while it cannot."""
        return self._unread[0] if self._unread else None

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
            self._unreadable(str(err), files)
            return
        self.files, self._unread = files, None
        self._take(fresh)

    def _unreadable(self, problem: str, files: KeyFiles) -> None:
        """Keep the keys the hub had, but those whose file is gone: a stray file must not hold a revocation up."""
        self.files = None                  # read it whole again once it can be, whatever it then holds
        gone = self._drop_deleted()
        if self._unread != (problem, files):         # said once per state of the folder
            self._unread = (problem, files)
            self.log(f"hub: the key folder changed, but cannot be read ({problem}): the hub goes on accepting the "
                     "keys it had" + (f", but those of {', '.join(gone)}, whose files are gone" if gone else "")
                     + "; it tries again at the next connection")

    def _drop_deleted(self) -> List[str]:
        gone = []
        for kind, accepted in (("robot", self.ring.robots), ("operator", self.ring.operators)):
            for key, who in list(accepted.items()):
                if not peer_key_path(self.ring.folder, kind, who).is_file():
                    del accepted[key]
                    gone.append(f"{kind} {who}")
        return gone

    def _take(self, fresh: KeyRing) -> None:
        ring = self.ring
        changes = (_changes(ring.robots, fresh.robots, "robot")
                   + _changes(ring.operators, fresh.operators, "operator"))
        ring.robots.clear()
        ring.robots.update(fresh.robots)
        ring.operators.clear()
        ring.operators.update(fresh.operators)
        added = [text for kind, text in changes if kind == "added"]
        replaced = [text for kind, text in changes if kind == "replaced"]
        gone = [text for kind, text in changes if kind == "gone"]
        if added:
            self.log(f"hub: accepting the keys of {', '.join(added)} (added to {ring.folder})")
        if replaced:
            self.log(f"hub: new keys for {', '.join(replaced)} in {ring.folder}: their old keys are refused")
        if gone:
            self.log(f"hub: no longer accepting the keys of {', '.join(gone)} (gone from {ring.folder}); a "
                     "connection open already goes on until it closes (`khepri ctl estop` stops every robot at once)")
        if fresh.public != ring.public:
            self.log(f"hub: {ring.folder / 'hub.key_secret'} changed: the hub keeps the key it started with until "
                     "it restarts")


def _changes(old: Dict[bytes, object], new: Dict[bytes, object], kind: str) -> List[Tuple[str, str]]:
    """("added" | "replaced" | "gone", "robot 3") per identity whose key changed. A key that moved to another
    identity (robot-1.key renamed robot-5.key) is said as such: robot 1's secret now speaks for robot 5."""
    old_by_id = {who: key for key, who in old.items()}
    new_by_id = {who: key for key, who in new.items()}
    found = []
    for who, key in new_by_id.items():
        if who not in old_by_id:
            moved = old.get(key)
            found.append(("added", f"{kind} {who}" + (f" (the key {kind} {moved} had)" if moved is not None else "")))
        elif old_by_id[who] != key:
            found.append(("replaced", f"{kind} {who}"))
    found += [("gone", f"{kind} {who}") for who in old_by_id if who not in new_by_id]
    return found
