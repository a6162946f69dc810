"""CURVE authentication: the hub talks only to robots and operators whose public key it holds (the key
folder and its files: ``hub/keyfiles.py``).

The hub accepts a robot key only on the robot socket and an operator key only on the control socket. The
authenticated key gives the peer's identity (ZAP User-Id ``robot:<id>`` or ``operator:<name>``), so a robot
cannot claim another robot's id.
"""
from __future__ import annotations

import itertools
import math
import os
import socket as sockets
import threading
import time
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

from onboard.config import ConfigError

from .key_reload import KeyReload
from .keyfiles import ROBOT_KEY, KeyRing, load_public

ROBOT_DOMAIN = "robots"
OPERATOR_DOMAIN = "operators"
REFUSAL_LOG_S = 60.0    # a refused key is logged at most this often per peer address and socket
HANDSHAKE_LOG_S = 10.0  # a failed CURVE handshake is logged at most this often per peer address and socket
ZAP_REBIND_WAIT_S = 2.0  # how long a starting hub waits for the previous one's ZAP endpoint to be released


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
        self.members = {ROBOT_DOMAIN: ring.robots, OPERATOR_DOMAIN: ring.operators}   # KeyReload updates them
        self.reload = KeyReload(ring, log)
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
        self.reload.refresh()
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
        if added is not None:       # "not in keys/robots" would read as wrong: it is there
            if domain == ROBOT_DOMAIN and not ROBOT_KEY.match(added.name):
                why = "a robot's key file must be named robot-<id>.key (the name gives the robot's id)"
            elif self.reload.problem:
                why = "the key folder cannot be read as a whole (said above); once it can, the key is accepted"
            else:
                why = "it was added just now, and is accepted at the next try"
            self.hub_log(f"hub: refused {who} key from {address}: {added} holds it, but {why}")
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
            if load_public(path, "") == z85_public:
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
