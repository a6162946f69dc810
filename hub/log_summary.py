"""Reading hub logs back: a record walker that survives a killed hub, and the summary ``khepri log info`` prints.

Use :func:`hub.recording.read_log` for decoded messages; this module holds the machinery behind it.
"""
from __future__ import annotations

import dataclasses
import io
import json
import struct
from collections import Counter
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any, Dict, Iterable, Iterator, List, Optional, Tuple, Union

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk

from hub.log_format import (
    FORMAT_METADATA,
    HUB_DROPS,
    MCAP_MAGIC,
    USER_METADATA,
    LogError,
    LogRecord,
    PathLike,
    metadata_from_text,
    split_robot_topic,
)

FOOTER_RECORD_BYTES = 1 + 8 + 20   # opcode, length, summary_start, summary_offset_start, summary_crc
RobotId = Union[int, str]


class LogReader:
    """Walk a log record by record, tolerating a file that ends early.

    After iterating, ``complete`` says whether the file ended with a footer, ``stop_reason`` says why reading
    stopped otherwise, and ``readable_bytes`` is how much of the file was read. ``metadata`` holds the MCAP
    metadata records seen (name -> {key: text}).
    """

    def __init__(self, path: PathLike):
        self.path = Path(path)
        self.file_bytes = _check_is_mcap(self.path)
        self.complete = False
        self.stop_reason = ""
        self.readable_bytes = 0
        self.channels: Dict[int, Channel] = {}
        self.metadata: Dict[str, Dict[str, str]] = {}

    def records(self, topics: Optional[Iterable[str]] = None) -> Iterator[LogRecord]:
        wanted = None if topics is None else {topics} if isinstance(topics, str) else set(topics)
        for topic, message in self.messages():
            if wanted is None or topic in wanted:
                yield LogRecord(topic, message.log_time / 1e9, self._decode(topic, message))

    def messages(self) -> Iterator[Tuple[str, Message]]:
        """``(topic, raw MCAP message)`` pairs, without decoding the JSON (cheap, for counting)."""
        for record in self._file_records():
            if isinstance(record, Message):
                channel = self.channels.get(record.channel_id)
                if channel is None:
                    raise LogError(str(self.path), f"a message uses channel {record.channel_id}, never defined")
                yield channel.topic, record
            elif isinstance(record, Channel):
                self.channels[record.id] = record
            elif isinstance(record, Metadata):
                self.metadata[record.name] = record.metadata

    def _decode(self, topic: str, message: Message) -> dict:
        try:
            payload = json.loads(message.data)
        except ValueError:
            payload = None
        if not isinstance(payload, dict):
            raise LogError(str(self.path), f"{topic}: message {message.sequence} is not a JSON object")
        return payload

    def _file_records(self) -> Iterator[Any]:
        """Top-level records, with chunks opened; stops at the footer or at the first incomplete record."""
        with open(self.path, "rb") as file:
            offset = file.seek(len(MCAP_MAGIC))
            while True:
                self.readable_bytes = offset
                head = file.read(9)
                if not head:
                    self.stop_reason = "the file has no footer (the hub did not close it)"
                    return
                opcode, length = struct.unpack("<BQ", head) if len(head) == 9 else (0, 0)
                if len(head) < 9 or length > self.file_bytes - offset - 9:
                    self.stop_reason = f"the file ends inside a record at byte {offset}"
                    return
                if opcode == 0:   # opcode 0 is invalid in MCAP: zeros left by a crash, or garbage
                    self.stop_reason = f"unreadable bytes at byte {offset}"
                    return
                records = self._parse(opcode, file.read(length), offset)
                if records is None:
                    return
                offset += 9 + length
                if opcode == Opcode.FOOTER:
                    self._finish_at_footer(file, offset)
                    return
                self.readable_bytes = offset
                yield from records

    def _finish_at_footer(self, file: io.BufferedReader, offset: int) -> None:
        if file.read(len(MCAP_MAGIC)) == MCAP_MAGIC:
            self.complete = True
            self.readable_bytes = offset + len(MCAP_MAGIC)
        else:
            self.readable_bytes = offset
            self.stop_reason = f"the footer at byte {offset} is not followed by the MCAP magic bytes"

    def _parse(self, opcode: int, body: bytes, offset: int) -> Optional[list]:
        stream = ReadDataStream(io.BytesIO(body))
        try:
            if opcode == Opcode.CHUNK:
                return breakup_chunk(Chunk.read(stream), validate_crc=True)
            if opcode == Opcode.CHANNEL:
                return [Channel.read(stream)]
            if opcode == Opcode.SCHEMA:
                return [Schema.read(stream)]
            if opcode == Opcode.MESSAGE:
                return [Message.read(stream, len(body))]
            if opcode == Opcode.METADATA:
                return [Metadata.read(stream)]
            return []   # indexes, statistics, attachments, unknown opcodes: not needed to read messages
        except Exception as err:  # noqa: BLE001 - zstd, lz4, CRC, struct and UTF-8 errors all mean "damaged record"
            reason = str(err) or type(err).__name__      # mcap's EndOfFile has no message
            self.stop_reason = f"damaged record (opcode {opcode:#04x}) at byte {offset}: {reason}"
            return None


def _check_is_mcap(path: Path) -> int:
    """The file's size; LogError naming the file if it is missing, empty or not MCAP."""
    if path.is_dir():
        raise LogError(str(path), "is a folder, not a log file")
    if path.exists() and not path.is_file():     # a FIFO would block the open below; /dev/zero never ends
        raise LogError(str(path), "not a regular file (a log is a file the hub wrote)")
    try:
        size = path.stat().st_size
        with open(path, "rb") as file:
            head = file.read(len(MCAP_MAGIC))
    except FileNotFoundError:
        raise LogError(str(path), "no such file") from None
    except OSError as err:
        raise LogError(str(path), f"cannot read: {err.strerror or err}") from None
    if size == 0:
        raise LogError(str(path), "empty file (not an MCAP log)")
    if head != MCAP_MAGIC:
        raise LogError(str(path), "not an MCAP file (it does not start with the MCAP magic bytes)")
    return size


@dataclass
class LogSummary:
    """What ``khepri log info`` reports. Times are the hub clock, in seconds since 1970."""

    path: str
    file_bytes: int
    truncated: bool               # the file has no footer (a killed hub) or stops at a damaged record
    stop_reason: str              # why reading stopped early; "" for a complete file
    readable_bytes: int           # bytes up to the last complete record
    start_s: Optional[float]      # earliest message stamp, None without messages
    end_s: Optional[float]        # latest message stamp: for a truncated file, what was recovered up to
    duration_s: float
    message_count: int
    topic_counts: Dict[str, int]  # topic -> messages, sorted by topic
    robots: List[RobotId]         # ids seen in /robot/<id>/... topics, numeric ids as int, sorted
    drops: Dict[str, int]         # reason -> frames dropped (from /hub/drops)
    drops_by_sender: Dict[str, int]
    metadata: Dict[str, Any]      # the Recorder's ``metadata`` dict
    format_version: Optional[int]

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass
class _Tally:
    counts: Counter = dataclasses.field(default_factory=Counter)
    drops: Counter = dataclasses.field(default_factory=Counter)
    drops_by_sender: Counter = dataclasses.field(default_factory=Counter)
    start_ns: Optional[int] = None
    end_ns: Optional[int] = None

    def add_drops(self, payload: Any) -> None:
        if not isinstance(payload, dict):
            return
        count = payload.get("count", 1)
        count = count if isinstance(count, int) and count > 0 else 1
        self.drops[str(payload.get("reason", "unknown"))] += count
        sender = payload.get("sender")
        self.drops_by_sender["unknown" if sender is None else str(sender)] += count


def summarise(path: PathLike, *, use_index: bool = True) -> LogSummary:
    """Summarise a log. A complete file is summarised from its index (fast); a truncated one by reading it all.

    ``use_index=False`` always reads every record (the two give the same summary for a complete file).
    """
    reader = LogReader(path)
    if use_index and _ends_with_footer(reader.path, reader.file_bytes):
        try:
            return _summary_from_index(reader)
        except (McapError, ValueError, KeyError, struct.error):
            pass   # a damaged summary section: fall back to walking the records, which says where it breaks
    return _summary_from_records(reader)


def _ends_with_footer(path: Path, size: int) -> bool:
    tail_bytes = FOOTER_RECORD_BYTES + len(MCAP_MAGIC)
    if size < len(MCAP_MAGIC) + tail_bytes:
        return False
    with open(path, "rb") as file:
        file.seek(size - tail_bytes)
        tail = file.read(tail_bytes)
    return tail[0] == Opcode.FOOTER and tail[1:9] == struct.pack("<Q", 20) and tail[-8:] == MCAP_MAGIC


def _summary_from_index(reader: LogReader) -> LogSummary:
    tally = _Tally()
    with open(reader.path, "rb") as file:
        indexed = SeekingReader(file)
        index = indexed.get_summary()
        if index is None or index.statistics is None:
            raise McapError("no statistics in the summary section")
        stats = index.statistics
        for channel_id, count in stats.channel_message_counts.items():
            if count:
                tally.counts[index.channels[channel_id].topic] += count
        if stats.message_count:
            tally.start_ns, tally.end_ns = stats.message_start_time, stats.message_end_time
        for _schema, _channel, message in indexed.iter_messages(topics=[HUB_DROPS], log_time_order=False):
            tally.add_drops(_json_or_none(message.data))
        metadata = {record.name: record.metadata for record in indexed.iter_metadata()}
    reader.complete, reader.readable_bytes = True, reader.file_bytes
    return _build_summary(reader, tally, metadata)


def _summary_from_records(reader: LogReader) -> LogSummary:
    tally = _Tally()
    for topic, message in reader.messages():
        tally.counts[topic] += 1
        stamp = message.log_time
        if tally.start_ns is None or stamp < tally.start_ns:
            tally.start_ns = stamp
        if tally.end_ns is None or stamp > tally.end_ns:
            tally.end_ns = stamp
        if topic == HUB_DROPS:
            tally.add_drops(_json_or_none(message.data))
    return _build_summary(reader, tally, reader.metadata)


def _build_summary(reader: LogReader, tally: _Tally, metadata: Dict[str, Dict[str, str]]) -> LogSummary:
    start_s = None if tally.start_ns is None else tally.start_ns / 1e9
    end_s = None if tally.end_ns is None else tally.end_ns / 1e9
    version = metadata.get(FORMAT_METADATA, {}).get("version", "")
    return LogSummary(
        path=str(reader.path), file_bytes=reader.file_bytes, truncated=not reader.complete,
        stop_reason="" if reader.complete else reader.stop_reason, readable_bytes=reader.readable_bytes,
        start_s=start_s, end_s=end_s, duration_s=(end_s - start_s) if start_s is not None else 0.0,
        message_count=sum(tally.counts.values()), topic_counts=dict(sorted(tally.counts.items())),
        robots=_robot_ids(tally.counts), drops=dict(sorted(tally.drops.items())),
        drops_by_sender=dict(sorted(tally.drops_by_sender.items())),
        metadata=metadata_from_text(metadata.get(USER_METADATA, {})),
        format_version=int(version) if version.isdigit() else None)


def _json_or_none(data: bytes) -> Any:
    try:
        return json.loads(data)
    except ValueError:
        return None


def _robot_ids(topics: Iterable[str]) -> List[RobotId]:
    ids = {split_robot_topic(topic)[0] for topic in topics if split_robot_topic(topic)}
    typed = [int(robot) if robot.isdigit() else robot for robot in ids]
    return sorted(typed, key=lambda robot: (isinstance(robot, str), robot))


def format_summary(summary: LogSummary, *, all_topics: bool = False) -> str:
    """The text ``khepri log info`` prints. Robot topics are grouped by kind unless ``all_topics``."""
    lines = [f"log:       {summary.path} ({_size(summary.file_bytes)})", f"status:    {_status(summary)}"]
    if summary.start_s is None:
        lines.append("messages:  none")
    else:
        lines += [f"start:     {_clock(summary.start_s)}", f"end:       {_clock(summary.end_s)}",
                  f"duration:  {summary.duration_s:.3f} s"]
    robots = ", ".join(str(robot) for robot in summary.robots) or "none"
    lines.append(f"robots:    {len(summary.robots)} ({robots})" if summary.robots else "robots:    none")
    if summary.start_s is not None:
        lines.append(f"messages:  {summary.message_count}")
        rows = summary.topic_counts.items() if all_topics else _grouped_topic_counts(summary.topic_counts)
        width = max(len(topic) for topic, _ in rows)
        lines += [f"  {topic:<{width}}  {count:>10}" for topic, count in rows]
    lines.append(f"drops:     {_drops_text(summary)}")
    for key, value in summary.metadata.items():
        lines.append(f"metadata:  {key} = {json.dumps(value)}")
    return "\n".join(lines)


def _status(summary: LogSummary) -> str:
    if not summary.truncated:
        return "complete"
    until = _clock(summary.end_s) if summary.end_s is not None else "no message"
    return (f"TRUNCATED, recovered up to {until} ({summary.readable_bytes} of {summary.file_bytes} bytes): "
            f"{summary.stop_reason}")


def _grouped_topic_counts(counts: Dict[str, int]) -> List[Tuple[str, int]]:
    plain: Dict[str, int] = {}
    by_kind: Dict[str, Counter] = {}
    for topic, count in counts.items():
        robot = split_robot_topic(topic)
        if robot is None:
            plain[topic] = count
        else:
            by_kind.setdefault(robot[1], Counter())[robot[0]] += count
    rows = sorted(plain.items())
    for kind, per_robot in sorted(by_kind.items()):
        label = f"/robot/*/{kind} ({len(per_robot)} robot{'s' if len(per_robot) != 1 else ''})"
        rows.append((label, sum(per_robot.values())))
    return rows


def _drops_text(summary: LogSummary) -> str:
    if not summary.drops:
        return "none"
    reasons = ", ".join(f"{reason} {count}" for reason, count in summary.drops.items())
    return f"{sum(summary.drops.values())} ({reasons})"


def _clock(stamp_s: Optional[float]) -> str:
    return datetime.fromtimestamp(stamp_s).astimezone().isoformat(sep=" ", timespec="milliseconds")


def _size(size: int) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if size < 1000 or unit == "GB":
            return f"{size:.0f} {unit}" if unit == "B" else f"{size:.1f} {unit}"
        size /= 1000
    return f"{size} B"
