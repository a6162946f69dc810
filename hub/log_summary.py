"""The summary ``khepri log info`` prints of a hub log, from a complete file's index or record by record.

The record walker underneath is :class:`hub.log_reader.LogReader` (still importable from here).
"""
from __future__ import annotations

import dataclasses
import math
from collections import Counter
from dataclasses import dataclass
from typing import Any, Dict, Iterable, List, Optional, Tuple, Union

from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Message

from hub.log_format import (
    CONTROL,
    HUB_DROPS,
    HUB_RUN,
    MOCAP_POSES,
    USER_METADATA,
    PathLike,
    format_version,
    is_json_channel,
    metadata_from_text,
    split_robot_topic,
    unreadable_version,
)
from hub.log_reader import LogReader, ends_with_footer, json_or_none, summary_crc_holds
from onboard.config import is_whole_number
from onboard.sorting import natural_key

RobotId = Union[int, str]

@dataclass
class LogSummary:
    """What ``khepri log info`` reports. Times are the hub clock, in seconds since 1970."""

    path: str
    file_bytes: int
    truncated: bool               # the file has no footer (a killed hub) or stops at a damaged record
    stop_reason: str              # why reading stopped early; "" for a complete file
    readable_bytes: int           # bytes up to the last complete record
    start_s: Optional[float]      # earliest message stamp (any channel's), None without messages
    end_s: Optional[float]        # latest message stamp: for a truncated file, what was recovered up to
    duration_s: float
    message_count: int            # messages of the JSON channels: what read_log yields
    topic_counts: Dict[str, int]  # topic -> messages, numbers in order (/robot/2 before /robot/10)
    robots: List[RobotId]         # ids seen in /robot/<id>/... topics, numeric ids as int, sorted
    drops: Dict[str, int]         # reason -> frames dropped (from /hub/drops)
    drops_by_sender: Dict[str, int]
    metadata: Dict[str, Any]      # the Recorder's ``metadata`` dict
    format_version: Optional[int]
    damaged_records: List[str] = dataclasses.field(default_factory=list)   # skipped: what and where
    # The simulated time (``clock_s``) of the first and last /mocap/poses record: a sil or sim-source hub's
    # log, whose wall-clock duration says nothing of how much it simulated. None without a simulated clock.
    sim_start_s: Optional[float] = None
    sim_end_s: Optional[float] = None
    # The robot ids that have a pose in the first or the last /mocap/poses record (the ids a replay of this
    # log feeds; a motion-capture-only log has no /robot topics to tell them).
    posed_robots: List[RobotId] = dataclasses.field(default_factory=list)
    # Channels that are not JSON (another tool's, e.g. protobuf in a merged file): topic -> {"encoding",
    # "messages"}. read_log and the replay skip them; they are not damage, and not in topic_counts.
    foreign_topics: Dict[str, Dict[str, Any]] = dataclasses.field(default_factory=dict)
    # Only with check_payloads (log info --check): messages of JSON channels that are not JSON objects, which
    # read_log stops at with a LogError; one line per topic. Empty otherwise, as they were not decoded.
    refused_messages: List[str] = dataclasses.field(default_factory=list)
    # The runs of the hub, in the order they started, from /hub/run: run_id, behaviour, started_s, started_by,
    # arrived_s (all waypoints reached), ended_s, ended_by, end_cause (ctl stop, signal), outcome, failures
    # and object (the sim source's progress at the end). A run the log has no end of has ended_s None.
    runs: List[Dict[str, Any]] = dataclasses.field(default_factory=list)
    # True only for a truncated file that just ends early (a killed hub); false for a complete one, and for one
    # that ends with MCAP's closing bytes where a damaged record stopped the reading (damaged since written).
    cut_short: bool = False
    # The operator's e-stops, from /control, in order: at_s, by, run_id (the run it stopped, None between runs),
    # cleared_s and cleared_by (None while latched at the log's end), resumed_s and resumed_by (the `start` that
    # resumed the run after the clear; None if it was stopped instead, or never went on).
    estops: List[Dict[str, Any]] = dataclasses.field(default_factory=list)
    # The version text of a khepri.log record whose version is not a whole number (format_version is None then,
    # as for a file with no such record, which another tool wrote); None otherwise.
    format_version_text: Optional[str] = None

    def to_dict(self) -> dict:
        """Every field, for JSON. Not ``dataclasses.asdict``, which copies every value recursively, two frames
        per level: a metadata value some 500 lists deep, which the reader parses, raised RecursionError. The
        containers are copies; the metadata's values are the summary's own."""
        data = {field.name: _copied(getattr(self, field.name)) for field in dataclasses.fields(self)}
        data["foreign_topics"] = {topic: dict(row) for topic, row in self.foreign_topics.items()}
        return data


def _copied(value: Any) -> Any:
    return dict(value) if isinstance(value, dict) else list(value) if isinstance(value, list) else value


@dataclass
class _Tally:
    counts: Counter = dataclasses.field(default_factory=Counter)
    drops: Counter = dataclasses.field(default_factory=Counter)
    drops_by_sender: Counter = dataclasses.field(default_factory=Counter)
    foreign: Counter = dataclasses.field(default_factory=Counter)     # non-JSON channels' topic -> messages
    foreign_encodings: Dict[str, str] = dataclasses.field(default_factory=dict)
    start_ns: Optional[int] = None
    end_ns: Optional[int] = None
    first_poses: Optional[bytes] = None    # the raw first and last /mocap/poses messages, for their clock_s
    last_poses: Optional[bytes] = None
    runs: Dict[str, Dict[str, Any]] = dataclasses.field(default_factory=dict)     # run id -> LogSummary.runs row
    commands: List[Tuple[float, str, Any]] = dataclasses.field(default_factory=list)  # (stamp, cmd, sender)

    def add_command(self, payload: Any, stamp_s: float) -> None:
        """One /control record: only the e-stop and what follows it (clear, the start that resumes) are kept."""
        if isinstance(payload, dict) and payload.get("ok") is True and not payload.get("nothing_done") \
                and payload.get("cmd") in ("estop", "clear", "start"):
            self.commands.append((stamp_s, payload["cmd"], payload.get("sender")))

    def add_run(self, payload: Any, stamp_s: float) -> None:
        """One /hub/run record: a run's start, its arrival at the last waypoint, or its end."""
        if not isinstance(payload, dict) or not isinstance(payload.get("run_id"), str):
            return
        run = self.runs.setdefault(payload["run_id"], {
            "run_id": payload["run_id"], "behaviour": payload.get("behaviour"), "started_s": None,
            "started_by": None, "arrived_s": None, "ended_s": None, "ended_by": None, "end_cause": None,
            "end_note": None, "outcome": None, "failures": [], "object": None})
        event, by = payload.get("event"), payload.get("by")
        if event == "started":
            run.update(started_s=stamp_s, started_by=by)
        elif event in ("all waypoints reached", "ended"):
            run.update({key: payload[key] for key in ("outcome", "failures", "object") if key in payload})
            if event == "ended":
                note = payload.get("note")
                run.update(ended_s=stamp_s, ended_by=by, end_cause=payload.get("cause"),
                           end_note=note if isinstance(note, str) else None)
            else:
                run["arrived_s"] = stamp_s

    def add_poses(self, data: bytes) -> None:
        """Only kept: decoding every pose record would cost a long log's walk more than the walk."""
        if self.first_poses is None:
            self.first_poses = data
        self.last_poses = data

    def add_count(self, channel: Channel, count: int) -> None:
        """JSON channels are counted as read_log yields them; the others apart, as it skips them."""
        if is_json_channel(channel.message_encoding):
            self.counts[channel.topic] += count
        else:
            self.foreign[channel.topic] += count
            self.foreign_encodings[channel.topic] = channel.message_encoding

    def add_drops(self, payload: Any) -> None:
        if not isinstance(payload, dict):
            return
        count = payload.get("count", 1)
        count = count if isinstance(count, int) and count > 0 else 1
        self.drops[str(payload.get("reason", "unknown"))] += count
        sender = payload.get("sender")
        self.drops_by_sender["unknown" if sender is None else str(sender)] += count


def summarise(path: PathLike, *, use_index: bool = True, check_payloads: bool = False) -> LogSummary:
    """Summarise a log. A complete file is summarised from its index (fast); a truncated one by reading it all.

    ``use_index=False`` always reads every record (the two give the same summary for a complete file).
    ``check_payloads`` (``khepri log info --check``) reads every record and also decodes every JSON message,
    listing in ``refused_messages`` those that ``read_log`` refuses (not a JSON object); it costs the decoding.
    """
    reader = LogReader(path)
    if check_payloads:
        return _summary_from_records(reader, check_payloads=True)
    if use_index and ends_with_footer(reader.path, reader.file_bytes) \
            and summary_crc_holds(reader.path, reader.file_bytes):
        try:
            return _summary_from_index(reader)
        except Exception:  # noqa: BLE001 - zstd, CRC, struct, overflow, UTF-8: a damaged index, chunk or metadata
            reader = LogReader(path)   # walk the records instead, which skips what is damaged and says so
    return _summary_from_records(reader)


def _summary_from_index(reader: LogReader) -> LogSummary:
    tally = _Tally()
    with open(reader.path, "rb") as file:
        indexed = SeekingReader(file, validate_crcs=True)
        index = indexed.get_summary()
        if index is None or index.statistics is None:
            raise McapError("no statistics in the summary section")
        stats = index.statistics
        for channel_id, count in stats.channel_message_counts.items():
            if count:
                tally.add_count(index.channels[channel_id], count)
        if stats.message_count:
            tally.start_ns, tally.end_ns = stats.message_start_time, stats.message_end_time
        for _schema, _channel, message in indexed.iter_messages(topics=[HUB_DROPS], log_time_order=False):
            tally.add_drops(json_or_none(message.data))
        for _schema, _channel, message in indexed.iter_messages(topics=[HUB_RUN]):
            tally.add_run(json_or_none(message.data), message.log_time / 1e9)
        for _schema, _channel, message in indexed.iter_messages(topics=[CONTROL]):
            tally.add_command(json_or_none(message.data), message.log_time / 1e9)
        # The first and the last pose record: a chunk at each end, not the whole file.
        for reverse in (False, True):
            found = next(indexed.iter_messages(topics=[MOCAP_POSES], reverse=reverse), None)
            if found is not None:
                tally.add_poses(found[2].data)
        # A damaged metadata record raises too: the walk then reads the others and names it by its offset (this
        # loop lost them all, the khepri.log record with them, and said the log was not a khepri hub's).
        metadata = {record.name: record.metadata for record in indexed.iter_metadata()}
    reader.complete, reader.readable_bytes = True, reader.file_bytes
    return _build_summary(reader, tally, metadata)


def _summary_from_records(reader: LogReader, check_payloads: bool = False) -> LogSummary:
    tally = _Tally()
    refused = _RefusedPayloads()
    for topic, message in reader.messages():
        tally.add_count(reader.channels[message.channel_id], 1)
        if check_payloads and not reader.is_foreign(message):
            refused.check(topic, message)
        stamp = message.log_time
        if tally.start_ns is None or stamp < tally.start_ns:
            tally.start_ns = stamp
        if tally.end_ns is None or stamp > tally.end_ns:
            tally.end_ns = stamp
        if topic == HUB_DROPS:
            tally.add_drops(json_or_none(message.data))
        elif topic == MOCAP_POSES:
            tally.add_poses(message.data)
        elif topic == HUB_RUN:
            tally.add_run(json_or_none(message.data), message.log_time / 1e9)
        elif topic == CONTROL:
            tally.add_command(json_or_none(message.data), message.log_time / 1e9)
    summary = _build_summary(reader, tally, reader.metadata)
    summary.refused_messages = refused.lines()
    return summary


class _RefusedPayloads:
    """Messages of JSON channels that are not JSON objects, which read_log refuses (LogError): without this, a
    file that read_log cannot read to the end passed ``--check``. One line per topic, not one per message."""

    def __init__(self) -> None:
        self.first: Dict[str, int] = {}       # topic -> the first such message's sequence
        self.count: Counter = Counter()

    def check(self, topic: str, message: Message) -> None:
        if isinstance(json_or_none(message.data), dict):
            return
        self.first.setdefault(topic, message.sequence)
        self.count[topic] += 1

    def lines(self) -> List[str]:
        return [f"{topic}: message {sequence} is not a JSON object"
                + (f", and {self.count[topic] - 1} more on that topic" if self.count[topic] > 1 else "")
                for topic, sequence in self.first.items()]


def _build_summary(reader: LogReader, tally: _Tally, metadata: Dict[str, Dict[str, str]]) -> LogSummary:
    start_s = None if tally.start_ns is None else tally.start_ns / 1e9
    end_s = None if tally.end_ns is None else tally.end_ns / 1e9
    sim_start_s, sim_end_s = _clock_s(tally.first_poses), _clock_s(tally.last_poses)
    if sim_start_s is None or sim_end_s is None:
        sim_start_s = sim_end_s = None
    return LogSummary(
        path=str(reader.path), file_bytes=reader.file_bytes, truncated=not reader.complete,
        stop_reason="" if reader.complete else reader.stop_reason, readable_bytes=reader.readable_bytes,
        start_s=start_s, end_s=end_s, duration_s=(end_s - start_s) if start_s is not None else 0.0,
        message_count=sum(tally.counts.values()),
        topic_counts=dict(sorted(tally.counts.items(), key=lambda item: natural_key(item[0]))),
        robots=_robot_ids(tally.counts), drops=dict(sorted(tally.drops.items())),
        drops_by_sender=dict(sorted(tally.drops_by_sender.items())),
        metadata=metadata_from_text(metadata.get(USER_METADATA, {})),
        format_version=format_version(metadata), format_version_text=unreadable_version(metadata),
        damaged_records=list(reader.damaged),
        sim_start_s=sim_start_s, sim_end_s=sim_end_s, posed_robots=_posed_ids(tally.first_poses, tally.last_poses),
        foreign_topics={topic: {"encoding": tally.foreign_encodings[topic], "messages": count}
                        for topic, count in sorted(tally.foreign.items(), key=lambda item: natural_key(item[0]))},
        runs=list(tally.runs.values()), cut_short=not reader.complete and reader.cut_short,
        estops=_estops(sorted(tally.commands, key=lambda command: command[0]), list(tally.runs.values())))


def _estops(commands: List[Tuple[float, str, Any]], runs: List[Dict[str, Any]]) -> List[Dict[str, Any]]:
    """Each e-stop with its clear and the start that resumed its run, from the /control records in time order.
    A log's reader otherwise had to find them in /control by hand to learn why a run stood still for a minute."""
    estops: List[Dict[str, Any]] = []
    for stamp_s, cmd, sender in commands:
        latest = estops[-1] if estops else None
        if cmd == "estop" and (latest is None or latest["cleared_s"] is not None):   # a repeat while latched: one
            estops.append({"at_s": stamp_s, "by": sender, "run_id": _run_at(runs, stamp_s), "cleared_s": None,
                           "cleared_by": None, "resumed_s": None, "resumed_by": None})
        elif cmd == "clear" and latest is not None and latest["cleared_s"] is None:
            latest.update(cleared_s=stamp_s, cleared_by=sender)
        elif cmd == "start" and latest is not None and latest["cleared_s"] is not None \
                and latest["resumed_s"] is None and latest["run_id"] is not None \
                and _run_at(runs, stamp_s) == latest["run_id"]:
            latest.update(resumed_s=stamp_s, resumed_by=sender)
    return estops


def _run_at(runs: List[Dict[str, Any]], stamp_s: float) -> Optional[str]:
    """The run going at that moment (started, and not yet ended), by its /hub/run records."""
    for run in runs:
        started, ended = run.get("started_s"), run.get("ended_s")
        if started is not None and started <= stamp_s and (ended is None or stamp_s <= ended):
            return run["run_id"]
    return None


def _clock_s(poses: Optional[bytes]) -> Optional[float]:
    """A /mocap/poses record's simulated time; None for motion capture (null) or a record that has none."""
    payload = json_or_none(poses) if poses is not None else None
    clock = payload.get("clock_s") if isinstance(payload, dict) else None
    if isinstance(clock, (int, float)) and not isinstance(clock, bool) and math.isfinite(clock):
        return float(clock)
    return None


def _posed_ids(*records: Optional[bytes]) -> List[RobotId]:
    """The body ids of these /mocap/poses records (a damaged one counts for none)."""
    ids = set()
    for record in records:
        payload = json_or_none(record) if record is not None else None
        bodies = payload.get("bodies") if isinstance(payload, dict) else None
        if isinstance(bodies, dict):
            ids.update(str(body) for body in bodies)
    typed = [int(robot) if is_whole_number(robot) else robot for robot in ids]
    return sorted(typed, key=lambda robot: (isinstance(robot, str), robot))


def _robot_ids(topics: Iterable[str]) -> List[RobotId]:
    ids = {split_robot_topic(topic)[0] for topic in topics if split_robot_topic(topic)}
    typed = [int(robot) if is_whole_number(robot) else robot for robot in ids]
    return sorted(typed, key=lambda robot: (isinstance(robot, str), robot))
