"""What each message type of the wire protocol holds, and the checks of its fields.

:mod:`onboard.protocol` encodes and decodes; this module says what is valid. Each field check takes
``(value, field path)`` and raises :class:`ProtocolError` naming the field; the sender is filled in by
``decode``. docs/protocol.md lists every type and field.
"""
from __future__ import annotations

import json
import math
from typing import Any, Callable, Dict, Iterable

#: Largest radio payload (compact JSON), the same limit as ``onboard.hal.Radio.MAX_PAYLOAD_BYTES``.
MAX_PAYLOAD_BYTES = 8192
MODES = ("idle", "run", "hold", "estop")
COMMANDS = ("start", "stop", "estop", "clear")
CONTROL_COMMANDS = ("status", "start", "stop", "estop", "clear")
MAX_ROBOT_ID = 999_999


class ProtocolError(ValueError):
    """A message broke the protocol. ``str(err)`` names the sender and the field, e.g.
    ``from robot 3: frame.pose: must be a list of 3 finite numbers``."""

    def __init__(self, problem: str, field: str = "", sender: str = "?"):
        self.problem, self.field, self.sender = problem, field, sender
        where = f"{field}: " if field else ""
        super().__init__(f"from {sender}: {where}{problem}")


Check = Callable[[Any, str], None]


def fail(field: str, problem: str) -> None:
    raise ProtocolError(problem, field)


# --- field checks: each takes (value, field path) and raises ProtocolError -------------------------------
def number(value: Any, field: str) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        fail(field, f"must be a finite number (got {short(value)})")


def non_negative(value: Any, field: str) -> None:
    number(value, field)
    if value < 0:
        fail(field, f"must be >= 0 (got {value})")


def integer(value: Any, field: str) -> None:
    if isinstance(value, bool) or not isinstance(value, int):
        fail(field, f"must be an integer (got {short(value)})")


def nonce(value: Any, field: str) -> None:
    """0 to 2**53 - 1: what every JSON reader holds exactly (docs/protocol.md), so the echo matches."""
    integer(value, field)
    if not 0 <= value < 1 << 53:
        fail(field, f"must be 0 to 2**53 - 1 (got {value})")


def robot_id(value: Any, field: str) -> None:
    integer(value, field)
    if not 0 <= value < 1_000_000:
        fail(field, f"must be a robot id 0..999999 (got {value})")


TEXT_MAX_CHARS = 200      # a text field (an agent's error, a reason): enough for one line


def text(value: Any, field: str) -> None:
    if not isinstance(value, str) or len(value) > TEXT_MAX_CHARS:
        fail(field, f"must be a string of at most {TEXT_MAX_CHARS} characters (got {short(value)})")


COUNT_LIMIT = 1 << 53     # a count an agent reports: what every JSON reader holds exactly


def counter(value: Any, field: str) -> None:
    """A count (frames lost, steps, misses): 0 to 2**53 - 1. A negative or 4000-digit one is no count."""
    integer(value, field)
    if not 0 <= value < COUNT_LIMIT:
        fail(field, f"must be a count, 0 to 2**53 - 1 (got {short(value)})")


def within(low: float, high: float) -> Check:
    """A finite number from ``low`` to ``high``: a value shown in ``ctl status`` (1e300 V printed 300 digits)."""
    def check(value: Any, field: str) -> None:
        number(value, field)
        if not low <= value <= high:
            fail(field, f"must be from {low:g} to {high:g} (got {short(value)})")
    return check


def label(value: Any, field: str) -> None:
    """What the status table shows in one column (a behaviour's state): short text, a number, true/false or
    null; not a list or an object, which the table printed raw."""
    if value is None or isinstance(value, bool):
        return
    if isinstance(value, (int, float)):
        number(value, field)
    elif not isinstance(value, str) or len(value) > TEXT_MAX_CHARS:
        fail(field, f"must be a string of at most {TEXT_MAX_CHARS} characters, a number or null "
                    f"(got {short(value)})")


def frame_seq(value: Any, field: str) -> None:
    """A frame's ``seq`` (a uint64 in the binary header), as a telemetry's ``step`` echoes it."""
    integer(value, field)
    if not 0 <= value < 1 << 64:
        fail(field, f"must be a frame's seq, 0 to 2**64 - 1 (got {short(value)})")


def mapping(value: Any, field: str) -> None:
    if not isinstance(value, dict):
        fail(field, f"must be a JSON object (got {short(value)})")


def boolean(value: Any, field: str) -> None:
    if not isinstance(value, bool):
        fail(field, f"must be true or false (got {short(value)})")


def one_of(options: Iterable[str]) -> Check:
    allowed = tuple(options)

    def check(value: Any, field: str) -> None:
        if value not in allowed:
            fail(field, f"must be one of {', '.join(allowed)} (got {short(value)})")
    return check


def numbers(count: int) -> Check:
    def check(value: Any, field: str) -> None:
        if not isinstance(value, list) or len(value) != count:
            fail(field, f"must be a list of {count} finite numbers (got {short(value)})")
        for i, item in enumerate(value):
            number(item, f"{field}[{i}]")
    return check


def optional(check: Check) -> Check:
    def check_optional(value: Any, field: str) -> None:
        if value is not None:
            check(value, field)
    return check_optional


def list_of(check: Check, limit: int = 100_000) -> Check:
    def check_list(value: Any, field: str) -> None:
        if not isinstance(value, list) or len(value) > limit:
            fail(field, f"must be a list of at most {limit} items (got {short(value)})")
        for i, item in enumerate(value):
            check(item, f"{field}[{i}]")
    return check_list


def fields_of(shape: str, *checks: Check) -> Check:
    """A list of exactly ``len(checks)`` items, item i passing ``checks[i]``; ``shape`` names them in errors."""
    def check_fields(value: Any, field: str) -> None:
        if not isinstance(value, list) or len(value) != len(checks):
            fail(field, f"must be {shape} (got {short(value)})")
        for i, (check, item) in enumerate(zip(checks, value)):
            check(item, f"{field}[{i}]")
    return check_fields


neighbour = fields_of("[id, range_m, bearing_rad]", robot_id, non_negative, number)
relayed = fields_of("[sender, sent_s, payload]", robot_id, number, mapping)


def fields(checks: Dict[str, Check]) -> Check:
    """A JSON object whose listed fields, those present, pass their checks; others are left alone."""
    def check_fields(value: Any, field: str) -> None:
        mapping(value, field)
        for name, check in checks.items():
            if name in value:
                check(value[name], f"{field}.{name}")
    return check_fields


# What the hub reads of a telemetry's `behaviour` (the rest is the behaviour's own) and its `loop`. The hub
# shows them in `ctl status` and acts on `finished`: a "no" there was taken for finished.
behaviour_report = optional(fields({"state": label, "finished": optional(boolean)}))
MAX_LOOP_HZ = 1e6           # far above any loop (a lockstep sil steps as fast as the PC goes), far below 1e300
MAX_BATTERY_V = 1000.0      # a KheperaIV reads at most 640 V (16 bits of 9.76 mV): a bad read, but still a reading
battery_reading = optional(within(0.0, MAX_BATTERY_V))
loop_report = fields({"hz": within(0.0, MAX_LOOP_HZ), "steps": counter, "misses": counter,
                      "mean_ms": non_negative, "max_ms": non_negative})


def sim_sensors(value: Any, field: str) -> None:
    mapping(value, field)
    numbers(8)(value.get("ir"), f"{field}.ir")
    numbers(2)(value.get("odo"), f"{field}.odo")


# --- schemas: per type, required and optional fields. Unknown fields are ignored (additions within a version).
Schema = Dict[str, Check]
SCHEMAS: Dict[str, Dict[str, Schema]] = {
    # hub -> agent
    "frame": {
        "required": {"seq": integer, "mode": one_of(MODES), "hub_t": number,
                     "neighbours": list_of(neighbour), "messages": list_of(relayed)},
        "optional": {"pose": optional(numbers(3)), "pose_age_s": non_negative, "reason": text,
                     "clock_s": number, "sim": sim_sensors},
    },
    "command": {
        "required": {"cmd": one_of(COMMANDS)},
        "optional": {"run": mapping, "reason": text},
    },
    # agent -> hub
    "hello": {
        "required": {"id": robot_id, "driver": text},
        "optional": {"run_id": optional(text), "agent": text},
    },
    "telemetry": {
        "required": {"id": robot_id, "step": frame_seq, "mode": text},
        "optional": {"behaviour": behaviour_report, "loop": loop_report, "battery_v": battery_reading,
                     "clock_s": optional(number), "frames_lost": counter, "frames_bad": counter, "unsent": counter,
                     "inbox_dropped": counter, "run_id": optional(text), "error": optional(text),
                     "refused_run_id": optional(text), "driver": text, "agent": text},
    },
    "broadcast": {
        "required": {"id": robot_id, "payload": mapping, "sent_s": number},
        "optional": {"agent": text},
    },
    "wheels": {
        "required": {"id": robot_id, "left": number, "right": number},
        "optional": {"agent": text, "at_s": number},
    },
    "ack": {
        "required": {"id": robot_id, "cmd": one_of(COMMANDS)},
        "optional": {"seq": integer, "agent": text},
    },
    # operator <-> hub (control socket)
    "request": {
        "required": {"cmd": one_of(CONTROL_COMMANDS)},
        "optional": {"nonce": nonce},
    },
    "reply": {
        "required": {"ok": boolean},
        "optional": {"error": text, "status": mapping, "nonce": nonce},
    },
}
DOWNLINK_TYPES = ("frame", "command")
UPLINK_TYPES = ("hello", "telemetry", "broadcast", "wheels", "ack")


def check_schema(message: Dict[str, Any], kind: str) -> None:
    """Raise ProtocolError naming the first field of ``message`` that its type's schema does not allow."""
    check_fields(message, kind)
    if kind == "broadcast":
        check_payload_size(message["payload"], f"{kind}.payload")


def check_fields(message: Dict[str, Any], kind: str) -> None:
    """``check_schema`` but for a broadcast's payload size, which takes encoding the payload to learn."""
    schema = SCHEMAS[kind]
    for name, check in schema["required"].items():
        if name not in message:
            fail(f"{kind}.{name}", "is required")
        check(message[name], f"{kind}.{name}")
    for name, check in schema["optional"].items():
        if name in message:
            check(message[name], f"{kind}.{name}")


def check_payload_size(payload: Dict[str, Any], field: str = "payload") -> int:
    """Bytes of the payload as compact JSON; ProtocolError above MAX_PAYLOAD_BYTES."""
    try:
        size = len(json.dumps(payload, separators=(",", ":"), allow_nan=False))
    except ValueError as err:                  # NaN or infinity: not JSON, refused as the hub would
        fail(field, f"radio payload is not JSON: {err}")
    if size > MAX_PAYLOAD_BYTES:
        fail(field, f"radio payload of {size} bytes exceeds {MAX_PAYLOAD_BYTES}")
    return size


def short(value: Any) -> str:
    """``value`` as shown in an error: its repr, cut to 40 characters (a bad field may be megabytes)."""
    shown = repr(value)
    return shown if len(shown) <= 40 else shown[:37] + "..."
