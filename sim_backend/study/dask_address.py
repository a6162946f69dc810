"""Dask scheduler addresses for ``khepri study --executor dask:ADDRESS``: their form checked before anything
starts, their host name and port tried before the study folder is made, and the connection itself bounded in
time, so that a typo is one line naming the address rather than Dask's 30 s of retries and a timeout."""
from __future__ import annotations

import socket
import threading
import time
from typing import Any, Dict, Optional, Tuple

from onboard.config import ConfigError


def check_dask_address(address: str) -> None:
    """Refuse a malformed scheduler address before anything starts (whether it answers is seen later)."""
    from distributed.comm.addressing import parse_address, parse_host_port
    from distributed.comm.registry import get_backend

    try:
        scheme, location = parse_address(address)
        get_backend(scheme)
        port = parse_host_port(location)[1] if scheme in ("tcp", "tls") else None
    except ValueError as err:
        raise ConfigError("--executor", f"not a Dask scheduler address: {address!r} ({err}); "
                                        "e.g. dask:tcp://10.0.0.5:8786") from None
    if port is not None and not 1 <= port <= 65535:
        # Dask takes any integer here, and an impossible port then fails as a 30 s timeout "cannot connect".
        raise ConfigError("--executor", f"the scheduler's port must be 1..65535 (got {port} in {address!r})")


# How long a scheduler's port may refuse connections before the address is refused: long enough for a scheduler
# started just before the study to listen, far shorter than Dask's 30 s of retries.
REFUSED_FOR_S = 10.0


def connect_to_scheduler(address: str, timeout_s: float = 30.0):
    """A Dask ``Client`` of the scheduler at ``address``, or a ConfigError naming it within about ``timeout_s``,
    whatever answers there: Dask's own timeout does not cover a server that accepts the connection and then
    never speaks Dask (a web server on that port keeps the handshake waiting forever), and a malformed
    address or a reply that is not Dask's raise all sorts of errors."""
    from distributed import Client

    outcome: Dict[str, Any] = {}

    def connect() -> None:
        try:
            reason = unreachable_reason(address, min(REFUSED_FOR_S, timeout_s))
            if reason:
                outcome["reason"] = reason
                return
            outcome["client"] = Client(address, timeout=f"{timeout_s:g}s")
        except Exception as err:              # noqa: BLE001 - every way of failing is "cannot use that address"
            outcome["error"] = err

    thread = threading.Thread(target=connect, name="dask-connect", daemon=True)
    thread.start()
    waited_s = 1.2 * timeout_s + 1.0           # Dask's own timeout first, when it applies
    thread.join(waited_s)
    if "client" in outcome:
        return outcome["client"]
    error = outcome.get("error")
    reason = outcome.get("reason") or (f"{type(error).__name__}: {error}" if error is not None else
                                       f"no Dask answer within {waited_s:g} s (is it a Dask scheduler's address?)")
    raise ConfigError("--executor", f"cannot use the Dask scheduler {address}: {reason}")


def tcp_host_port(address: str) -> Optional[Tuple[str, int]]:
    """The host and port of a ``tcp://`` scheduler address, or None for another scheme."""
    from distributed.comm.addressing import parse_address, parse_host_port

    scheme, location = parse_address(address)
    return parse_host_port(location) if scheme == "tcp" else None


def unknown_host_reason(address: str) -> Optional[str]:
    """``unknown host 'x' (...)`` when the host name of a ``tcp://`` address does not exist, else None (a resolver
    that failed this time, EAI_AGAIN, may yet answer). Cheap enough for ``--dry-run``, which connects to nothing."""
    host_port = tcp_host_port(address)
    if host_port is None:
        return None
    host, port = host_port
    try:
        socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as err:
        return f"unknown host {host!r} ({err.strerror})" if err.errno == socket.EAI_NONAME else None
    return None


def unreachable_reason(address: str, refused_for_s: float = 10.0) -> Optional[str]:
    """Why nothing can answer at a TCP ``address`` (its host name unknown, or its port refusing connections for
    ``refused_for_s``: a scheduler started just before the study takes a few seconds to listen), or None when
    that cannot be told soon. Dask retries both until its timeout and then says only "Timed out trying to
    connect ... after 30 s": a mistyped port or host name cost half a minute and hid which it was."""
    unknown = unknown_host_reason(address)
    if unknown is not None:
        return unknown
    host, port = tcp_host_port(address) or (None, None)
    if host is None:
        return None
    deadline = time.monotonic() + refused_for_s
    while True:
        try:
            socket.create_connection((host, port), timeout=5.0).close()
            return None
        except ConnectionRefusedError:
            if time.monotonic() >= deadline:
                return (f"nothing listens on port {port} of {host} (connection refused for {refused_for_s:g} s): "
                        f"is the scheduler running there?")
            time.sleep(0.25)
        except OSError:
            return None           # unreachable or slow: Dask's own timeout says so
