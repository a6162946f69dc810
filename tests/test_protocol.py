"""The wire protocol: every message type round-trips, and bad messages are rejected naming sender and field."""
import json
import math

import pytest

from onboard.protocol import (
    DOWNLINK_TYPES,
    MAX_MESSAGE_BYTES,
    PROTOCOL_VERSION,
    UPLINK_TYPES,
    ProtocolError,
    decode,
    encode,
)

EXAMPLES = {
    "frame": {"type": "frame", "seq": 7, "mode": "run", "hub_t": 12.5, "pose": [0.1, -0.2, 1.5],
              "pose_age_s": 0.004, "neighbours": [[3, 0.42, -1.2], [4, 1.0, 3.1]],
              "messages": [[3, 10.1, {"task": [1, 2]}]], "clock_s": 10.2,
              "sim": {"ir": [0.0] * 8, "odo": [0.5, 0.6]}},
    "command": {"type": "command", "cmd": "start", "run": {"behaviour": "aggregate", "params": {}}},
    "hello": {"type": "hello", "id": 3, "driver": "SimDriver", "run_id": None},
    "telemetry": {"type": "telemetry", "id": 3, "step": 7, "mode": "run", "behaviour": {"state": "push"},
                  "loop": {"hz": 10.0}, "battery_v": 7.4, "frames_lost": 0, "frames_bad": 0},
    "broadcast": {"type": "broadcast", "id": 3, "payload": {"bid": 0.4}, "sent_s": 1.0},
    "wheels": {"type": "wheels", "id": 3, "left": 0.1, "right": -0.1},
    "ack": {"type": "ack", "id": 3, "cmd": "estop", "seq": 7},
    "request": {"type": "request", "cmd": "status", "nonce": 1},
    "reply": {"type": "reply", "ok": True, "status": {"mode": "idle"}, "nonce": 1},
}


@pytest.mark.parametrize("kind", sorted(EXAMPLES))
def test_every_message_type_round_trips(kind):
    data = encode(EXAMPLES[kind])
    decoded = decode(data, "robot 3")
    assert decoded["v"] == PROTOCOL_VERSION
    assert {k: v for k, v in decoded.items() if k != "v"} == EXAMPLES[kind]


def test_encoding_is_compact_json():
    data = encode(EXAMPLES["wheels"])
    assert b" " not in data
    assert json.loads(data)["type"] == "wheels"


def reject(data, accept=None, sender="robot 3"):
    with pytest.raises(ProtocolError) as info:
        decode(data if isinstance(data, bytes) else json.dumps(data).encode(), sender, accept)
    return str(info.value)


def with_v(message):
    return {**message, "v": PROTOCOL_VERSION}


def test_wrong_version_names_the_field_and_both_versions():
    text = reject({**EXAMPLES["hello"], "v": 99})
    assert text.startswith("from robot 3: v: ") and "99" in text and str(PROTOCOL_VERSION) in text
    assert "v:" in reject(EXAMPLES["hello"])           # no version at all


@pytest.mark.parametrize("data, field", [
    (b"\xff\xfe not json", ""), (b"[1, 2]", ""), (b"{\"v\": 1", ""), (b"", ""),
])
def test_garbage_is_rejected(data, field):
    assert reject(data).startswith("from robot 3: ")


@pytest.mark.parametrize("kind, field, value", [
    ("frame", "pose", [0.0, 1.0]),
    ("frame", "pose", [0.0, math.nan, 0.0]),
    ("frame", "neighbours", [[3, -0.5, 0.0]]),
    ("frame", "neighbours", [["three", 0.5, 0.0]]),
    ("frame", "messages", [[3, 1.0, "not a mapping"]]),
    ("frame", "mode", "dance"),
    ("frame", "seq", 1.5),
    ("telemetry", "step", True),
    ("wheels", "left", "fast"),
    ("wheels", "right", math.inf),
    ("hello", "id", -1),
    ("command", "cmd", "self-destruct"),
])
def test_bad_fields_are_named(kind, field, value):
    message = dict(EXAMPLES[kind])
    message[field] = value
    text = reject(with_v(message))
    assert f"{kind}.{field}" in text


def test_missing_required_field_is_named():
    message = dict(EXAMPLES["broadcast"])
    del message["sent_s"]
    assert "broadcast.sent_s: is required" in reject(with_v(message))


def test_a_socket_accepts_only_its_direction():
    frame = encode(EXAMPLES["frame"])
    assert "type" in reject(frame, accept=UPLINK_TYPES)
    assert decode(frame, "hub", accept=DOWNLINK_TYPES)["seq"] == 7
    assert "type" in reject(encode(EXAMPLES["wheels"]), accept=DOWNLINK_TYPES)


def test_oversized_messages_are_refused_both_ways():
    huge = {"type": "broadcast", "id": 1, "payload": {"x": "a" * MAX_MESSAGE_BYTES}, "sent_s": 0.0}
    with pytest.raises(ProtocolError, match="exceeds"):
        encode(huge)
    raw = json.dumps(with_v(huge)).encode()
    assert "exceeds" in reject(raw)


def test_radio_payload_limit_is_the_hal_limit():
    message = with_v({**EXAMPLES["broadcast"], "payload": {"x": "a" * 8200}})
    assert "broadcast.payload" in reject(message) and "8192" in reject(message)


def test_deeply_nested_json_is_rejected_not_crashing():
    assert reject(b"[" * 30_000 + b"]" * 30_000).startswith("from robot 3")


def test_unknown_fields_are_ignored_for_forward_compatibility():
    decoded = decode(encode({**EXAMPLES["wheels"], "future": 1}), "robot 3")
    assert decoded["left"] == 0.1
