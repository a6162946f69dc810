"""The wire protocol between the hub and the robot agents (and the operator's ``khepri ctl``).

One message is one ZeroMQ frame. Downlink ``frame`` messages (the hub's 20 Hz sensor frames, the bulk of the
traffic) are binary: a fixed little-endian header, the neighbours as packed records, and a JSON tail for the
variable parts (relayed messages, ``reason``, ``sim``). Every other message is one compact JSON object with a
version ``v`` and a ``type``. The hub and the agent import this module, so both sides check exactly the same
rules: :func:`encode` refuses oversized messages and frames that do not fit their schema, :func:`decode`
rejects what does not fit a schema and raises :class:`ProtocolError` naming the sender and the field.
docs/protocol.md documents every type and the binary layout.

Units: metres, seconds, radians, m/s. Poses are in the world (motion-capture) frame, z up; bearings are in
the receiving robot's frame, counter-clockwise, in (-pi, pi].
"""
from __future__ import annotations

import json
import math
import struct
from typing import Any, Dict, Iterable, List, Optional, Tuple

import numpy as np

from .jsontext import parse_json
from .protocol_schema import (  # noqa: F401  (re-exported: the protocol's names live here for its users)
    COMMANDS,
    CONTROL_COMMANDS,
    DOWNLINK_TYPES,
    MAX_PAYLOAD_BYTES,
    MAX_ROBOT_ID,
    MODES,
    SCHEMAS,
    UPLINK_TYPES,
    ProtocolError,
    check_fields,
    check_payload_size,
    check_schema,
    fail,
    non_negative,
    number,
    numbers,
    short,
)

PROTOCOL_VERSION = 2
#: Largest encoded message on any socket. Downlink frames pack relayed messages only up to this size.
MAX_MESSAGE_BYTES = 65536
# The hub's replies to `khepri ctl` (the status of every robot, ~300 bytes each) may be larger: an operator's
# PC, not a robot, reads them, and a lab of a few hundred robots would not fit in MAX_MESSAGE_BYTES.
MAX_REPLY_BYTES = 4 * 1024 * 1024

# --- the binary frame (docs/protocol.md, "Binary frame layout") ----------------------------------------------
FRAME_MAGIC = b"KF"
#: magic, version, mode code, flags, 3 reserved bytes, seq, hub_t, pose_age_s, x, y, yaw, clock_s,
#: neighbour count, tail bytes: 72 bytes, little-endian, no padding.
FRAME_HEADER = struct.Struct("<2sBBB3xQddddddII")
#: One neighbour: robot id (uint32), range_m (float64), bearing_rad (float64): 20 bytes, packed.
NEIGHBOUR_DTYPE = np.dtype([("id", "<u4"), ("range", "<f8"), ("bearing", "<f8")])
FLAG_POSE = 1        # the header's x, y, yaw hold the robot's pose (else pose is null)
FLAG_CLOCK = 2       # the header's clock_s is set (sim source)
_KNOWN_FLAGS = FLAG_POSE | FLAG_CLOCK
#: Frame fields carried by the header and the neighbour block; the JSON tail must not repeat them.
FRAME_BINARY_FIELDS = ("v", "type", "seq", "mode", "hub_t", "pose", "pose_age_s", "clock_s", "neighbours")
MODE_CODES = {mode: code for code, mode in enumerate(MODES)}
# An agent sends telemetry once per loop step: at the run's control_hz, and at this rate while it has no run.
IDLE_TELEMETRY_HZ = 10.0
# The fastest control_hz a run may loop at: the hub's config accepts no more, and an agent refuses a start above it.
MAX_CONTROL_HZ = 100.0


def encode(message: Dict[str, Any], max_bytes: int = MAX_MESSAGE_BYTES) -> bytes:
    """The wire bytes of one message, the version added: a binary frame for ``type: frame`` (validated against
    its schema first), compact JSON for every other type. Raises ProtocolError when the peer would reject it:
    too large (over ``max_bytes``; MAX_REPLY_BYTES for control replies), not JSON, or (frames, and the agents'
    messages) a field that does not fit."""
    kind = message.get("type")
    if kind == "frame":
        return _encode_frame_message(message)
    body = dict(message)
    body["v"] = PROTOCOL_VERSION
    try:
        if kind in UPLINK_TYPES:
            # An agent's messages carry its driver's and its behaviour's values: one the hub drops (a state
            # that is a list) would leave the robot silent there. A broadcast's payload size is the radio's
            # to check, before it comes here: measuring it again would encode every payload twice.
            check_fields(body, kind)
        data = json.dumps(body, separators=(",", ":"), allow_nan=False).encode("utf-8")
    except ProtocolError as err:
        raise ProtocolError(err.problem, err.field, "self") from None
    except (TypeError, ValueError) as err:
        raise ProtocolError(f"cannot encode: {err}", str(message.get("type", "")), "self") from None
    if len(data) > max_bytes:
        raise ProtocolError(f"message of {len(data)} bytes exceeds {max_bytes}", str(message.get("type", "")), "self")
    return data


def pack_frame(seq: int, mode_code: int, hub_t: float, pose_age_s: float, pose: Optional[Iterable[float]],
               neighbours: Any = b"", tail: bytes = b"", clock_s: Optional[float] = None) -> bytes:
    """A binary frame from its parts, without per-field checks: the hub's fast path (``encode`` validates a
    frame dict and then calls this). ``neighbours`` is a bytes-like block of :data:`NEIGHBOUR_DTYPE` records
    (e.g. ``array.tobytes()`` or a slice of it), ``tail`` the compact-JSON tail from :func:`frame_tail` or
    ``b""``. The caller guarantees finite numbers, ranges >= 0 and robot ids; the size is checked here."""
    flags, x, y, yaw = 0, 0.0, 0.0, 0.0
    if pose is not None:
        flags = FLAG_POSE
        x, y, yaw = pose
    if clock_s is None:
        clock_s = 0.0
    else:
        flags |= FLAG_CLOCK
    block = len(neighbours)
    size = FRAME_HEADER.size + block + len(tail)
    if size > MAX_MESSAGE_BYTES:
        raise ProtocolError(f"message of {size} bytes exceeds {MAX_MESSAGE_BYTES}", "frame", "self")
    if block % NEIGHBOUR_DTYPE.itemsize:
        raise ProtocolError(f"a neighbour block of {block} bytes is not whole records", "frame.neighbours", "self")
    try:
        header = FRAME_HEADER.pack(FRAME_MAGIC, PROTOCOL_VERSION, mode_code, flags, seq, hub_t, pose_age_s,
                                   x, y, yaw, clock_s, block // NEIGHBOUR_DTYPE.itemsize, len(tail))
    except struct.error as err:
        raise ProtocolError(f"cannot encode: {err}", "frame", "self") from None
    return b"".join((header, neighbours, tail))


def frame_tail(fields: Dict[str, Any]) -> bytes:
    """The JSON tail of a frame (``messages``, ``reason``, ``sim``, future optional fields); ``b""`` when empty."""
    if not fields:
        return b""
    try:
        return json.dumps(fields, separators=(",", ":"), allow_nan=False).encode("utf-8")
    except (TypeError, ValueError) as err:
        raise ProtocolError(f"cannot encode: {err}", "frame", "self") from None


def _encode_frame_message(message: Dict[str, Any]) -> bytes:
    try:
        check_schema(message, "frame")
        if "v" in message and message["v"] != PROTOCOL_VERSION:
            fail("frame.v", f"must be {PROTOCOL_VERSION} (got {short(message['v'])})")
    except ProtocolError as err:
        raise ProtocolError(err.problem, err.field, "self") from None
    neighbours = message["neighbours"]
    block = np.array([tuple(n) for n in neighbours], dtype=NEIGHBOUR_DTYPE).tobytes() if neighbours else b""
    tail = {k: v for k, v in message.items() if k not in FRAME_BINARY_FIELDS and not (k == "messages" and not v)}
    return pack_frame(message["seq"], MODE_CODES[message["mode"]], message["hub_t"],
                      message.get("pose_age_s", 0.0), message.get("pose"), block, frame_tail(tail),
                      message.get("clock_s"))


def decode(data: bytes, sender: str = "?", accept: Optional[Iterable[str]] = None,
           neighbour_columns: bool = False, max_bytes: int = MAX_MESSAGE_BYTES) -> Dict[str, Any]:
    """Parse and validate one message (binary frame or JSON). ``accept`` restricts the types this socket takes.

    ``neighbour_columns``: a binary frame's ``neighbours`` come as the columns the block already holds, a tuple
    ``(ids, ranges_m, bearings_rad)`` of numpy arrays (int64, float64, float64), instead of a list of
    ``[id, range_m, bearing_rad]``; same checks, same values, no Python object per neighbour (the agent's path)."""
    try:
        if len(data) > max_bytes:
            fail("", f"message of {len(data)} bytes exceeds {max_bytes}")
        allowed = tuple(accept) if accept is not None else tuple(SCHEMAS)
        if data[:2] == FRAME_MAGIC:
            if "frame" not in allowed:
                fail("type", f"must be one of {', '.join(allowed)} (got a binary frame)")
            return _decode_frame(data, neighbour_columns)
        message, non_finite = _json_object(data, "", "not a JSON message or a binary frame")
        version = message.get("v")
        if version != PROTOCOL_VERSION:
            fail("v", f"unsupported protocol version {short(version)} (this side speaks {PROTOCOL_VERSION})")
        kind = message.get("type")
        if kind not in allowed:
            fail("type", f"must be one of {', '.join(allowed)} (got {short(kind)}){wrong_port_hint(kind, allowed)}")
        if kind == "frame":
            fail("type", "a frame must come in the binary frame encoding, not as JSON")
        check_schema(message, kind)
        if non_finite:
            _refuse_non_finite(message, str(kind))
        return message
    except ProtocolError as err:
        raise ProtocolError(err.problem, err.field, sender) from None


def wrong_port_hint(kind: Any, allowed: Tuple[str, ...]) -> str:
    """A message that belongs on the hub's other socket says which port was mixed up: an agent given the
    control port, or ``khepri ctl`` the robots port, otherwise only hears of "a bad message"."""
    if kind == "request" and "hello" in allowed:
        return ": a `khepri ctl` request on the robots port; ctl talks to the hub's control port"
    if kind in UPLINK_TYPES and "request" in allowed:
        return ": an agent on the control port; agents connect to the hub's robots port"
    if kind == "reply" and "frame" in allowed:
        return ": the hub's control port answered; agents connect to its robots port"
    return ""


def _decode_frame(data: bytes, neighbour_columns: bool = False) -> Dict[str, Any]:
    size, header = len(data), FRAME_HEADER.size
    if size < header:
        fail("frame", f"binary frame of {size} bytes is shorter than its {header}-byte header")
    _, version, mode_code, flags, seq, hub_t, pose_age_s, x, y, yaw, clock_s, count, tail_len = \
        FRAME_HEADER.unpack_from(data)
    if version != PROTOCOL_VERSION:
        fail("v", f"unsupported protocol version {version} (this side speaks {PROTOCOL_VERSION})")
    expected = header + count * NEIGHBOUR_DTYPE.itemsize + tail_len
    if size != expected:
        fail("frame", f"{size} bytes, but its header announces {count} neighbours and a {tail_len}-byte tail "
                       f"({expected} bytes)")
    if mode_code >= len(MODES):
        fail("frame.mode", f"must be one of {', '.join(MODES)} (got code {mode_code})")
    if flags & ~_KNOWN_FLAGS:
        fail("frame.flags", f"unknown flag bits {flags & ~_KNOWN_FLAGS:#x}")
    number(hub_t, "frame.hub_t")
    non_negative(pose_age_s, "frame.pose_age_s")
    pose = None
    if flags & FLAG_POSE:
        pose = [x, y, yaw]
        numbers(3)(pose, "frame.pose")
    message: Dict[str, Any] = {"v": version, "type": "frame", "seq": seq, "mode": MODES[mode_code],
                               "hub_t": hub_t, "pose": pose, "pose_age_s": pose_age_s}
    if flags & FLAG_CLOCK:
        number(clock_s, "frame.clock_s")
        message["clock_s"] = clock_s
    if neighbour_columns:
        message["neighbours"] = _neighbour_columns(data, count)
    else:
        message["neighbours"] = _decode_neighbours(data, count) if count else []
    message["messages"] = []
    if tail_len:
        message.update(_decode_tail(data[size - tail_len:]))
    return message


def _checked_block(data: bytes, count: int) -> np.ndarray:
    """The frame's neighbour records (a read-only view of ``data``), checked: ids, ranges >= 0, finite."""
    block = np.frombuffer(data, NEIGHBOUR_DTYPE, count, FRAME_HEADER.size)
    ids, ranges, bearings = block["id"], block["range"], block["bearing"]
    for column, bad, problem in ((0, ids > MAX_ROBOT_ID, f"must be a robot id 0..{MAX_ROBOT_ID}"),
                                 (1, ~(ranges >= 0.0) | ~np.isfinite(ranges), "must be a finite number >= 0"),
                                 (2, ~np.isfinite(bearings), "must be a finite number")):
        if bad.any():
            i = int(np.argmax(bad))
            fail(f"frame.neighbours[{i}][{column}]", f"{problem} (got {block[i][column]})")
    return block


def _decode_neighbours(data: bytes, count: int) -> List[list]:
    block = _checked_block(data, count)
    return [[i, r, b] for i, r, b in zip(block["id"].tolist(), block["range"].tolist(), block["bearing"].tolist())]


def _neighbour_columns(data: bytes, count: int) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    block = _checked_block(data, count)
    return (block["id"].astype(np.int64), block["range"].astype(np.float64),
            block["bearing"].astype(np.float64))     # contiguous, writable copies in native byte order


def _json_object(data: bytes, field: str, unreadable: str) -> Tuple[Dict[str, Any], bool]:
    """``data`` parsed as a JSON object, and whether it held NaN or Infinity (as such, or as a number too large
    for a float); a ProtocolError naming ``field`` if it is not JSON or not an object."""
    constants: List[str] = []

    def constant(name: str) -> float:
        constants.append(name)
        return float(name)

    def number(text: str) -> float:
        value = float(text)
        if not math.isfinite(value):        # 1e999: a JSON number, but one that overflows to infinity
            constants.append(text)
        return value

    try:
        value = parse_json(data, parse_constant=constant, parse_float=number)
    except ValueError:                         # not UTF-8, not JSON, or nested past the recursion limit
        fail(field, f"{unreadable} ({short(bytes(data[:40]))})")
    if not isinstance(value, dict):
        fail(field, f"must be a JSON object (got {short(value)})")
    return value, bool(constants)


def _refuse_non_finite(value: Any, where: str) -> None:
    """NaN and Infinity are not JSON: Python writes and reads them, but other JSON readers (the MCAP log's
    among them) do not, so a message holding one is refused, naming where (after the schema's own checks,
    which name a typed field more precisely)."""
    if isinstance(value, float) and not math.isfinite(value):
        fail(where, f"{value} is not a JSON number")
    if isinstance(value, dict):
        for key, item in value.items():
            _refuse_non_finite(item, f"{where}.{key}")
    elif isinstance(value, list):
        for k, item in enumerate(value):
            _refuse_non_finite(item, f"{where}[{k}]")


def _decode_tail(data: bytes) -> Dict[str, Any]:
    tail, non_finite = _json_object(data, "frame.tail", "not a JSON object")
    checks = {**SCHEMAS["frame"]["required"], **SCHEMAS["frame"]["optional"]}
    for name, value in tail.items():
        if name in FRAME_BINARY_FIELDS:
            fail(f"frame.{name}", "belongs in the binary header, not in the JSON tail")
        check = checks.get(name)
        if check is not None:
            check(value, f"frame.{name}")
    if non_finite:
        _refuse_non_finite(tail, "frame")
    return tail
