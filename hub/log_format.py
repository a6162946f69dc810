"""The khepri log format as its writer and its reader share it: names, topics, schemas, metadata and records.

docs/recording.md documents the format for users. :mod:`hub.recording` writes it (and is where users import
from); :mod:`hub.log_reader` reads it and :mod:`hub.log_summary` summarises it. They take their vocabulary from
here, so the writer and the readers do not import each other's machinery.

- One MCAP channel per topic, message encoding ``json`` (compact UTF-8 JSON objects, :data:`compact_json`), and
  a ``jsonschema`` schema per kind of topic (all ``/robot/<id>/frame`` channels share one schema).
- Two metadata records: :data:`FORMAT_METADATA` (format name and version) and :data:`USER_METADATA` (the
  Recorder's ``metadata`` dict, each value stored as JSON text).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Optional, Tuple, Union

from onboard.config import ConfigError, is_whole_number
from onboard.jsontext import parse_json

LOG_FORMAT_VERSION = 1
LIBRARY = f"khepri-recorder/{LOG_FORMAT_VERSION}"
FORMAT_METADATA = "khepri.log"      # MCAP metadata record: format name and version
USER_METADATA = "khepri.metadata"   # MCAP metadata record: the Recorder's ``metadata`` dict, values as JSON text
MCAP_MAGIC = b"\x89MCAP0\r\n"

MOCAP_POSES = "/mocap/poses"
CONTROL = "/control"
HUB_DROPS = "/hub/drops"
HUB_STATUS = "/hub/status"
HUB_RUN = "/hub/run"
HUB_LOG = "/hub/log"         # the hub's console lines (hub/console.py)
ROBOT_TOPIC_KINDS = ("frame", "broadcast", "relay", "telemetry", "command", "wheels")

PathLike = Union[str, Path]


class LogError(ConfigError):
    """A log cannot be written or read. ``str(err)`` is one line naming the file or the topic."""


class LogExistsError(LogError):
    """The log file to write exists already: the hub never writes over a log."""


class ForeignChannelWarning(UserWarning):
    """A log's channel whose messages are not JSON (protobuf, ros2msg, ... : another tool wrote it, or merged it
    into a hub's log): readers skip it, and say so once per channel."""


JSON_ENCODING = "json"      # the MCAP message encoding of every channel the hub writes


def is_json_channel(message_encoding: str) -> bool:
    """Whether a channel's messages are JSON, which is all that :func:`hub.recording.read_log` decodes."""
    return message_encoding.lower() == JSON_ENCODING


def robot_topic(robot_id: Any, kind: str) -> str:
    """``/robot/<id>/<kind>``, e.g. ``robot_topic(3, "frame") == "/robot/3/frame"``."""
    return f"/robot/{robot_id}/{kind}"


def split_robot_topic(topic: str) -> Optional[Tuple[str, str]]:
    """``(id, kind)`` for a ``/robot/<id>/<kind>`` topic, else None."""
    parts = topic.split("/")
    if len(parts) == 4 and parts[0] == "" and parts[1] == "robot" and parts[2] and parts[3]:
        return parts[2], parts[3]
    return None


def _object_schema(title: str, description: str, properties: Optional[dict] = None,
                   required: Tuple[str, ...] = ()) -> dict:
    # Loose on purpose: the hub and agent own the fields; the schema names them for Foxglove's panels.
    schema: Dict[str, Any] = {"title": title, "description": description, "type": "object"}
    if properties:
        schema["properties"] = properties
    if required:
        schema["required"] = list(required)
    return schema


_POSE7 = {"type": "array", "items": {"type": "number"}, "minItems": 7, "maxItems": 7,
          "description": "[x, y, z, qx, qy, qz, qw] in the motion-capture world frame (m)"}

# Schema name -> JSON schema. Topic kinds map onto these in schema_name_for.
SCHEMAS: Dict[str, dict] = {
    "khepri.MocapPoses": _object_schema(
        "khepri.MocapPoses", "One motion-capture frame, as the hub's robots' poses.",
        {"bodies": {"type": "object", "additionalProperties": _POSE7,
                    "description": "robot id (as text) -> [x, y, z, qx, qy, qz, qw], world frame, z up"},
         "clock_s": {"type": ["number", "null"], "description": "simulated time, with the sim source"}}),
    "khepri.RobotFrame": _object_schema("khepri.RobotFrame", "The downlink frame the hub sent to one robot."),
    "khepri.RobotBroadcast": _object_schema("khepri.RobotBroadcast", "A radio message one robot sent (uplink)."),
    "khepri.RobotRelay": _object_schema("khepri.RobotRelay", "Which robots one robot's broadcast was relayed to.",
                                        {"receivers": {"type": "array", "items": {"type": "integer"}}}),
    "khepri.RobotWheels": _object_schema("khepri.RobotWheels", "Wheel speeds one robot asked the sim source for."),
    "khepri.RobotTelemetry": _object_schema("khepri.RobotTelemetry", "Telemetry one robot reported."),
    "khepri.RobotCommand": _object_schema("khepri.RobotCommand", "An operator or safety command sent to one robot."),
    "khepri.Control": _object_schema("khepri.Control", "An operator request to the hub, or the hub's reply."),
    "khepri.HubDrops": _object_schema(
        "khepri.HubDrops", "Frames the hub dropped with one reason from one sender, since the previous record.",
        {"reason": {"type": "string"}, "sender": {"type": ["string", "null"]},
         "count": {"type": "integer", "minimum": 1}},
        required=("reason", "count")),
    "khepri.HubStatus": _object_schema("khepri.HubStatus", "Periodic hub statistics."),
    "khepri.HubRun": _object_schema(
        "khepri.HubRun", "A run started, reached its last waypoint, or ended; with the sim source, the object's "
                         "progress and the outcome.",
        {"run_id": {"type": "string"}, "event": {"enum": ["started", "all waypoints reached", "ended"]},
         "cause": {"type": "string"}, "by": {"type": "string"},
         "note": {"type": "string", "description": "why it was ended, when the one who ended it says"}},
        required=("run_id", "event")),
    # Foxglove's own log message (its Log panel shows these): the hub's console, line by line.
    "foxglove.Log": _object_schema(
        "foxglove.Log", "A line the hub printed on its console.",
        {"timestamp": {"type": "object", "properties": {"sec": {"type": "integer", "minimum": 0},
                                                        "nsec": {"type": "integer", "minimum": 0}}},
         "level": {"type": "integer", "description": "1 debug, 2 info, 3 warning, 4 error, 5 fatal"},
         "message": {"type": "string"}, "name": {"type": "string"}, "file": {"type": "string"},
         "line": {"type": "integer", "minimum": 0}},
        required=("timestamp", "level", "message", "name", "file", "line")),
    "khepri.Any": _object_schema("khepri.Any", "A JSON object on a topic khepri does not define."),
}
_FIXED_TOPIC_SCHEMAS = {MOCAP_POSES: "khepri.MocapPoses", CONTROL: "khepri.Control", HUB_DROPS: "khepri.HubDrops",
                        HUB_STATUS: "khepri.HubStatus", HUB_RUN: "khepri.HubRun", HUB_LOG: "foxglove.Log"}
_ROBOT_KIND_SCHEMAS = {"frame": "khepri.RobotFrame", "broadcast": "khepri.RobotBroadcast",
                       "relay": "khepri.RobotRelay", "telemetry": "khepri.RobotTelemetry",
                       "command": "khepri.RobotCommand", "wheels": "khepri.RobotWheels"}


def schema_name_for(topic: str) -> str:
    """The name of the schema in :data:`SCHEMAS` that ``topic``'s channel is registered with."""
    if topic in _FIXED_TOPIC_SCHEMAS:
        return _FIXED_TOPIC_SCHEMAS[topic]
    robot = split_robot_topic(topic)
    if robot and robot[1] in _ROBOT_KIND_SCHEMAS:
        return _ROBOT_KIND_SCHEMAS[robot[1]]
    return "khepri.Any"


# The log's JSON: compact, UTF-8, and no NaN or infinity, which are not JSON (docs/recording.md).
_compact_utf8 = json.JSONEncoder(separators=(",", ":"), allow_nan=False, ensure_ascii=False).encode
_compact_ascii = json.JSONEncoder(separators=(",", ":"), allow_nan=False).encode


def json_bytes(value: Any) -> bytes:
    """``value`` as the log's compact UTF-8 JSON. A string with a lone surrogate (a file name read with
    ``surrogateescape``, a ``\\udcff`` received in a robot's JSON) has no UTF-8 form: that value is written with
    every non-ASCII character escaped (``"\\udcff"``), which is still JSON and reads back as the same string.
    TypeError or ValueError for what JSON cannot hold (NaN, infinity, a set, ...)."""
    text = _compact_utf8(value)
    try:
        return text.encode("utf-8")
    except UnicodeEncodeError:
        return _compact_ascii(value).encode("ascii")


def compact_json(value: Any) -> str:
    """:func:`json_bytes` as text (MCAP metadata values are strings)."""
    return json_bytes(value).decode("utf-8")


class UnrecordableMessage(LogError):
    """One message that cannot be written (not a dict, or not JSON-able); the log itself is intact and the
    recording goes on (docs/recording.md)."""


def format_version(metadata: Dict[str, Dict[str, str]]) -> Optional[int]:
    """The log format version a file's ``khepri.log`` record gives (MCAP metadata, name -> {key: text}), or None
    when it has none (another tool's file) or not a number."""
    version = metadata.get(FORMAT_METADATA, {}).get("version", "")
    return int(version) if isinstance(version, str) and is_whole_number(version) else None


def unreadable_version(metadata: Dict[str, Dict[str, str]]) -> Optional[str]:
    """The version text of a ``khepri.log`` record that has one but not a whole number (``"²"``, ``"-1"``), for
    saying so; None when the version reads, or there is no such record (another tool's file)."""
    record = metadata.get(FORMAT_METADATA)
    if record is None or format_version(metadata) is not None:
        return None
    return str(record.get("version", ""))


def newer_format(version: Optional[int]) -> Optional[str]:
    """What to say of a log written in a newer format than this khepri reads, or None."""
    if version is None or version <= LOG_FORMAT_VERSION:
        return None
    return (f"newer than the log format {LOG_FORMAT_VERSION} this khepri reads: a topic or field may mean something "
            f"else in it (read it with the khepri that wrote it)")


def metadata_as_text(metadata: dict) -> Dict[str, str]:
    """MCAP metadata maps strings to strings: store each value as JSON text so numbers and lists survive."""
    if not isinstance(metadata, dict):
        raise LogError("metadata", f"must be a dict (got {type(metadata).__name__})")
    text = {}
    for key, value in metadata.items():
        if not isinstance(key, str):
            raise LogError("metadata", f"keys must be strings (got {key!r})")
        try:
            text[key] = compact_json(value)
        except (TypeError, ValueError) as err:
            raise LogError(f"metadata.{key}", f"is not JSON-able: {err}") from None
    return text


def metadata_from_text(text: Dict[str, str]) -> Dict[str, Any]:
    """Inverse of :func:`metadata_as_text`; a value that is not JSON is kept as the string, and so is one holding
    NaN, Infinity or a number too large for a float (another tool's file): Python reads them, but printed back
    (``log info --json``) they would not be JSON."""
    values = {}
    for key, value in text.items():
        try:
            values[key] = parse_json(value, parse_constant=_refuse_constant, parse_float=_finite_float)
        except ValueError:
            values[key] = value
    return values


def _refuse_constant(name: str) -> float:
    raise ValueError(f"{name} is not JSON")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"{text} is too large for a float")
    return value


@dataclass(frozen=True)
class LogRecord:
    """One recorded message: its topic, its hub-clock stamp (s since 1970) and its decoded JSON payload."""

    topic: str
    stamp_s: float
    payload: dict
