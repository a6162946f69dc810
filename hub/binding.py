"""Binding the hub's sockets: every address a name stands for, and a failed bind as the config field to fix."""
from __future__ import annotations

import errno
import socket
from typing import List

import zmq

from onboard.agent.link import endpoint_candidates, tcp_host, unbracket, use_ipv6
from onboard.config import ConfigError, as_written

# A loopback this PC does not have (a container without IPv6): ZeroMQ says "No such device" or "Cannot assign".
NO_SUCH_ADDRESS = (errno.EADDRNOTAVAIL, errno.ENODEV)


def bind_every(sock: zmq.Socket, endpoint: str) -> List[str]:
    """Bind every address ``endpoint`` stands for (``localhost``: 127.0.0.1 and ::1, so that agents and ``ctl``
    reach the hub as localhost, 127.0.0.1 or ::1 alike), all on the port the first one got; the bound
    endpoints. A loopback this PC lacks is left out, as long as one is bound; ZMQError otherwise."""
    bound: List[str] = []
    addresses = endpoint_candidates(endpoint)
    for k, address in enumerate(addresses):
        if bound:
            address = f"{address.rpartition(':')[0]}:{bound[0].rpartition(':')[2]}"    # port 0: the one picked
        use_ipv6(sock, address)
        try:
            sock.bind(address)
        except zmq.ZMQError as err:
            if err.errno in NO_SUCH_ADDRESS and (bound or k + 1 < len(addresses)):
                continue
            raise
        bound.append(sock.getsockopt_string(zmq.LAST_ENDPOINT))
    return bound


def bind_error(err: zmq.ZMQError, bind: str, port: int, port_field: str) -> ConfigError:
    """A failed bind as the config field to fix: the port when it is taken, else the address."""
    if err.errno == zmq.EADDRINUSE:
        return ConfigError(f"network.{port_field}", f"port {port} on {bind} is already in use")
    reason = (err.strerror or str(err)).split(" (addr=")[0]     # pyzmq appends the endpoint; we name it ourselves
    return ConfigError("network.bind", f"cannot listen on {as_written(bind)}: {reason} (give an address of this PC, "
                       "e.g. 127.0.0.1 or ::1, or * for all IPv4 interfaces, :: for all IPv6 and IPv4 ones)")


def check_ports_free(bind: str, ports: List[tuple]) -> None:
    """Before a motion-capture system is asked to connect (seconds, with a slow one): ConfigError naming the
    port field when another process (a hub left running) already listens on it. ``ports``: (field, port)
    pairs; port 0 (any free port) is not looked at. What cannot be told here is left to the real bind."""
    for field, port in ports:
        if port and any(_taken(address) for address in endpoint_candidates(f"tcp://{tcp_host(bind)}:{port}")):
            raise ConfigError(f"network.{field}", f"port {port} on {bind} is already in use")


def _taken(address: str) -> bool:
    """Whether binding ``tcp://host:port`` fails with "address in use", tried as libzmq binds (SO_REUSEADDR)."""
    host, _, port = address[len("tcp://"):].rpartition(":")
    host = unbracket(host)
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    host = {"*": "0.0.0.0"}.get(host, host)
    try:
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            probe.bind((host, int(port)))
    except OSError as err:
        return err.errno == errno.EADDRINUSE
    except ValueError:
        return False
    return False


def is_loopback(host: str) -> bool:
    """localhost, 127.x.x.x, or ::1 however written: bare, in brackets as in a URL ([::1], as the hub writes its
    own addresses), or in full; the hub binds each of them."""
    from onboard.agent.link import ipv6_literal

    return host == "localhost" or host.startswith("127.") or ipv6_literal(host) == "::1"
