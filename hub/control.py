"""``khepri ctl``'s side of the control socket: one request, one reply, and the status table."""
from __future__ import annotations

import math
import random
import time
from typing import Any, Callable, Dict, List, Optional, Tuple

import zmq

from onboard.agent import connection
from onboard.agent.connection import ConnectionWatch, watch_connection
from onboard.agent.link import endpoint_candidates, family_hint, use_ipv6
from onboard.console import one_line
from onboard.protocol import MAX_REPLY_BYTES, ProtocolError, decode, encode

from .security import apply_client_keys

DEFAULT_CONTROL_ENDPOINT = "tcp://127.0.0.1:5561"


class ControlError(RuntimeError):
    """The hub did not answer, or answered with an error. ``keys_may_help``: no answer, and nothing tells that
    keys are beside the point (a refused connection is; an encrypted hub is not)."""

    def __init__(self, message: str, keys_may_help: bool = False) -> None:
        super().__init__(message)
        self.keys_may_help = keys_may_help


class BadEndpoint(ControlError):
    """ZeroMQ cannot use the hub's address at all (e.g. a space in the host name)."""


def request(endpoint: str, cmd: str, keys: Optional[Dict[str, bytes]] = None, timeout_s: float = 2.0,
            context: Optional[zmq.Context] = None) -> Dict[str, Any]:
    """Send one control request and return the reply (``ok`` true), or raise ControlError."""
    context = context or zmq.Context.instance()
    sock = context.socket(zmq.DEALER)
    sock.linger = 0
    if keys is not None:
        apply_client_keys(sock, keys)
    watch = watch_connection(context, sock)      # before connect: its first events say why a hub is silent
    try:
        try:
            connect_any(sock, endpoint)
        except zmq.ZMQError as err:
            raise BadEndpoint(f"cannot connect to {endpoint!r}: {(err.strerror or str(err)).split(' (addr=')[0]}") \
                from None
        nonce = random.randrange(1 << 30)
        # A DEALER blocks sending until a connection is up; with a wrong key it never comes up.
        sock.sndtimeo = int(timeout_s * 1000)
        try:
            sock.send(encode({"type": "request", "cmd": cmd, "nonce": nonce}))
        except zmq.Again:
            raise no_answer(endpoint, timeout_s, watch, keys is not None) from None
        reply = _await_reply(sock, nonce, timeout_s, endpoint)
        if reply is None:
            raise no_answer(endpoint, timeout_s, watch, keys is not None)
    finally:
        if watch is not None:
            watch.close()
        sock.close(0)
    if not reply["ok"]:
        raise ControlError(f"the hub refused {cmd}: {reply.get('error', 'no reason given')}")
    return reply


def connect_any(sock: zmq.Socket, endpoint: str) -> None:
    """Connect to every address ``endpoint`` stands for (localhost: both loopbacks). IMMEDIATE makes the request
    wait for whichever connects, instead of queueing it for an address where no hub listens; a hub on both
    gets one request on one connection, and answers on that one."""
    addresses = endpoint_candidates(endpoint)
    if len(addresses) > 1:
        sock.immediate = 1
    for address in addresses:         # IPv4 first: the IPV6 option, once on, stays on for the later ones
        use_ipv6(sock, address)
        sock.connect(address)


def refusals_after_start(endpoint: str, keys: Optional[Dict[str, bytes]] = None, timeout_s: float = 2.0,
                         wait_s: float = 5.0) -> List[Tuple[int, str]]:
    """After ``start``: the connected robots that say they cannot run it (an unknown behaviour, bad params, an
    ``__init__`` that raised), as (id, error). An agent says so in its telemetry, after the hub's reply, so
    this asks the status until every connected robot has answered the new run (it holds it, or it refused
    it: ``refused_run_id``) or ``wait_s`` has passed. The wait is that long only for a robot that does not
    answer: on a loaded lab PC or a slow radio an answer can take over a second."""
    deadline = time.monotonic() + wait_s
    while True:
        status = request(endpoint, "status", keys=keys, timeout_s=timeout_s)["status"]
        connected = [row for row in status["robots"] if row.get("connected")]
        run_id = status.get("run_id")
        # A robot that reports the new run has also dropped any older error (a fresh one: its __init__ raised)
        answered = all(run_id in (row.get("run_id"), row.get("refused_run_id")) for row in connected)
        if answered or time.monotonic() >= deadline:
            return [(row["id"], str(row["error"])) for row in connected if row.get("error")]
        time.sleep(0.1)


def _await_reply(sock: zmq.Socket, nonce: int, timeout_s: float, endpoint: str) -> Optional[Dict[str, Any]]:
    """The reply to ``nonce``, or None when none came within ``timeout_s``."""
    poller = zmq.Poller()
    poller.register(sock, zmq.POLLIN)
    while poller.poll(timeout_s * 1000.0):
        try:
            reply = decode(sock.recv(), f"hub at {endpoint}", accept=("reply",), max_bytes=MAX_REPLY_BYTES)
        except ProtocolError as err:
            raise ControlError(str(err)) from None
        if reply.get("nonce") == nonce:
            return reply
    return None


def no_answer(endpoint: str, timeout_s: float, watch: Optional[ConnectionWatch] = None,
              keyed: bool = False) -> ControlError:
    """No reply: what the connection's events tell (refused, no keys for an encrypted hub, ...), else every
    question. A dead hub was answered with `try again with --keys`: keys do not help where nothing listens."""
    start = f"no answer from the hub at {endpoint} within {timeout_s:g} s"
    kind = watch.kind() if watch is not None else None      # read once: the cause and the hint say one thing
    found = connection_cause(kind, watch, keyed) if watch is not None else None
    if found is None:
        return ControlError(f"{start} (is it running, and is that its control port, the one it printed after "
                            "`listening control`? A secure hub needs --keys with an operator key it lists; a hub "
                            f"run with --insecure needs no keys). {family_hint(endpoint)}".rstrip(),
                            keys_may_help=True)
    cause, keys_may_help = found
    # The address family matters only where nothing answered: not after a handshake, whose cause is known.
    hint = family_hint(endpoint) if kind in (connection.REFUSED, connection.NO_ANSWER) else ""
    return ControlError(f"{start}: {cause} {hint}".rstrip(), keys_may_help=keys_may_help)


def connection_cause(kind: Optional[str], watch: ConnectionWatch, keyed: bool) -> Optional[Tuple[str, bool]]:
    """(the likeliest cause, whether operator keys may be the fix), from what the connection's events said
    (``watch.kind()``)."""
    if kind == connection.MECHANISM_MISMATCH:
        if keyed:
            return "the hub is not encrypted (it runs --insecure): run ctl without --keys.", False
        return ("the hub is encrypted: give --keys, a folder holding hub.key and operators/<name>.key_secret "
                "(khepri keys init made it)."), True
    if kind == connection.KEY_REFUSED:
        # The robots port refuses every operator key too: that mix-up sent operators off to check their keys.
        return ("the hub refused this operator key: is that the hub's control port, the one it printed after "
                "`listening control`, and not its robots port (which takes robot keys only)? If it is, does the "
                "hub's key folder list the key in operators/?"), True
    if kind == connection.HANDSHAKE_DROPPED and keyed and watch.protocol_error is None:   # libzmq's timing
        return ("the hub dropped the encrypted handshake (no detail given): is the hub.key in --keys this hub's "
                "key, and does the hub run with keys (not --insecure, for which ctl runs without --keys)?"), True
    if kind == connection.HANDSHAKE_DROPPED and keyed:
        return "the hub dropped the encrypted handshake: the hub.key in --keys is not this hub's key.", True
    if kind == connection.HANDSHAKE_DROPPED:  # libzmq says "no detail" as often as "mechanism mismatch", by timing
        return (f"the hub dropped the connection in ZeroMQ's handshake ({watch.detail()}), as an encrypted hub "
                "does to a ctl without keys: give --keys, a folder holding hub.key and operators/<name>.key_secret "
                "(khepri keys init made it); or is that not the hub's control port?"), True
    if kind == connection.CONNECTED_SILENT:
        return ("connected, but nothing answers: is that the hub's control port, the one it printed after "
                "`listening control`, and not its robots port? (a hub too busy to answer needs a longer "
                "--timeout)"), False
    if kind == connection.REFUSED:
        return ("nothing accepts a connection there (refused or unreachable): is the hub running, and is that "
                "its control port, the one it printed after `listening control`?"), False
    if kind == connection.NO_ANSWER:
        return ("no answer at that address at all: is it the hub PC's, is that PC on this network, or does a "
                "firewall drop the connection?"), False
    return None


def status_table(status: Dict[str, Any]) -> str:
    """``ctl status``'s text. It prints whatever the hub reports, a peer's values included (an older hub checked
    no telemetry: a loop rate of "fast" ended ctl in a traceback), so no value can make it fail."""
    lines = [f"hub: {status.get('mode')}  run: {status.get('run_id') or '-'}  behaviour: {status.get('behaviour')}  "
             f"source: {status.get('source')}  mocap: {figure(status.get('mocap_hz'), '.1f')} Hz  "
             f"{'secure (CURVE)' if status.get('secure') else 'INSECURE'}"]
    recording = status.get("recording")
    if not isinstance(recording, dict):
        recording = None
    if recording and recording.get("error"):
        lines.append(f"RECORDING STOPPED ({recording.get('path')}): {recording['error']}")
    elif recording:         # "am I recording, and where?" had only --json to answer it
        lines.append(f"recording: {recording.get('path')}")
    if recording and recording.get("left_out"):
        lines.append(f"RECORDING FELL BEHIND: {recording['left_out']} messages left out (the disk was too slow)")
    robots = status.get("robots")
    lines = [one_line(line) for line in lines]      # the robot rows are escaped cell by cell, to keep in line
    lines += robot_table([row for row in robots if isinstance(row, dict)] if isinstance(robots, list) else [])
    # Newer hubs' fields (docs/protocol.md): an older hub's reply has none of them, and gets no such line.
    if status.get("object"):
        lines.append(one_line(readable("object", object_text, status["object"])))
    if status.get("replay"):
        lines.append(one_line(readable("replay", replay_text, status["replay"])))
    drops = status.get("drops") or {}
    if isinstance(drops, dict) and drops:
        # The counts are the hub's lifetime's: said so, as they outlive the run they came from.
        counts = ", ".join(f"{reason} {count}" for reason, count in sorted(drops.items()))
        lines.append(one_line(f"dropped since the hub started: {counts}"))
    return "\n".join(lines)


def figure(value: Any, spec: str = "", unit: str = "") -> str:
    """A number as the table prints it: ``-`` for none, ``?`` for what is not a number of a sensible size (text,
    NaN, 1e300 printed 300 digits wide), rather than a traceback or a column out of all proportion."""
    if value is None:
        return "-"
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not abs(value) < 1e12:   # NaN fails too
        return "?"
    return f"{value:{spec}}{unit}"


def readable(name: str, text: Callable[[Dict[str, Any]], str], section: Any) -> str:
    """``text(section)``, or a line saying the hub's ``name`` could not be read (a hub of another version)."""
    try:
        return text(section)
    except (TypeError, ValueError, KeyError, IndexError, AttributeError):
        return f"{name}: the hub's report of it cannot be read (khepri versions differ?)"


# The status table's columns: title and whether it is right-aligned (numbers). The note is last, unpadded.
COLUMNS = (("robot", True), ("connected", False), ("last seen", True), ("mode", False), ("state", False),
           ("loop Hz", True), ("misses", True), ("battery", True), ("note", False))
STATE_WIDTH = 14        # a behaviour's state name longer than this is cut: the note after it stays in view


def robot_table(rows: List[Dict[str, Any]]) -> List[str]:
    """Header and one line per robot, each column as wide as its widest cell (a 6-digit id, a robot silent
    for hours, a million misses), so that the columns stay in line."""
    cells = [[title for title, _ in COLUMNS]] + [_row_cells(row) for row in rows]
    widths = [max(len(line[i]) for line in cells) for i in range(len(COLUMNS) - 1)]

    def line(values: List[str]) -> str:
        padded = [value.rjust(width) if right else value.ljust(width)
                  for value, width, (_, right) in zip(values, widths, COLUMNS)]
        return "  ".join(padded + [values[-1]]).rstrip()

    return [line(values) for values in cells]


def _row_cells(row: Dict[str, Any]) -> List[str]:
    seen_s, connected = row.get("last_seen_s"), bool(row.get("connected"))
    seen = "never" if seen_s is None else figure(seen_s, ".1f", " s")
    notes: List[str] = [str(n) for n in (row.get("reason"), row.get("error")) if n]
    if not connected and seen_s is not None:
        # The state is what the agent said last, not what it does now: it may be dead, its wheels held.
        # (A crashed agent's last report had no behaviour, so no state: then there is none to speak of.)
        last = ": state is its last report" if row.get("state") else ""
        notes.insert(0, f"silent for {seen}{last}")
    if row.get("finished") is True:          # only true: a peer's "no" read as finished
        notes.insert(0, "finished")
    if row.get("estop_ack_ms") is not None:
        notes.append(f"e-stop acknowledged in {figure(row['estop_ack_ms'], '.1f')} ms")
    state = one_line(str(row.get("state") or "-"))[:STATE_WIDTH]
    # A robot never connected runs nothing: `run` in its row, the hub's mode for it, read as if it did.
    mode = "-" if seen_s is None and not connected else str(row.get("mode"))
    cells = [str(row.get("id")), "yes" if connected else "no", seen, mode, state, figure(row.get("loop_hz"), ".1f"),
             figure(row.get("loop_misses")), figure(row.get("battery_v"), ".2f", " V"), "; ".join(notes)]
    return [one_line(cell) for cell in cells]       # a robot's text: its newline broke the table, its ESC coloured it


def object_text(status: Optional[Dict[str, Any]]) -> str:
    """'object at (0.01, 0.31) m, yaw -2.0°, waypoint 2 of 3 is 0.29 m away': ``ctl status``'s line."""
    if not status:
        return ""
    x, y, yaw = status["pose"]
    text = f"object at ({round(x, 2) + 0.0:.2f}, {round(y, 2) + 0.0:.2f}) m, yaw {_degrees(yaw)}°"   # no "-0.00"
    count, reached = status["waypoints"], status.get("reached")
    if not count:
        return text + ", no waypoints"
    if reached is None or status.get("distance_m") is None:
        return text + f", {count} waypoint{'s' if count != 1 else ''} (which are reached is not known)"
    away = f"{status['distance_m']:.2f} m and {_degrees(status['yaw_error_rad'])}°"
    if reached >= count:
        return text + f", all {count} waypoints reached, {away} from the last"
    return text + f", waypoint {status['target'] + 1} of {count} is {away} away ({reached} reached)"


def _degrees(radians: float) -> str:
    return f"{round(math.degrees(radians), 1) + 0.0:.1f}"     # + 0.0: never "-0.0"


def replay_text(replay: Dict[str, Any]) -> str:
    """'replay: 12.3 s of 60.0 s played (20 %) at 1x': how far a replay source has got."""
    played, total, percent = replay["played_s"], replay.get("total_s"), replay.get("percent")
    rate = f" at {replay['rate']:g}x" if replay.get("rate") is not None else ""
    if total is not None:
        text = f"{played:.1f} s of {total:.1f} s played ({percent:.0f} %){rate}"
    elif percent is not None:
        text = f"{played:.1f} s played{rate}, {percent:.0f} % of the file (a log cut short: its length is not known)"
    else:
        text = f"{played:.1f} s played{rate}"
    if replay.get("passed_over"):       # latest-only at a high rate: not every recorded frame was fed
        passed = replay['passed_over']
        text += f", {passed} frame{'s' if passed != 1 else ''} passed over to keep up"
    return f"replay: {'ended: ' if replay.get('ended') else ''}{text}"
