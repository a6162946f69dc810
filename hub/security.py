"""CURVE keys and authentication: the hub talks only to robots and operators whose public key it holds.

Key folder (``khepri keys init DIR``)::

    DIR/hub.key, DIR/hub.key_secret                     the hub's pair (the secret stays on the lab PC)
    DIR/robots/robot-<id>.key, robot-<id>.key_secret    one pair per robot; copy both + hub.key to the robot
    DIR/operators/<name>.key, <name>.key_secret         one pair per operator (khepri ctl)

The hub accepts a robot key only on the robot socket and an operator key only on the control socket. The
authenticated key gives the peer's identity (ZAP User-Id ``robot:<id>`` or ``operator:<name>``), so a robot
cannot claim another robot's id.
"""
from __future__ import annotations

import itertools
import math
import os
import re
import socket as sockets
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

from onboard.agent.link import exposed_secret, key_folder_problem
from onboard.config import ConfigError

ROBOT_DOMAIN = "robots"
OPERATOR_DOMAIN = "operators"
ROBOT_KEY = re.compile(r"^robot-(\d+)\.key$")
MAX_OPERATOR_NAME = 64
HUB_KEYS_FIELD = "security.keys"   # what the hub's key errors name: the lab config's key
REFUSAL_LOG_S = 60.0    # a refused key is logged at most this often per peer address and socket
HANDSHAKE_LOG_S = 10.0  # a failed CURVE handshake is logged at most this often per peer address and socket
ZAP_REBIND_WAIT_S = 2.0  # how long a starting hub waits for the previous one's ZAP endpoint to be released


@dataclass
class KeyRing:
    """What the hub needs: its own pair and the public keys it accepts (z85 bytes -> identity)."""

    folder: Path
    public: bytes
    secret: bytes
    robots: Dict[bytes, int] = field(default_factory=dict)
    operators: Dict[bytes, str] = field(default_factory=dict)


def init_keys(folder: Path, robot_ids: List[int], operators: List[str], force: bool = False) -> List[Path]:
    """Create the hub, robot and operator key pairs. Refuses to overwrite existing keys unless ``force``; with
    it, the folder holds exactly the new set afterwards (``stale_keys`` names what ``force`` removes)."""
    targets = [folder / "hub.key"] + [folder / "robots" / f"robot-{i}.key" for i in robot_ids] \
        + [folder / "operators" / f"{name}.key" for name in operators]
    _refuse_files_in_the_way(folder, targets)
    existing = [p for p in targets if p.exists()]
    if existing and not force:
        raise ConfigError("FOLDER", f"{existing[0]} already exists (use --force to replace keys)")
    check_operator_names(operators)
    for path in stale_keys(folder, targets) if force else []:   # rotating keys must not leave an old robot
        path.unlink()                                             # or operator key that the hub still accepts
    return _create_pairs(targets)


def add_keys(folder: Path, robot_ids: List[int], operators: List[str]) -> List[Path]:
    """Add robot and operator key pairs to an existing key folder, leaving every key in it as it is (the hub's
    and the other robots' and operators'), so nothing already given out has to be copied again. Refuses a
    robot or operator that already has a key: replacing one is deleting it first, or ``init --force``. A
    revoked key's leftover secret (``revoked_secrets``) is replaced."""
    if not (folder / "hub.key").is_file():
        raise ConfigError("FOLDER", f"no hub key {folder / 'hub.key'}: make the lab's keys with "
                                    f"`khepri keys init {folder}` first")
    check_operator_names(operators)
    targets = _peer_keys(folder, robot_ids, operators)
    _refuse_files_in_the_way(folder, targets)
    for path in targets:
        _refuse_a_key_in_use(path)
    return _create_pairs(targets)


def revoked_secrets(folder: Path, robot_ids: List[int], operators: List[str]) -> List[Path]:
    """The secret files these robots and operators still have without their public key: what revoking a key
    (deleting its ``.key``) leaves behind. ``add_keys`` replaces them; the hub no longer accepts them anyway."""
    secrets = [path.with_suffix(".key_secret") for path in _peer_keys(folder, robot_ids, operators)]
    return [path for path in secrets if path.exists() and not path.with_suffix(".key").exists()]


def _peer_keys(folder: Path, robot_ids: List[int], operators: List[str]) -> List[Path]:
    return [folder / "robots" / f"robot-{i}.key" for i in robot_ids] \
        + [folder / "operators" / f"{name}.key" for name in operators]


def _refuse_a_key_in_use(path: Path) -> None:
    """A robot or operator whose public key is in the folder keeps it (the hub accepts it, and the robot may hold
    its secret): replacing it is deleting it first. The hint names only the files that are there."""
    if not path.exists():
        return
    robot = path.parent.name == "robots"
    who = f"robot {path.stem[len('robot-'):]}" if robot else f"operator {path.stem}"
    secret = path.with_suffix(".key_secret")
    files = f"{path.name} and {secret.name}" if secret.exists() else path.name
    raise ConfigError("--robots" if robot else "--operator",
                      f"{who} already has a key ({path}); to replace it, delete {files} first")


def _refuse_files_in_the_way(folder: Path, targets: List[Path]) -> None:
    """A file where the key folder or its robots/ or operators/ folder goes, checked before anything is written:
    found half-way, the hub's pair was already made, and running init again was refused for it."""
    for place in dict.fromkeys([folder] + [path.parent for path in targets]):
        if place.exists() and not place.is_dir():
            raise ConfigError("FOLDER", f"{place} is a file, not a folder: move it away first")


def _create_pairs(targets: List[Path]) -> List[Path]:
    created = []
    for path in targets:
        path.parent.mkdir(parents=True, exist_ok=True)
        public, secret = zmq.auth.create_certificates(str(path.parent), path.stem)
        Path(secret).chmod(0o600)
        created += [Path(public), Path(secret)]
    return created


def check_operator_names(operators: List[str]) -> None:
    """An operator name becomes a file name: refuse one that would not be a plain one."""
    for name in operators:
        if not re.fullmatch(r"[A-Za-z0-9_.-]+", name):
            raise ConfigError("--operator", f"use letters, digits, '.', '_' or '-' only (got {name!r})")
        if name[0] in ".-":     # `.`/`..` made `...key`; `-x` cannot be given back to `ctl --operator`
            raise ConfigError("--operator", f"must start with a letter, a digit or '_' (got {name!r})")
        if len(name) > MAX_OPERATOR_NAME:     # its .key_secret must fit a file name (checked before writing)
            raise ConfigError("--operator", f"at most {MAX_OPERATOR_NAME} characters (got {len(name)})")


def stale_keys(folder: Path, keep: List[Path]) -> List[Path]:
    """Robot and operator key files in ``folder`` (public and secret) whose pair is not among ``keep``."""
    kept = {path.with_suffix("") for path in keep}
    found = list((folder / "robots").glob("robot-*.key*")) + list((folder / "operators").glob("*.key*"))
    return sorted(path for path in found
                  if path.suffix in (".key", ".key_secret") and path.with_suffix("") not in kept)


def load_keyring(folder: Path) -> KeyRing:
    problem = key_folder_problem(folder)
    if problem:
        raise ConfigError(HUB_KEYS_FIELD, problem)
    public, secret = _load_pair(folder / "hub.key_secret", "hub", HUB_KEYS_FIELD)
    if _load_public(folder / "hub.key", HUB_KEYS_FIELD) != public:
        # What robots and operators are given: with another key there, every client is refused, and each
        # was told its hub.key was not this hub's (it was this folder's hub.key).
        raise ConfigError(HUB_KEYS_FIELD, f"{folder / 'hub.key'} is not the public key of {folder / 'hub.key_secret'} "
                                          "(copied from another key folder?): robots and operators given it could "
                                          "not connect; copy the pair from one `khepri keys init`")
    ring = KeyRing(folder, public, secret)
    holders: Dict[bytes, Path] = {public: folder / "hub.key"}
    for path in sorted((folder / "robots").glob("robot-*.key")):
        match = ROBOT_KEY.match(path.name)
        if match:
            ring.robots[_unique_public(path, holders)] = int(match.group(1))
    for path in sorted((folder / "operators").glob("*.key")):
        ring.operators[_unique_public(path, holders)] = path.stem
    if not ring.robots:
        raise ConfigError(HUB_KEYS_FIELD, f"no robot keys in {folder / 'robots'} (add them with `khepri keys add "
                                          f"{folder} --robots N`)")
    return ring


def operator_client_keys(folder: Path, name: Optional[str] = None) -> Dict[str, bytes]:
    """``khepri ctl``'s side: an operator pair (the only one in the folder unless ``name`` is given)."""
    problem = key_folder_problem(folder)
    if problem:
        raise ConfigError("--keys", problem)
    found = sorted((folder / "operators").glob("*.key_secret"))
    candidates = [p for p in found if name is None or p.stem == name]
    stem = name.rsplit(".", 1)[0] if name is not None and name.endswith((".key_secret", ".key")) else None
    if not candidates and any(p.stem == stem for p in found):
        raise ConfigError("--operator", f"takes the operator's name, not its key file: --operator {stem}")
    if not candidates:
        # With keys in the folder, the name is what is wrong (`--operator bob` among alice's): say that option.
        option = "--operator" if name is not None and found else "--keys"
        raise ConfigError(option, f"no operator key{'' if name is None else ' ' + repr(name)} in "
                                  f"{folder / 'operators'}{' (it holds ' + key_files(found) + ')' if found else ''}")
    if len(candidates) > 1:
        raise ConfigError("--operator", f"several operator keys in {folder / 'operators'}: {key_files(found)}; "
                                        f"name one, e.g. --operator {found[0].stem}")
    public, secret = _load_pair(candidates[0], "operator", "--keys")
    exposed = exposed_secret(candidates[0])
    if exposed:
        print(f"khepri ctl: warning: {exposed}", file=sys.stderr, flush=True)
    return {"public": public, "secret": secret, "server": _load_public(folder / "hub.key", "--keys")}


def key_files(paths: List[Path]) -> str:
    """'alice.key_secret, bob.key_secret': the key files an error offers to choose from."""
    return ", ".join(path.name for path in paths)


def apply_client_keys(socket: zmq.Socket, keys: Dict[str, bytes]) -> None:
    socket.curve_publickey = keys["public"]
    socket.curve_secretkey = keys["secret"]
    socket.curve_serverkey = keys["server"]


def make_curve_server(socket: zmq.Socket, ring: KeyRing, domain: str) -> None:
    socket.zap_domain = domain.encode()
    socket.curve_publickey = ring.public
    socket.curve_secretkey = ring.secret
    socket.curve_server = True


class _Members:
    """ZAP callback: is this public key listed for the domain?"""

    def __init__(self, keys):
        self.keys = keys

    def callback(self, domain: str, key: bytes) -> bool:
        return key in self.keys


class HubAuthenticator(ThreadAuthenticator):
    """Accepts listed keys per domain and names the peer by the key's identity (``robot:3``). Logs a refused
    key with the peer's address (at most once a minute per address and socket), so that an operator can tell a
    key mix-up from a robot that is not there."""

    def __init__(self, context: zmq.Context, ring: KeyRing, log: Callable[[str], None] = print):
        super().__init__(context)
        self.ring, self.hub_log = ring, log
        self.members = {ROBOT_DOMAIN: ring.robots, OPERATOR_DOMAIN: ring.operators}
        self._refusals_said: Dict[Tuple[str, str], float] = {}
        for domain, keys in self.members.items():
            self.configure_curve_callback(domain, _Members(keys))

    def start(self) -> None:
        """Bind the context's one ZAP endpoint, waiting up to ZAP_REBIND_WAIT_S for a hub closed just before in
        this process to let go of it: ZeroMQ unbinds a closed socket's inproc endpoint in its own thread, so a
        hub started right after another (the tests, one after the other) found it still taken."""
        deadline = time.monotonic() + ZAP_REBIND_WAIT_S
        while True:
            try:
                super().start()
                return
            except zmq.ZMQError as err:
                if err.errno != zmq.EADDRINUSE or time.monotonic() > deadline:
                    raise
                if self.zap_socket is not None:
                    self.zap_socket.close(0)
                    self.zap_socket = None
                time.sleep(0.01)

    async def handle_zap_message(self, msg: List[bytes]) -> None:
        self._say_if_refused(msg)
        await super().handle_zap_message(msg)

    def _say_if_refused(self, msg: List[bytes]) -> None:
        """ZAP request frames: version, request id, domain, address, identity, mechanism, credentials."""
        if len(msg) != 7 or msg[5] != b"CURVE":
            return
        domain, address = msg[2].decode("utf-8", "replace"), msg[3].decode("utf-8", "replace")
        if zmq.utils.z85.encode(msg[6]) in self.members.get(domain, {}):
            return
        now = time.monotonic()
        if now - self._refusals_said.get((domain, address), -math.inf) < REFUSAL_LOG_S:
            return
        if len(self._refusals_said) > 10_000:     # a flood of addresses must not grow memory without bound
            self._refusals_said.clear()
        self._refusals_said[(domain, address)] = now
        who = "a robot" if domain == ROBOT_DOMAIN else "an operator"
        added = _key_file_holding(self.ring.folder / domain, zmq.utils.z85.encode(msg[6]))
        if added is not None:       # `keys add` while the hub ran: "not in keys/robots" read as wrong, it was there
            self.hub_log(f"hub: refused {who} key from {address}: {added} was added after this hub loaded its keys; "
                         "restart the hub to accept it")
            return
        self.hub_log(f"hub: refused {who} key from {address}: not in {self.ring.folder / domain} "
                     f"(a key made for another hub or lab, or for the other socket?)")

    def curve_user_id(self, client_public_key: bytes) -> str:
        z85 = zmq.utils.z85.encode(client_public_key)
        if z85 in self.ring.robots:
            return f"robot:{self.ring.robots[z85]}"
        return f"operator:{self.ring.operators.get(z85, '?')}"


_WATCHES = itertools.count()


class HandshakeWatch:
    """Logs peers dropped during the CURVE handshake, before any ZAP request or message: an agent started without
    ``--keys`` (an unencrypted peer), or with a hub key that is not this hub's (its hello cannot be decrypted).
    ZeroMQ drops them without a word to either side, so without this the hub's log stayed empty while a robot
    never connected. Nothing is sent to such a peer.

    A thread reads the socket's monitor: an accepted connection gives its file descriptor, whose peer address is
    read at once; a failed handshake is followed by that connection's disconnection, which names it. A peer
    can fail faster than the address is read (on loopback, without keys): it is then said without one. One line per
    peer address, socket and reason every HANDSHAKE_LOG_S at most (a peer retrying, or a flood, cannot fill the log),
    with how many were dropped meanwhile."""

    # MONITOR_STOPPED: disable_monitor's last event, on which the reader ends (close()).
    EVENTS = (zmq.EVENT_ACCEPTED | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL | zmq.EVENT_DISCONNECTED
              | zmq.EVENT_MONITOR_STOPPED)

    def __init__(self, context: zmq.Context, sock: zmq.Socket, domain: str, ring: KeyRing,
                 log: Callable[[str], None] = print):
        self.domain, self.ring, self.log = domain, ring, log
        self.sock = sock
        self.address = f"inproc://handshakes-{domain}-{next(_WATCHES)}"   # id(self) is reused: an address too
        sock.monitor(self.address, self.EVENTS)
        self._stop = threading.Event()
        self.monitor_stopped = False        # the reader read the monitor's last event (close() turned it off)
        self._listening = threading.Event()  # the reader's PAIR socket is connected to the monitor
        self._said: Dict[Tuple[str, int], Tuple[float, int]] = {}   # (address, error) -> (last said, drops since)
        self._thread = threading.Thread(target=self._run, args=(context,), name=f"handshakes-{domain}", daemon=True)
        self._thread.start()
        self._listening.wait(5.0)    # disable_monitor (close) blocks for ever if the reader is not yet connected

    def close(self) -> None:
        """In the thread that owns the socket, before closing it. The monitor is turned off first, while the
        reader still reads: libzmq's I/O thread sends each event to the reader's PAIR socket holding a lock, and
        with the reader gone a send waits for ever (a PAIR without its peer blocks). disable_monitor then waited
        for that lock holding Python's GIL, and the whole hub froze on its way out (seen at the end of a test,
        as an agent disconnected just after the reader had stopped). The reader is connected since __init__."""
        try:
            self.sock.disable_monitor()
        except zmq.ZMQError:
            pass
        self._thread.join(timeout=1.0)     # the reader ends on the monitor's last event, MONITOR_STOPPED...
        self._stop.set()                   # ... or here, should that never come
        self._thread.join(timeout=1.0)

    def _run(self, context: zmq.Context) -> None:
        from zmq.utils.monitor import recv_monitor_message

        pair = context.socket(zmq.PAIR)
        pair.linger = 0
        pair.connect(self.address)
        self._listening.set()
        peers: Dict[int, str] = {}          # file descriptor -> peer address, while connected
        failed: Optional[int] = None        # the ZMTP error of a handshake that failed, until its disconnection
        try:
            while not self._stop.is_set():
                if not pair.poll(100):
                    continue
                event = recv_monitor_message(pair)
                kind, value = event["event"], event["value"]
                if kind == zmq.EVENT_MONITOR_STOPPED:
                    self.monitor_stopped = True      # the last event: nothing more will be sent to us
                    break
                if kind == zmq.EVENT_ACCEPTED:
                    peers[value] = peer_address(value)
                    if len(peers) > 10_000:     # descriptors are reused: this only guards against a leak
                        peers.clear()
                elif kind == zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL:
                    failed = value
                elif kind == zmq.EVENT_DISCONNECTED:
                    address = peers.pop(value, "?")
                    if failed is not None:
                        self.dropped(address, failed, time.monotonic())
                    failed = None
        finally:
            pair.close(0)

    def dropped(self, address: str, error: int, now: float) -> None:
        last, unsaid = self._said.get((address, error), (-math.inf, 0))
        if now - last < HANDSHAKE_LOG_S:
            self._said[(address, error)] = (last, unsaid + 1)
            return
        if len(self._said) > 10_000:         # a flood of addresses must not grow memory without bound
            self._said.clear()
        self._said[(address, error)] = (now, 0)
        robots = self.domain == ROBOT_DOMAIN
        who, option = ("a robot's agent", "the agent's --keys") if robots else ("an operator", "khepri ctl --keys")
        if error == zmq.PROTOCOL_ERROR_ZMTP_MECHANISM_MISMATCH:
            keyless = "a robot's agent started" if robots else "an operator's `khepri ctl`"
            why = f"it is not encrypted: {keyless} without --keys?"
        elif error == zmq.PROTOCOL_ERROR_ZMTP_CRYPTOGRAPHIC:
            why = (f"its hello cannot be decrypted with this hub's key: {option} holds a hub.key that is not "
                   f"{self.ring.folder / 'hub.key'} (keys of another hub or an older `keys init`?)")
        else:
            why = f"ZMTP error {error:#x}"
        more = f"; {unsaid} more dropped from there since the last line" if unsaid else ""
        where = "robot" if robots else "control"
        source = f"from {address}" if address != "?" else "from a peer gone before its address was read"
        self.log(f"hub: dropped a connection {source} to the {where} socket in the CURVE handshake: {why}; "
                 f"nothing was answered (said at most every {HANDSHAKE_LOG_S:g} s per address{more})")


def _key_file_holding(folder: Path, z85_public: bytes) -> Optional[Path]:
    """The public key file in ``folder`` that holds this key now, if one does (read only on a refusal)."""
    for path in sorted(folder.glob("*.key")):
        try:
            if _load_public(path, "") == z85_public:
                return path
        except ConfigError:          # not a key file: not the one
            continue
    return None


def peer_address(fd: int) -> str:
    """The remote IP address of a connected TCP socket's file descriptor, "?" when it is gone already."""
    try:
        with sockets.socket(fileno=os.dup(fd)) as sock:
            return str(sock.getpeername()[0])
    except (OSError, IndexError):
        return "?"


def _load_pair(path: Path, who: str, where: str):
    """``where``: what the error names, the hub config's ``security.keys`` or ``khepri ctl --keys``."""
    if not path.is_file():
        raise ConfigError(where, f"no {who} key {path} (run `khepri keys init {path.parent}`, or --insecure "
                          "on a trusted loopback only)")
    try:
        public, secret = zmq.auth.load_certificate(str(path))
    except (OSError, ValueError) as err:
        raise ConfigError(where, f"{path}: not a key file ({err})") from None
    if secret is None:
        raise ConfigError(where, f"{path}: holds no secret key")
    try:
        derived = zmq.curve_public(secret)
    except (zmq.ZMQError, ValueError):
        raise ConfigError(where, f"{path}: its secret key is not a CURVE key") from None
    if derived != public:      # an edited file: the clients would be told the wrong public key
        raise ConfigError(where, f"{path}: its public key is not its secret key's pair (an edited file? make the "
                                 f"keys again with `khepri keys init --force`)")
    return public, secret


def _unique_public(path: Path, holders: Dict[bytes, Path]) -> bytes:
    """A public key of the hub's folder that no other file of it holds: a copied key file would make one
    peer two (robot-1.key copied to robot-9.key: the later file won, and robot 1 was refused as robot 9)."""
    public = _load_public(path, HUB_KEYS_FIELD)
    if public in holders:
        raise ConfigError(HUB_KEYS_FIELD, f"{holders[public]} and {path} hold the same key: each robot and "
                                          f"operator needs its own pair (delete the copy)")
    holders[public] = path
    return public


def _load_public(path: Path, where: str) -> bytes:
    if not path.is_file():
        raise ConfigError(where, f"no public key {path}")
    try:
        public, _ = zmq.auth.load_certificate(str(path))
    except (OSError, ValueError) as err:
        raise ConfigError(where, f"{path}: not a key file ({err})") from None
    return public
