"""The wire protocol: every message type round-trips, and bad messages are rejected naming sender and field."""
import json
import math
import re
import struct

import pytest

from onboard.protocol import (
    DOWNLINK_TYPES,
    FRAME_HEADER,
    MAX_MESSAGE_BYTES,
    NEIGHBOUR_DTYPE,
    PROTOCOL_VERSION,
    UPLINK_TYPES,
    ProtocolError,
    decode,
    encode,
    frame_tail,
    pack_frame,
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


def test_a_frame_is_binary_with_the_documented_layout():
    data = encode(EXAMPLES["frame"])
    magic, version, mode, flags, seq, hub_t, age, x, y, yaw, clock_s, count, tail = FRAME_HEADER.unpack_from(data)
    assert FRAME_HEADER.size == 72 and NEIGHBOUR_DTYPE.itemsize == 20
    assert (magic, version, mode, flags, seq, hub_t, age) == (b"KF", PROTOCOL_VERSION, 1, 3, 7, 12.5, 0.004)
    assert (x, y, yaw, clock_s, count) == (0.1, -0.2, 1.5, 10.2, 2)
    assert struct.unpack_from("<Idd", data, 72) == (3, 0.42, -1.2)
    assert json.loads(data[72 + 40:]) == {"messages": [[3, 10.1, {"task": [1, 2]}]],
                                          "sim": {"ir": [0.0] * 8, "odo": [0.5, 0.6]}}
    assert len(data) == 72 + 40 + tail


def test_a_frame_without_pose_messages_or_extras_has_no_tail():
    data = encode({"type": "frame", "seq": 1, "mode": "hold", "hub_t": 3.0, "pose": None, "neighbours": [],
                   "messages": [], "reason": ""})
    assert len(data) == FRAME_HEADER.size + len(b'{"reason":""}')
    decoded = decode(encode({"type": "frame", "seq": 1, "mode": "idle", "hub_t": 3.0, "neighbours": [],
                             "messages": []}), "hub")
    assert decoded == {"v": PROTOCOL_VERSION, "type": "frame", "seq": 1, "mode": "idle", "hub_t": 3.0,
                       "pose": None, "pose_age_s": 0.0, "neighbours": [], "messages": []}


def test_the_hubs_fast_path_gives_what_encode_gives():
    frame = EXAMPLES["frame"]
    block = b"".join(struct.pack("<Idd", *n) for n in frame["neighbours"])
    fast = pack_frame(7, 1, 12.5, 0.004, (0.1, -0.2, 1.5), memoryview(block),
                      frame_tail({"messages": frame["messages"], "sim": frame["sim"]}), 10.2)
    assert fast == encode(frame)


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
    ("telemetry", "step", -1),
    ("telemetry", "loop", {"hz": "fast"}),               # ended `ctl status` in a traceback
    ("telemetry", "loop", {"misses": 1.5}),
    ("telemetry", "behaviour", {"finished": "no"}),      # the hub took it for finished
    ("telemetry", "behaviour", {"state": {"a": 1}}),
    ("telemetry", "battery_v", 1e300),
    ("telemetry", "inbox_dropped", -1),
    ("wheels", "left", "fast"),
    ("wheels", "right", math.inf),
    ("hello", "id", -1),
    ("command", "cmd", "self-destruct"),
    ("request", "nonce", -5),                  # protocol.md: 0 to 2**53 - 1; the hub took and echoed these
    ("request", "nonce", 9007199254740993),
])
def test_bad_fields_are_named(kind, field, value):
    message = dict(EXAMPLES[kind])
    message[field] = value
    if kind == "frame":          # binary: encode refuses it, naming the field, as decode would
        with pytest.raises(ProtocolError, match=f"from self: {kind}.{field}"):
            encode(message)
        return
    text = reject(with_v(message))
    assert f"{kind}.{field}" in text


def corrupt(offset, fmt, value, frame=None):
    data = bytearray(encode(frame or EXAMPLES["frame"]))
    struct.pack_into(fmt, data, offset, value)
    return bytes(data)


@pytest.mark.parametrize("data, field", [
    (corrupt(2, "<B", 1), "v: unsupported protocol version 1"),
    (corrupt(3, "<B", 4), "frame.mode"),
    (corrupt(4, "<B", 0x83), "frame.flags"),
    (corrupt(16, "<d", math.nan), "frame.hub_t"),
    (corrupt(24, "<d", -0.1), "frame.pose_age_s"),
    (corrupt(40, "<d", math.inf), "frame.pose[1]"),
    (corrupt(56, "<d", math.nan), "frame.clock_s"),
    (corrupt(64, "<I", 3), "frame: "),                       # announces 3 neighbours, carries 2
    (corrupt(68, "<I", 1), "frame: "),                       # announces a 1-byte tail
    (corrupt(72 + 20, "<I", 1_000_000), "frame.neighbours[1][0]"),
    (corrupt(72 + 4, "<d", -0.5), "frame.neighbours[0][1]"),
    (corrupt(72 + 20 + 12, "<d", math.nan), "frame.neighbours[1][2]"),
    (encode(EXAMPLES["frame"])[:60], "frame: "),             # shorter than the header
    (encode(EXAMPLES["frame"])[:-1] + b"]", "frame.tail"),   # a tail that is not JSON
])
def test_bad_binary_frames_are_rejected_naming_the_field(data, field):
    assert reject(data, accept=DOWNLINK_TYPES, sender="hub").startswith(f"from hub: {field}")


@pytest.mark.parametrize("tail, field", [
    (b"[1]", "frame.tail"), (b'{"seq": 3}', "frame.seq"), (b'{"messages": [[1, 0.0, 5]]}', "frame.messages[0][2]"),
    (b'{"sim": {"ir": [0.0], "odo": [0.0, 0.0]}}', "frame.sim.ir"), (b'{"reason": 5}', "frame.reason"),
])
def test_bad_frame_tails_are_rejected_naming_the_field(tail, field):
    data = pack_frame(1, 0, 0.0, 0.0, None, b"", tail)
    assert reject(data, sender="hub").startswith(f"from hub: {field}")


def test_a_json_frame_is_refused():
    assert "binary" in reject(with_v(EXAMPLES["frame"]))


def test_missing_required_field_is_named():
    message = dict(EXAMPLES["broadcast"])
    del message["sent_s"]
    assert "broadcast.sent_s: is required" in reject(with_v(message))


def test_a_socket_accepts_only_its_direction():
    frame = encode(EXAMPLES["frame"])
    assert "type" in reject(frame, accept=UPLINK_TYPES)
    assert decode(frame, "hub", accept=DOWNLINK_TYPES)["seq"] == 7
    assert "type" in reject(encode(EXAMPLES["wheels"]), accept=DOWNLINK_TYPES)


@pytest.mark.parametrize("kind, accept, said", [
    ("request", UPLINK_TYPES, "a `khepri ctl` request on the robots port"),
    ("hello", ("request",), "an agent on the control port"),
    ("reply", DOWNLINK_TYPES, "the hub's control port answered"),
])
def test_a_message_for_the_other_port_says_which_port_was_mixed_up(kind, accept, said):
    """An agent given the hub's control port, or `khepri ctl` its robots port, only heard of a bad message."""
    messages = {"request": {"type": "request", "cmd": "status", "nonce": 1},
                "hello": {"type": "hello", "id": 0, "driver": "sim"},
                "reply": {"type": "reply", "ok": True, "nonce": 1}}
    with pytest.raises(ProtocolError, match=re.escape(said)) as refused:
        decode(encode(messages[kind]), "peer", accept=accept)
    assert refused.value.field == "type"
    with pytest.raises(ProtocolError) as plain:          # a type of no socket's: no hint
        decode(encode({"type": "telemetry", "id": 0, "step": 1, "mode": "idle"}), "hub", accept=DOWNLINK_TYPES)
    assert "port" not in str(plain.value)


def test_oversized_messages_are_refused_both_ways():
    huge = {"type": "broadcast", "id": 1, "payload": {"x": "a" * MAX_MESSAGE_BYTES}, "sent_s": 0.0}
    with pytest.raises(ProtocolError, match="exceeds"):
        encode(huge)
    raw = json.dumps(with_v(huge)).encode()
    assert "exceeds" in reject(raw)
    crowded = {**EXAMPLES["frame"], "neighbours": [[i, 1.0, 0.0] for i in MAX_MESSAGE_BYTES // 20 * [1]]}
    with pytest.raises(ProtocolError, match="exceeds"):
        encode(crowded)
    block = b"\0" * (MAX_MESSAGE_BYTES // 20 * 20)
    oversized = FRAME_HEADER.pack(b"KF", PROTOCOL_VERSION, 0, 0, 1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, len(block) // 20, 0)
    assert "exceeds" in reject(oversized + block)


def test_radio_payload_limit_is_the_hal_limit():
    message = with_v({**EXAMPLES["broadcast"], "payload": {"x": "a" * 8200}})
    assert "broadcast.payload" in reject(message) and "8192" in reject(message)


def test_deeply_nested_json_is_rejected_not_crashing():
    assert reject(b"[" * 30_000 + b"]" * 30_000).startswith("from robot 3")


@pytest.mark.parametrize("field, text", [
    ("telemetry.behaviour.y", '"behaviour": {"y": -1e999}'),     # a state the robot reports
    ("telemetry.extra.q", '"extra": {"q": 1e999}'),               # a field this version does not know
    ("telemetry.behaviour.y", '"behaviour": {"y": NaN}'),
])
def test_a_number_too_large_for_a_float_is_refused_like_nan(field, text):
    """1e999 is a JSON number, but Python reads it as infinity: it passed the NaN check (which saw only the
    literals NaN and Infinity), and the hub's recording then stopped on a telemetry it could not write."""
    message = ('{"v": 2, "type": "telemetry", "id": 0, "step": 1, "mode": "idle", ' + text + "}").encode()
    with pytest.raises(ProtocolError, match=f"from robot 0: {field}: -?(inf|nan) is not a JSON number"):
        decode(message, "robot 0")


def test_unknown_fields_are_ignored_for_forward_compatibility():
    decoded = decode(encode({**EXAMPLES["wheels"], "future": 1}), "robot 3")
    assert decoded["left"] == 0.1


@pytest.mark.parametrize("check, value, said", [
    ("neighbour", [1, 2.0], "frame.neighbours[0]: must be [id, range_m, bearing_rad] (got [1, 2.0])"),
    ("neighbour", [1, -0.1, 0.0], "frame.neighbours[0][1]: must be >= 0 (got -0.1)"),
    ("relayed", "x", "frame.neighbours[0]: must be [sender, sent_s, payload] (got 'x')"),
    ("relayed", [1, 0.0, []], "frame.neighbours[0][2]: must be a JSON object (got [])"),
])
def test_a_bad_neighbour_record_or_relayed_message_names_its_field(check, value, said):
    from onboard import protocol_schema

    with pytest.raises(ProtocolError) as caught:
        getattr(protocol_schema, check)(value, "frame.neighbours[0]")
    assert said in str(caught.value)
