"""Hub recordings: every frame in and out, written to an MCAP file that Foxglove opens and a killed hub leaves readable.

The format is documented for users in docs/recording.md and named in :mod:`hub.log_format`. This module is
where users import from: :class:`Recorder` writes logs, and the replay source, the replay tool and the live
viewer read them through :func:`read_log` (or :class:`~hub.log_reader.LogReader`). The hub's loop records
through :class:`~hub.background_recorder.BackgroundRecorder`, which wraps a Recorder.

- ``log_time`` = ``publish_time`` = the hub clock (``time.time()``) in nanoseconds; ``sequence`` = write order.
- Chunks are zstd-compressed and closed at least every ``flush_period_s / 2`` by a timer thread, and the file is
  flushed then, so a SIGKILLed hub loses at most about ``flush_period_s`` of messages.
- A killed hub leaves no summary section or footer; the reader walks the file record by record and stops cleanly
  at the first record the file cuts short.
"""
from __future__ import annotations

import io
import json
import threading
import time
from pathlib import Path
from typing import Any, Dict, Iterable, Iterator, Optional, Tuple

from mcap.writer import CompressionType, Writer

from .background_recorder import BackgroundRecorder
from .log_format import (
    CONTROL,
    FORMAT_METADATA,
    HUB_DROPS,
    HUB_LOG,
    HUB_RUN,
    HUB_STATUS,
    LIBRARY,
    LOG_FORMAT_VERSION,
    MCAP_MAGIC,
    MOCAP_POSES,
    ROBOT_TOPIC_KINDS,
    SCHEMAS,
    USER_METADATA,
    ForeignChannelWarning,
    LogError,
    LogExistsError,
    LogRecord,
    PathLike,
    UnrecordableMessage,
    json_bytes,
    metadata_as_text,
    metadata_from_text,
    robot_topic,
    schema_name_for,
    split_robot_topic,
)
from .log_reader import LogReader
from .log_summary import LogSummary
from .log_summary import summarise as summarise_log

# Users import recording from here (docs/recording.md): besides its own Recorder, read_log and summarise, this
# module offers the format's names (hub.log_format) and the BackgroundRecorder, which live in modules of their own.
__all__ = [
    "CONTROL", "FORMAT_METADATA", "HUB_DROPS", "HUB_LOG", "HUB_RUN", "HUB_STATUS", "LIBRARY", "LOG_FORMAT_VERSION",
    "MCAP_MAGIC", "MOCAP_POSES", "ROBOT_TOPIC_KINDS", "SCHEMAS", "USER_METADATA", "BackgroundRecorder",
    "ForeignChannelWarning", "LogError", "LogRecord", "PathLike", "Recorder", "UnrecordableMessage",
    "metadata_from_text", "read_log", "robot_topic", "split_robot_topic", "summarise",
]

# Stamps are wall-clock seconds (time.time()). Before 2001 means a monotonic or simulated clock slipped in, which
# would silently scramble durations and the order of topics; after 2540 overflows MCAP's 64-bit nanoseconds.
_MIN_STAMP_S, _MAX_STAMP_S = 1e9, 1.8e10


class Recorder:
    """Write hub traffic to an MCAP log.

    ``write()`` and ``count_drop()`` are meant to be called from one thread (the hub's loop). A timer thread closes
    the open chunk every ``flush_period_s / 2`` under a lock, so calls never interleave with a flush.
    """

    def __init__(self, path: PathLike, *, flush_period_s: float = 1.0, metadata: Optional[dict] = None,
                 chunk_size: int = 4 * 1024 * 1024, exclusive: bool = False):
        """``exclusive``: refuse a file that exists (the hub's logs) instead of writing over it."""
        if not flush_period_s > 0:
            raise LogError("flush_period_s", f"must be > 0 (got {flush_period_s!r})")
        user_metadata = metadata_as_text(metadata or {})
        self.path = Path(path)
        try:
            self._file = open(self.path, "xb" if exclusive else "wb")  # noqa: SIM115 - closed in close()
        except FileExistsError:
            raise LogExistsError(str(self.path), "exists: the log is not written over") from None
        except OSError as err:
            raise LogError(str(self.path), f"cannot create the log: {err.strerror or err}") from None
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        try:
            self._writer.start(profile="", library=LIBRARY)
            self._writer.add_metadata(FORMAT_METADATA, {"format": "khepri-log", "version": str(LOG_FORMAT_VERSION)})
            self._writer.add_metadata(USER_METADATA, user_metadata)
            self._file.flush()
        except OSError as err:
            _close_quietly(self._file)
            raise LogError(str(self.path), f"cannot write the log: {err.strerror or err}") from None
        self._channels: Dict[str, int] = {}
        self._schemas: Dict[str, int] = {}
        self._drops: Dict[Tuple[str, Optional[str]], Tuple[int, int]] = {}   # -> (count, latest stamp ns)
        self._sequence = 0
        self._unflushed = False
        self._refusal: Optional[str] = None   # why writes are refused: closed, or a write to the file failed
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._flush_period_s = float(flush_period_s)
        self._flusher = threading.Thread(target=self._flush_periodically, name="khepri-recorder-flush", daemon=True)
        self._flusher.start()

    def write(self, topic: str, payload: dict, stamp_s: Optional[float] = None) -> None:
        """Record ``payload`` (a JSON-able dict) on ``topic`` at ``stamp_s`` (hub clock; now if None)."""
        channel_id = self._channels.get(topic) or self._register(topic)
        if not isinstance(payload, dict):
            raise UnrecordableMessage(topic, f"payload must be a dict (got {type(payload).__name__})")
        try:
            data = json_bytes(payload)
        except (TypeError, ValueError) as err:
            # Raised before anything reaches the writer, so the file stays intact.
            raise UnrecordableMessage(topic, f"payload is not JSON-able: {err}") from None
        stamp_ns = _stamp_ns(topic, stamp_s)
        with self._lock:
            if self._refusal:
                raise LogError(str(self.path), self._refusal)
            try:   # add_message writes to the file itself when the chunk reaches chunk_size
                self._writer.add_message(channel_id, stamp_ns, data, stamp_ns, self._sequence)
            except OSError as err:
                raise self._failed(err) from None
            self._sequence = (self._sequence + 1) & 0xFFFFFFFF
            self._unflushed = True

    def count_drop(self, reason: str, sender: Optional[str] = None, stamp_s: Optional[float] = None) -> None:
        """Count one frame the hub dropped at ``stamp_s`` (hub clock; now if None).

        Counts go to ``/hub/drops`` at each flush: one record per (reason, sender), stamped with the latest drop.
        """
        if HUB_DROPS not in self._channels:
            self._register(HUB_DROPS)
        key = (str(reason), None if sender is None else str(sender))
        stamp_ns = _stamp_ns(HUB_DROPS, stamp_s)
        with self._lock:
            if self._refusal:
                raise LogError(str(self.path), self._refusal)
            count, latest_ns = self._drops.get(key, (0, stamp_ns))
            self._drops[key] = (count + 1, max(latest_ns, stamp_ns))
            self._unflushed = True

    def flush(self) -> None:
        """Close the open chunk and push everything to the operating system now."""
        with self._lock:
            if self._refusal:
                raise LogError(str(self.path), self._refusal)
            try:
                self._flush_locked()
            except OSError as err:
                raise self._failed(err) from None

    def close(self) -> None:
        """Flush, write the summary section and footer, and close the file. Safe to call twice."""
        with self._lock:
            if self._file.closed:
                return
            failure, self._refusal = self._refusal, "the recorder is closed"
            self._stop.set()
            try:
                if failure is None:
                    self._write_drops()
                    self._writer.finish()
                    self._file.close()
            except OSError as err:
                failure = f"cannot finish the log: {err.strerror or err}"
            finally:
                _close_quietly(self._file)
        if self._flusher is not threading.current_thread():
            self._flusher.join()
        if failure is not None:
            raise LogError(str(self.path), failure)

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def _register(self, topic: str) -> int:
        if not isinstance(topic, str) or not topic.startswith("/"):
            raise LogError("topic", f"must be a string starting with '/' (got {topic!r})")
        schema_name = schema_name_for(topic)
        with self._lock:
            if self._refusal:
                raise LogError(str(self.path), self._refusal)
            schema_id = self._schemas.get(schema_name)
            if schema_id is None:
                schema_data = json.dumps(SCHEMAS[schema_name]).encode()
                schema_id = self._writer.register_schema(schema_name, "jsonschema", schema_data)
                self._schemas[schema_name] = schema_id
            channel_id = self._writer.register_channel(topic, "json", schema_id)
        self._channels[topic] = channel_id
        return channel_id

    def _flush_periodically(self) -> None:
        while not self._stop.wait(self._flush_period_s / 2):
            with self._lock:
                if self._unflushed and not self._refusal:
                    try:
                        self._flush_locked()
                    except OSError as err:
                        self._failed(err)   # reported by the hub's next write(), flush() or close()

    def _failed(self, err: OSError) -> LogError:
        self._refusal = f"writing the log failed: {err.strerror or err}"
        return LogError(str(self.path), self._refusal)

    def _flush_locked(self) -> None:
        self._write_drops()
        self._writer.flush()   # closes the chunk, writes it and its indexes, flushes the file object
        self._unflushed = False

    def _write_drops(self) -> None:
        if not self._drops:
            return
        channel_id = self._channels[HUB_DROPS]   # registered by count_drop
        for (reason, sender), (count, stamp_ns) in sorted(self._drops.items(), key=_drop_order):
            data = json_bytes({"reason": reason, "sender": sender, "count": count})
            self._writer.add_message(channel_id, stamp_ns, data, stamp_ns, self._sequence)
            self._sequence = (self._sequence + 1) & 0xFFFFFFFF
        self._drops.clear()

def _stamp_ns(where: str, stamp_s: Optional[float]) -> int:
    if stamp_s is None:
        return int(time.time() * 1e9)
    try:
        if _MIN_STAMP_S <= stamp_s < _MAX_STAMP_S:   # False for NaN
            return int(stamp_s * 1e9)
    except TypeError:
        pass
    raise LogError(where, f"stamp_s must be wall-clock seconds since 1970, as time.time() gives (got {stamp_s!r})")


def _close_quietly(file: io.BufferedWriter) -> None:
    """Close after a write error: closing flushes the buffer again, which fails the same way."""
    try:
        file.close()
    except OSError:
        pass


def _drop_order(item: Tuple[Tuple[str, Optional[str]], Tuple[int, int]]) -> Tuple[int, str, str]:
    (reason, sender), (_count, stamp_ns) = item
    return stamp_ns, reason, sender or ""


def read_log(path: PathLike, topics: Optional[Iterable[str]] = None) -> Iterator[LogRecord]:
    """The messages of a log in the order the hub wrote them, optionally only those on ``topics``.

    A truncated file (a killed hub) yields every message up to the first record the file cuts short. Missing,
    empty and non-MCAP files raise :class:`LogError` at once, before iteration. A channel that is not JSON
    (another tool's protobuf or ros2msg) is skipped, with one :class:`ForeignChannelWarning` per channel.
    """
    return LogReader(path).records(topics)


def summarise(path: PathLike, **options: Any) -> LogSummary:
    """A :class:`hub.log_summary.LogSummary` of the log at ``path`` (see that module)."""
    return summarise_log(path, **options)


def _measure_write_rate(robots: int = 100, frames: int = 120) -> None:
    """``python -m hub.recording``: write one second of a 100-robot, 120 Hz lab and print messages/s."""
    import tempfile

    frame = {"t": 0.0, "pose": [1.234, -0.567, 0.891, 0.0], "neighbours": [[j, 0.5, 0.1, 0.0] for j in range(10)],
             "messages": [{"sender": 3, "payload": {"state": "push", "task": 12}, "sent_s": 1.0}]}
    poses = {"bodies": {f"kh{i}": [1.0, 2.0, 0.05, 0.0, 0.0, 0.3, 0.95] for i in range(robots)}}
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "bench.mcap"
        started = time.perf_counter()
        with Recorder(path) as recorder:
            for _ in range(frames):
                recorder.write(MOCAP_POSES, poses)
                for robot in range(robots):
                    recorder.write(robot_topic(robot, "frame"), frame)
        seconds = time.perf_counter() - started
        count = frames * (robots + 1)
        print(f"{count} messages in {seconds:.3f} s: {count / seconds:,.0f} messages/s, "
              f"{path.stat().st_size / 1e6:.2f} MB on disk")


if __name__ == "__main__":
    _measure_write_rate()
