"""Reading hub logs back: a record walker that survives a killed hub, and the summary ``khepri log info`` prints.

Use :func:`hub.recording.read_log` for decoded messages; this module holds the machinery behind it.
"""
from __future__ import annotations

import dataclasses
import io
import math
import struct
import warnings
import zlib
from collections import Counter
from dataclasses import dataclass
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
    MOCAP_POSES,
    USER_METADATA,
    ForeignChannelWarning,
    LogError,
    LogRecord,
    PathLike,
    is_json_channel,
    metadata_from_text,
    split_robot_topic,
)
from onboard.jsontext import parse_json
from onboard.sorting import natural_key

FOOTER_RECORD_BYTES = 1 + 8 + 20   # opcode, length, summary_start, summary_offset_start, summary_crc
RobotId = Union[int, str]


class LogReader:
    """Walk a log record by record, tolerating a file that ends early.

    After iterating, ``complete`` says whether the file ended with a footer, ``stop_reason`` says why reading
    stopped otherwise, and ``readable_bytes`` is how much of the file was read. ``metadata`` holds the MCAP
    metadata records seen (name -> {key: text}). A damaged record whose length still fits the file (a chunk
    that fails its CRC or does not decompress, a bit flipped on disk) is skipped and said in ``damaged``: the
    records after it are read, as they are intact. ``foreign`` holds the channels whose messages are not JSON
    (topic -> message encoding: another tool's protobuf or ros2msg, say), which ``records()`` skips.
    """

    def __init__(self, path: PathLike):
        self.path = Path(path)
        self.file_bytes = _check_is_mcap(self.path)
        self.complete = False
        self.stop_reason = ""
        self.readable_bytes = 0
        self.channels: Dict[int, Channel] = {}
        self.metadata: Dict[str, Dict[str, str]] = {}
        self.damaged: List[str] = []       # what was skipped, one line each
        self.foreign: Dict[str, str] = {}  # channels records() skips, said once each: topic -> message encoding
        self._lost_channels: set = set()
        self._summary: Any = None          # the summary section, once needed: False if there is none

    def records(self, topics: Optional[Iterable[str]] = None) -> Iterator[LogRecord]:
        """The decoded messages of the JSON channels. A channel in another encoding (a foreign tool's, in a
        merged file) is skipped with one ForeignChannelWarning, not a LogError that ended the whole read:
        ``khepri log info --check`` calls such a file sound, and what it counts is what this yields."""
        wanted = None if topics is None else {topics} if isinstance(topics, str) else set(topics)
        for topic, message in self.messages():
            if wanted is not None and topic not in wanted:
                continue
            if self.is_foreign(message):
                self._say_foreign(topic, self.channels[message.channel_id].message_encoding)
                continue
            yield LogRecord(topic, message.log_time / 1e9, self._decode(topic, message))

    def is_foreign(self, message: Message) -> bool:
        """Whether a message that ``messages()`` gave is on a channel that is not JSON."""
        return not is_json_channel(self.channels[message.channel_id].message_encoding)

    def _say_foreign(self, topic: str, encoding: str) -> None:
        if topic in self.foreign:
            return
        self.foreign[topic] = encoding
        warnings.warn(f"{self.path}: {topic}: message encoding {encoding!r}, not JSON: its messages are skipped "
                      "(a channel another tool wrote; `khepri log info` lists such channels)",
                      ForeignChannelWarning, stacklevel=3)

    def messages(self) -> Iterator[Tuple[str, Message]]:
        """``(topic, raw MCAP message)`` pairs, without decoding the JSON (cheap, for counting)."""
        for record in self._file_records():
            if isinstance(record, Message):
                channel = self.channels.get(record.channel_id) or self._indexed_channel(record.channel_id)
                if channel is None:        # its channel record was damaged (skipped), or never written
                    if record.channel_id not in self._lost_channels:
                        self._lost_channels.add(record.channel_id)
                        self.damaged.append(f"messages of channel {record.channel_id}, whose channel record "
                                            "is damaged or missing")
                    continue
                yield channel.topic, record
            elif isinstance(record, Channel):
                self.channels[record.id] = record
            elif isinstance(record, Metadata):
                self.metadata[record.name] = record.metadata

    def _decode(self, topic: str, message: Message) -> dict:
        payload = _json_or_none(message.data)
        if not isinstance(payload, dict):
            raise LogError(str(self.path), f"{topic}: message {message.sequence} is not a JSON object")
        return payload

    def _file_records(self) -> Iterator[Any]:
        """Top-level records, with chunks opened; stops at the footer or at the first incomplete record."""
        if self.file_bytes < len(MCAP_MAGIC):   # _check_is_mcap let it through: a prefix of the magic
            self.stop_reason = (f"the file ends inside the MCAP magic bytes at byte {self.file_bytes} (it was cut "
                                "short as it began)")
            return
        with open(self.path, "rb") as file:
            offset = file.seek(len(MCAP_MAGIC))
            while True:
                self.readable_bytes = offset
                head = file.read(9)
                if not head:
                    self.stop_reason = "the file has no footer (the hub did not close it)"
                    return
                opcode, length = struct.unpack("<BQ", head) if len(head) == 9 else (0, 0)
                overrun = len(head) < 9 or length > self.file_bytes - offset - 9
                if overrun or opcode == 0:     # opcode 0 is invalid in MCAP: zeros left by a crash, or garbage
                    resume = self._next_chunk_after(offset)
                    if resume is not None:     # a complete file's index says where the next chunk starts
                        self.damaged.append(f"bytes {offset}-{resume} (a record's length or opcode is damaged)")
                        offset = file.seek(resume)
                        continue
                    self.stop_reason = (f"the file ends inside a record at byte {offset}" if overrun
                                        else f"unreadable bytes at byte {offset}")
                    return
                records = self._parse(opcode, file.read(length), offset)
                offset += 9 + length
                if records is None:        # damaged, but its length fits: the records after it are intact
                    continue
                if opcode == Opcode.FOOTER:
                    self._finish_at_footer(file, offset)
                    return
                self.readable_bytes = offset
                yield from records

    def _index(self) -> Any:
        """A complete file's summary section (chunk offsets, channels), read once; None if it has none or it
        is damaged. Only needed to walk past damage."""
        if self._summary is None:
            self._summary = False
            if _ends_with_footer(self.path, self.file_bytes) and _summary_crc_holds(self.path, self.file_bytes):
                try:
                    with open(self.path, "rb") as file:
                        self._summary = SeekingReader(file).get_summary() or False
                except Exception:  # noqa: BLE001 - a damaged summary: walk without it
                    self._summary = False
        return self._summary or None

    def _next_chunk_after(self, offset: int) -> Optional[int]:
        index = self._index()
        starts = sorted(c.chunk_start_offset for c in index.chunk_indexes) if index is not None else []
        return next((start for start in starts if start > offset), None)

    def _indexed_channel(self, channel_id: int) -> Optional[Channel]:
        """A channel whose own record was in a damaged chunk: the summary section repeats every channel."""
        if not self.damaged:
            return None
        index = self._index()
        channel = index.channels.get(channel_id) if index is not None else None
        if channel is not None:
            self.channels[channel_id] = channel
        return channel

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
            self.damaged.append(f"{_RECORD_NAMES.get(opcode, f'record (opcode {opcode:#04x})')} at byte {offset}: "
                                f"{reason}")
            return None


_RECORD_NAMES = {Opcode.CHUNK: "chunk", Opcode.CHANNEL: "channel record", Opcode.SCHEMA: "schema record",
                 Opcode.MESSAGE: "message", Opcode.METADATA: "metadata record"}


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
        raise LogError(str(path), "empty file (0 bytes): not even the MCAP magic bytes a hub writes as it opens a log")
    # A file shorter than the magic that starts it is a log cut short in its first bytes: truncated, read as such.
    if head != MCAP_MAGIC and not (len(head) < len(MCAP_MAGIC) and MCAP_MAGIC.startswith(head)):
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
    # Channels that are not JSON (another tool's, e.g. protobuf in a merged file): topic -> {"encoding",
    # "messages"}. read_log and the replay skip them; they are not damage, and not in topic_counts.
    foreign_topics: Dict[str, Dict[str, Any]] = dataclasses.field(default_factory=dict)
    # Only with check_payloads (log info --check): messages of JSON channels that are not JSON objects, which
    # read_log stops at with a LogError; one line per topic. Empty otherwise, as they were not decoded.
    refused_messages: List[str] = dataclasses.field(default_factory=list)

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
    if use_index and _ends_with_footer(reader.path, reader.file_bytes) \
            and _summary_crc_holds(reader.path, reader.file_bytes):
        try:
            return _summary_from_index(reader)
        except Exception:  # noqa: BLE001 - zstd, CRC, struct, overflow: a damaged index or drops chunk
            reader = LogReader(path)   # walk the records instead, which skips what is damaged and says so
    return _summary_from_records(reader)


def _summary_crc_holds(path: Path, size: int) -> bool:
    """The footer's CRC of the summary section (0: not computed) matches: its counts can be trusted."""
    with open(path, "rb") as file:
        file.seek(size - len(MCAP_MAGIC) - FOOTER_RECORD_BYTES + 9)
        summary_start, _offsets, crc = struct.unpack("<QQI", file.read(20))
        if crc == 0:
            return True
        if not len(MCAP_MAGIC) <= summary_start < size:
            return False
        file.seek(summary_start)
        covered = file.read(size - len(MCAP_MAGIC) - 4 - summary_start)
    return zlib.crc32(covered) == crc


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
            tally.add_drops(_json_or_none(message.data))
        # The first and the last pose record: a chunk at each end, not the whole file.
        for reverse in (False, True):
            found = next(indexed.iter_messages(topics=[MOCAP_POSES], reverse=reverse), None)
            if found is not None:
                tally.add_poses(found[2].data)
        try:
            metadata = {record.name: record.metadata for record in indexed.iter_metadata()}
        except Exception as err:  # noqa: BLE001 - the counts above stand without it
            metadata = {}
            reader.damaged.append(f"metadata record: {str(err) or type(err).__name__}")
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
            tally.add_drops(_json_or_none(message.data))
        elif topic == MOCAP_POSES:
            tally.add_poses(message.data)
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
        if isinstance(_json_or_none(message.data), dict):
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
    version = metadata.get(FORMAT_METADATA, {}).get("version", "")
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
        format_version=int(version) if version.isdigit() else None, damaged_records=list(reader.damaged),
        sim_start_s=sim_start_s, sim_end_s=sim_end_s,
        foreign_topics={topic: {"encoding": tally.foreign_encodings[topic], "messages": count}
                        for topic, count in sorted(tally.foreign.items(), key=lambda item: natural_key(item[0]))})


def _clock_s(poses: Optional[bytes]) -> Optional[float]:
    """A /mocap/poses record's simulated time; None for motion capture (null) or a record that has none."""
    payload = _json_or_none(poses) if poses is not None else None
    clock = payload.get("clock_s") if isinstance(payload, dict) else None
    if isinstance(clock, (int, float)) and not isinstance(clock, bool) and math.isfinite(clock):
        return float(clock)
    return None


def _json_or_none(data: bytes) -> Any:
    try:
        return parse_json(data)
    except ValueError:
        return None


def _robot_ids(topics: Iterable[str]) -> List[RobotId]:
    ids = {split_robot_topic(topic)[0] for topic in topics if split_robot_topic(topic)}
    typed = [int(robot) if robot.isdigit() else robot for robot in ids]
    return sorted(typed, key=lambda robot: (isinstance(robot, str), robot))
