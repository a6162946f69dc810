"""Reading hub logs back record by record: a walker that survives a killed hub's file and a damaged record.

Use :func:`hub.recording.read_log` for decoded messages; :class:`LogReader` is the machinery behind it, and
behind the summary ``khepri log info`` prints (:mod:`hub.log_summary`).
"""
from __future__ import annotations

import io
import struct
import warnings
import zlib
from pathlib import Path
from typing import Any, Dict, Iterable, Iterator, List, Optional, Tuple

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk

from hub.log_format import (
    MCAP_MAGIC,
    ForeignChannelWarning,
    LogError,
    LogRecord,
    PathLike,
    is_json_channel,
)
from onboard.jsontext import parse_json

FOOTER_RECORD_BYTES = 1 + 8 + 20   # opcode, length, summary_start, summary_offset_start, summary_crc


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
        self.cut_short = True              # when not complete: cut short (a killed hub), or else damaged
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
        for topic, message in self.json_messages(topics):
            yield LogRecord(topic, message.log_time / 1e9, self._decode(topic, message))

    def json_messages(self, topics: Optional[Iterable[str]] = None, *, warn: bool = True
                      ) -> Iterator[Tuple[str, Message]]:
        """``messages()`` of the JSON channels on ``topics`` (all when None), undecoded. A foreign channel's are
        skipped and it goes into ``foreign``, said once with a ForeignChannelWarning unless ``warn`` is False (a
        caller that refuses the file with its own error, as the replay does)."""
        wanted = None if topics is None else {topics} if isinstance(topics, str) else set(topics)
        for topic, message in self.messages():
            if wanted is not None and topic not in wanted:
                continue
            if self.is_foreign(message):
                self._note_foreign(topic, self.channels[message.channel_id].message_encoding, warn)
                continue
            yield topic, message

    def is_foreign(self, message: Message) -> bool:
        """Whether a message that ``messages()`` gave is on a channel that is not JSON."""
        return not is_json_channel(self.channels[message.channel_id].message_encoding)

    def _note_foreign(self, topic: str, encoding: str, warn: bool) -> None:
        if topic in self.foreign:
            return
        self.foreign[topic] = encoding
        if warn:
            warnings.warn(f"{self.path}: {topic}: message encoding {encoding!r}, not JSON: its messages are skipped "
                          "(a channel another tool wrote; `khepri log info` lists such channels)",
                          ForeignChannelWarning, stacklevel=4)

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
        payload = json_or_none(message.data)
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
                    if self._ends_closed(file):
                        self.cut_short = False
                        self.stop_reason = (f"a record's length or opcode is damaged at byte {offset}, and nothing "
                                            "after it could be found; the file ends with MCAP's closing bytes, so "
                                            "it was written to its end and damaged since, not cut short")
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

    def _ends_closed(self, file: Any) -> bool:
        """Whether the file's last bytes are MCAP's closing magic: a file written to its end (by a hub that
        closed it), whatever happened to the bytes before."""
        if self.file_bytes < 2 * len(MCAP_MAGIC):
            return False
        here = file.tell()
        file.seek(self.file_bytes - len(MCAP_MAGIC))
        closed = file.read(len(MCAP_MAGIC)) == MCAP_MAGIC
        file.seek(here)
        return closed

    def _index(self) -> Any:
        """A complete file's summary section (chunk offsets, channels), read once; None if it has none or it
        is damaged. Only needed to walk past damage."""
        if self._summary is None:
            self._summary = False
            if ends_with_footer(self.path, self.file_bytes) and summary_crc_holds(self.path, self.file_bytes):
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
            extra = self.file_bytes - self.readable_bytes
            if extra > 0:       # `cat a.mcap b.mcap`: b was dropped without a word, and the file passed --check
                self.damaged.append(f"{extra} bytes after the log's end at byte {self.readable_bytes}, not read "
                                    "(two logs joined with cat? each log must be a file of its own)")
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


def summary_crc_holds(path: Path, size: int) -> bool:
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


def ends_with_footer(path: Path, size: int) -> bool:
    tail_bytes = FOOTER_RECORD_BYTES + len(MCAP_MAGIC)
    if size < len(MCAP_MAGIC) + tail_bytes:
        return False
    with open(path, "rb") as file:
        file.seek(size - tail_bytes)
        tail = file.read(tail_bytes)
    return tail[0] == Opcode.FOOTER and tail[1:9] == struct.pack("<Q", 20) and tail[-8:] == MCAP_MAGIC


def json_or_none(data: bytes) -> Any:
    try:
        return parse_json(data)
    except ValueError:
        return None


def last_indexed_stamp(path: PathLike, topic: str) -> Optional[float]:
    """The stamp (s since 1970) of the last message on ``topic`` (a JSON channel), from a complete log's index, which
    takes a chunk or two to read; None for a log without a sound index (a killed hub's: only reading the whole
    file would tell) or without such a message."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if not (ends_with_footer(path, size) and summary_crc_holds(path, size)):
            return None
        with open(path, "rb") as file:
            for _schema, channel, message in SeekingReader(file).iter_messages(topics=[topic], reverse=True):
                if is_json_channel(channel.message_encoding):
                    return message.log_time / 1e9
    except Exception:  # noqa: BLE001 - a damaged index: the stamp is not known, as without one
        return None
    return None

