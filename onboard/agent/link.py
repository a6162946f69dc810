"""The agent's connection to the hub: one DEALER socket, CURVE when keys are given, protocol checks both ways."""
from __future__ import annotations

import ipaddress
import os
import re
import socket
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple

import zmq

from onboard.config import ConfigError
from onboard.protocol import DOWNLINK_TYPES, ProtocolError, decode, encode

from .bad_messages import BadMessages
from .connection import watch_connection

RECEIVE_HWM = 16      # downlink frames waiting; the agent drains every poll, so more would be stale anyway
IPV6_LOOKUP_RETRY_S = 30.0   # a host name the DNS could not answer for is looked up again this much later
MAX_SOCKET_BYTES = 1 << 20   # larger frames cut the connection; up to here they are read and rejected as oversized


def hub_endpoint(hub: str, port: int, option: str = "--hub", port_given: bool = False) -> str:
    """The ZeroMQ address for ``--hub`` and ``--port`` (the agent's and ``khepri ctl``'s): a whole address such as
    ``tcp://10.0.0.1:5560`` as it is, else ``tcp://HOST:PORT``. A host with a port in it (``10.0.0.1:5560``) is
    refused: it would make ``tcp://10.0.0.1:5560:5560``, which ZeroMQ takes and never reaches, so the agent
    would wait for ever and ``ctl`` time out as if no hub were running. A whole address with ``--port`` too
    (``port_given``) is refused: the address's own port would win, silently. So is an empty host (``--hub
    "$HUB"`` with HUB unset), which made ``tcp://:5560``: ZeroMQ takes that too and never reaches anything."""
    if not hub.strip():
        raise ConfigError(option, "is empty: give the hub PC's host name or IP address (e.g. --hub 192.168.10.1; "
                                  "an unset shell variable?)")
    if "://" in hub:
        if hub.split("://", 1)[1].strip().startswith(":"):
            raise ConfigError(option, f"{hub!r} has no host: give the hub PC's host name or IP address before "
                                      "the port (e.g. tcp://192.168.10.1:5560)")
        if port_given:
            raise ConfigError("--port", f"{hub!r} is a whole address with its own port: leave --port out, or "
                                        f"give --hub the host alone")
        scheme, rest = hub.split("://", 1)
        if scheme == "tcp" and not re.search(r":\d+$", rest):     # ZeroMQ said only "Invalid argument"
            raise ConfigError(option, f"{hub!r} has no port: a whole address ends with one ({hub}:{port}), or "
                                      f"give the host alone (--hub {rest.strip('[]') or 'HOST'}) and the port with "
                                      "--port")
        return hub
    literal = ipv6_literal(hub)
    if literal is not None:
        return f"tcp://[{literal}]:{port}"
    if ":" in hub:
        host, _, given_port = hub.rpartition(":")
        if not host or (":" in host and ipv6_literal(host) is None) or not given_port.isdigit():
            host, given_port = "HOST", str(port)
        raise ConfigError(option, f"{hub!r} has a ':' in it: give the host alone and the port with --port "
                                  f"(--hub {host} --port {given_port}), or a whole address "
                                  f"(--hub tcp://{host}:{given_port})")
    return f"tcp://{hub}:{port}"


def unresolvable_host(endpoint: str) -> Optional[Tuple[str, socket.gaierror]]:
    """The host of a ``tcp://`` address and why it cannot be resolved, or None when it can (or is an address).
    ZeroMQ resolves a host name only while connecting, in its own thread, and says nothing when it cannot: a
    typo in ``--hub`` made the agent wait for ever and ``ctl`` time out as if no hub were running."""
    host = endpoint_host(endpoint)
    if not host:
        return None        # not tcp://, or no port: ZeroMQ itself refuses the address
    try:
        socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
    except socket.gaierror as err:
        return host, err
    except UnicodeError:            # an empty label (labpc..lan) fails before any lookup
        return host, socket.gaierror(socket.EAI_NONAME, "not a valid host name")
    return None


def endpoint_host(endpoint: str) -> Optional[str]:
    """The host of a ``tcp://[iface;]host:port`` address, without an IPv6 address's brackets ("" with no port);
    None for another transport."""
    if not endpoint.startswith("tcp://"):
        return None
    return unbracket(endpoint[len("tcp://"):].rsplit(";", 1)[-1].rpartition(":")[0])


def resolve_problem(host: str, err: socket.gaierror) -> str:
    return f"cannot resolve the host name {host!r}: {err.strerror} (a typo? or give the hub PC's IP address)"


def unbracket(host: str) -> str:
    """``host`` without the brackets round an IPv6 address in a URL (``[::1]`` gives ``::1``)."""
    return host[1:-1] if host.startswith("[") and host.endswith("]") else host


def ipv6_literal(host: str) -> Optional[str]:
    """``host`` as a bare IPv6 address (``::1`` or ``[::1]`` give ``::1``), or None if it is not one."""
    bare = unbracket(host)
    try:
        return str(ipaddress.IPv6Address(bare)) if ":" in bare else None
    except ValueError:
        return None


def tcp_host(host: str) -> str:
    """``host`` as it goes between ``tcp://`` and ``:port``: an IPv6 address in brackets."""
    literal = ipv6_literal(host)
    return host if literal is None else f"[{literal}]"


LOOPBACK_ADDRESSES = ("127.0.0.1", "[::1]")   # what `localhost` stands for, in the order tried


def endpoint_candidates(endpoint: str) -> List[str]:
    """The addresses that stand for ``endpoint``, in the order to try them: for ``localhost``, both loopbacks
    (IPv4 first, as ZeroMQ resolved it), else ``endpoint`` alone. ZeroMQ resolves a name to one family only
    (IPv4, unless its IPV6 option is on), so a hub listening on ::1 was never reached as localhost, and a hub
    told to listen on localhost was never reached as ::1, whichever way this PC's resolver answers."""
    if not endpoint.startswith("tcp://") or ";" in endpoint:     # tcp://eth0;host:port names an interface too
        return [endpoint]
    host, colon, port = endpoint[len("tcp://"):].rpartition(":")
    if not colon or host.lower().rstrip(".") != "localhost":
        return [endpoint]
    return [f"tcp://{address}:{port}" for address in LOOPBACK_ADDRESSES]


def family_hint(endpoint: str) -> str:
    """For an address of one IP family, a sentence on a hub listening on the other one, which looks from here
    like no hub at all, for ever; "" for a name (``localhost`` tries both loopbacks) or an interface address."""
    if not endpoint.startswith("tcp://") or ";" in endpoint:
        return ""
    host = unbracket(endpoint[len("tcp://"):].rpartition(":")[0])
    both = " (--hub localhost tries 127.0.0.1 and ::1)"
    if ipv6_literal(host) is not None:
        return ("A hub listening on IPv4 only (network.bind * or an IPv4 address such as 127.0.0.1) is never "
                f"reached at an IPv6 address{both if ipv6_literal(host) == '::1' else ''}.")
    if host == "127.0.0.1":
        return f"A hub listening on ::1 only is never reached at 127.0.0.1{both}."
    return ""


def use_ipv6(sock: zmq.Socket, endpoint: str, ipv6_only: Optional[bool] = None) -> None:
    """ZeroMQ reaches an IPv6 address only with its IPV6 option on; it is off by default, and an address such as
    tcp://[::1]:5560 then fails with "No such device". Turned on for such addresses only, and for host names
    with IPv6 addresses alone (ZeroMQ looked such a name up for IPv4, found nothing, and kept retrying in
    silence), so the IPv4 setups are as they were. ``ipv6_only``: the name's answer already looked up (the
    agent keeps it), else it is looked up here."""
    if "://[" in endpoint or (ipv6_only_name(endpoint) if ipv6_only is None else ipv6_only):
        sock.ipv6 = True


def ipv6_only_name(endpoint: str) -> Optional[bool]:
    """``tcp://NAME:port`` whose name resolves to IPv6 addresses and no IPv4 one (an AAAA record alone): True;
    False for any other address; None (falsy) when the name cannot be looked up just now (no DNS server
    reachable), so that a caller keeping the answer asks again later."""
    host = endpoint_host(endpoint)
    if not host or host == "*" or ":" in host or host.replace(".", "").isdigit():    # no name: * or an address
        return False
    try:
        families = {info[0] for info in socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)}
    except socket.gaierror as err:          # said elsewhere (unresolvable_host), or an interface name ZeroMQ knows
        return None if err.errno == socket.EAI_AGAIN else False
    except UnicodeError:
        return False
    return socket.AF_INET6 in families and socket.AF_INET not in families


def exposed_secret(path: Path) -> Optional[str]:
    """A warning when a secret key file can be read by other users than its owner (as ssh refuses such a
    key): whoever reads it can pose as that robot, operator or hub. None when it is private (or on a system
    without POSIX modes)."""
    try:
        mode = path.stat().st_mode & 0o777
    except OSError:
        return None
    if os.name != "posix" or not mode & 0o077:
        return None
    return (f"the secret key {path} can be read by other users (mode {mode:04o}): anyone who reads it can pose "
            f"as its owner; run `chmod 600 {path}`")


def robot_secret_file(folder: Path, robot_id: int) -> Path:
    return folder / "robots" / f"robot-{robot_id}.key_secret"


def key_folder_problem(folder: Path) -> Optional[str]:
    """What is wrong with a key folder that is not one at all, said before the files it should hold are: a
    missing folder read as "missing <folder>/robots/robot-0.key_secret" (or "no hub key"), and a file given
    for it was told to run `khepri keys init <the file>`."""
    if folder.is_file():
        return f"{folder} is a file: give the key folder `khepri keys init` made (it holds hub.key)"
    if not folder.exists():
        return f"no such folder: {folder} (a key folder is made by `khepri keys init FOLDER` on the lab PC)"
    return None


def load_robot_keys(folder: Path, robot_id: int) -> Dict[str, bytes]:
    """The robot's key pair and the hub's public key, from a folder laid out by ``khepri keys init``
    (``robots/robot-<id>.key_secret`` and ``hub.key``; copy just these two files onto the robot)."""
    import zmq.auth

    problem = key_folder_problem(folder)
    if problem:
        raise ConfigError("--keys", problem)
    secret_file = robot_secret_file(folder, robot_id)
    hub_file = folder / "hub.key"
    # On a robot, the folder holds what was copied from the lab PC's: `keys init` there would refuse (the lab
    # has keys already), and a robot left out of it gets its key with `keys add`.
    if not secret_file.is_file():
        raise ConfigError("--keys", f"missing {secret_file}: copy it from the lab PC's key folder; a robot that "
                                    f"has no key there yet gets one with `khepri keys add KEYS --robots {robot_id},` "
                                    f"(a running hub accepts it from then on)")
    if not hub_file.is_file():
        raise ConfigError("--keys", f"missing {hub_file}: copy hub.key from the lab PC's key folder (made by "
                                    "`khepri keys init`)")
    try:
        public, secret = zmq.auth.load_certificate(str(secret_file))
        server, _ = zmq.auth.load_certificate(str(hub_file))
    except (OSError, ValueError) as err:
        raise ConfigError("--keys", f"not a key file: {err}") from None
    if secret is None:
        raise ConfigError("--keys", f"{secret_file} holds no secret key")
    return {"public": public, "secret": secret, "server": server}


class HubLink:
    """Sends uplink messages and returns validated downlink messages. Never raises on bad input from the hub:
    bad messages are counted (``bad``) and reported through ``log`` at most once a second (``bad_messages``)."""

    def __init__(self, robot_id: int, endpoint: str, keys: Optional[Dict[str, bytes]] = None,
                 log: Callable[[str], None] = print, context: Optional[zmq.Context] = None):
        self.robot_id = robot_id
        self.endpoint = endpoint
        self.log = log
        self.context = context or zmq.Context.instance()
        self.bad_messages = BadMessages(robot_id, log)
        # Messages that could not leave once the hub had spoken on the connection (a full socket, the hub gone).
        # Before that, a refused send is no loss: there is nobody to lose it to yet, and hellos are repeated.
        # Counting those made every clean SIL run report a few dropped hellos (an agent says hello at once,
        # before its connection is up).
        self.unsent = 0
        self.keys = keys
        self.resets = 0
        # Names this agent process on every message, the same on each connection it opens: the hub tells the
        # agent's own reconnect (a new socket after a silence, or ZeroMQ's after a dropped TCP connection) from a
        # second agent with the same --id, which keeps its own token.
        self.instance = os.urandom(8).hex()
        # One address at a time (localhost: 127.0.0.1, then ::1): connected to both, a hub listening on both
        # (:: or localhost) would get this agent's messages over two connections, each taking the robot over
        # from the other. One that never answered gives way to the next at each reset (2 s of silence).
        self.addresses = endpoint_candidates(endpoint)
        self.address = self.addresses[0]
        self._ipv6_only: Dict[str, Optional[bool]] = {}    # per address: its name has IPv6 addresses alone
        self._ipv6_lookup_after = 0.0
        self._open()

    def _open(self) -> None:
        self.socket = self.context.socket(zmq.DEALER)
        self.socket.linger = 0
        self.socket.rcvhwm = RECEIVE_HWM
        self.socket.sndhwm = 1000
        self.socket.immediate = 1          # queue nothing while disconnected: stale uplink is worse than none
        self.socket.reconnect_ivl = 100
        self.socket.reconnect_ivl_max = 1000
        # Bounds memory against an absurd frame. ZeroMQ drops the connection for a frame past this and may not
        # reconnect, which is why the agent calls reset() after a long silence.
        self.socket.maxmsgsize = MAX_SOCKET_BYTES
        if self.keys is not None:
            self.socket.curve_publickey = self.keys["public"]
            self.socket.curve_secretkey = self.keys["secret"]
            self.socket.curve_serverkey = self.keys["server"]
        use_ipv6(self.socket, self.address, self._is_ipv6_only_name())
        self.watch = watch_connection(self.context, self.socket)    # before connect: its first events count
        self.socket.connect(self.address)
        self.heard = False                 # the hub has spoken on this socket (see unsent)
        self.only_bad: Optional[str] = None     # what it said, while all of it was unreadable (likely_cause)
        self.poller = zmq.Poller()
        self.poller.register(self.socket, zmq.POLLIN)

    def _is_ipv6_only_name(self) -> bool:
        """ipv6_only_name, looked up once per address: a reset after 2 s of silence must not wait on the DNS
        every time (the loop waits with it). A lookup the DNS could not answer is tried again after a while."""
        answer = self._ipv6_only.get(self.address)
        if answer is None and time.monotonic() >= self._ipv6_lookup_after:
            answer = self._ipv6_only[self.address] = ipv6_only_name(self.address)
            if answer is None:
                self._ipv6_lookup_after = time.monotonic() + IPV6_LOOKUP_RETRY_S
        return bool(answer)

    def reset(self) -> None:
        """A fresh socket and connection (the hub learns the new one from the next hello), to the next address
        if the hub never spoke on this one."""
        if not self.heard:
            self.address = self.addresses[(self.addresses.index(self.address) + 1) % len(self.addresses)]
        if self.watch is not None:
            self.watch.close()
        self.socket.close(0)
        self.resets += 1
        self._open()

    def likely_cause(self) -> Optional[str]:
        """Why the hub is silent on this connection, as far as ZeroMQ's events tell (see connection.py), with
        the address family's hint when the connection never got through (a hub on ::1 only, say)."""
        if self.only_bad is not None:     # the control port, say: "connected, but it sends nothing" was wrong
            return f"what answers at {self.address} is not a hub's robots port: its last message was {self.only_bad}"
        if self.watch is None:
            return None
        cause = self.watch.likely_cause(self.robot_id, self.address, self.keys is not None)
        if cause is None or self.watch.connected:
            return cause
        return f"{cause} {family_hint(self.endpoint)}".rstrip()

    def encode(self, message: Dict[str, Any]) -> bytes:
        """The message's wire bytes with this robot's id and this agent's token; ProtocolError if the hub would
        refuse it."""
        return encode(dict(message, id=self.robot_id, agent=self.instance))

    def send(self, message: Dict[str, Any]) -> bool:
        """Best effort: False when the hub is unreachable right now (nothing is queued for later)."""
        try:
            data = self.encode(message)
        except ProtocolError as err:
            self.log(f"agent {self.robot_id}: cannot send {message.get('type')}: {err}")
            return False
        return self.send_encoded(data)

    def send_encoded(self, data: bytes) -> bool:
        """``send`` for bytes from :meth:`encode`."""
        try:
            self.socket.send(data, zmq.NOBLOCK)
            return True
        except zmq.Again:
            if self.heard:
                self.unsent += 1
            return False

    def receive(self, timeout_s: float) -> List[Dict[str, Any]]:
        """Every message waiting (waiting up to ``timeout_s`` for the first)."""
        self.bad_messages.flush(time.monotonic())      # called each turn of the loop: a burst's count is said
        out: List[Dict[str, Any]] = []
        if not self.poller.poll(max(0.0, timeout_s) * 1000.0):
            return out
        for _ in range(1000):
            try:
                data = self.socket.recv(zmq.NOBLOCK)
            except zmq.Again:
                break
            first = not self.heard
            self.heard = True
            try:
                # Frames keep their neighbours as the decoder's numpy columns: the devices use them as they are.
                out.append(decode(data, "hub", accept=DOWNLINK_TYPES, neighbour_columns=True))
                self.only_bad = None
            except ProtocolError as err:
                self.bad_messages.drop(str(err), time.monotonic())
                if first or self.only_bad is not None:
                    self.only_bad = str(err)
        return out

    @property
    def bad(self) -> int:
        """The hub's messages dropped so far (the telemetry's ``frames_bad``)."""
        return self.bad_messages.count

    def close(self) -> None:
        # A short linger: the last messages (the wheels' stop for the sim driver, the final telemetry) get out.
        if self.watch is not None:
            self.watch.close()
        self.socket.close(linger=200)
