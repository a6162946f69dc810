"""Binding the hub's sockets: every address a name stands for, and a failed bind as the config field to fix."""
from __future__ import annotations

import errno
from typing import List

import zmq

from onboard.agent.link import endpoint_candidates, use_ipv6
from onboard.config import ConfigError

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
    return ConfigError("network.bind", f"cannot listen on {bind!r}: {reason} (give an address of this PC, "
                       "e.g. 127.0.0.1 or ::1, or * for all IPv4 interfaces, :: for all IPv6 and IPv4 ones)")
