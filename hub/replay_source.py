"""The ``replay`` pose source: a recorded MCAP log's ``/mocap/poses``, paced by their stamps."""
from __future__ import annotations

import math
import time
from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np

from onboard.config import ConfigError, as_written, is_whole_number
from onboard.jsontext import parse_json
from onboard.protocol import MAX_ROBOT_ID

from .sources import PoseFrame, PoseSource, SourceRestartError, pose_from_mocap

NEVER_PLACED_SCAN_S = 3.0      # at start, how long the hub looks through the log for robots it never places


class ReplaySource(PoseSource):
    """Poses from a recorded log's ``/mocap/poses`` topic, paced by their stamps at ``rate``.

    A record that cannot be read as poses is skipped (one log line a second at most): a replay is a tool for
    looking at a run, and one damaged record must not end it. A log that holds no such record at all is not a
    hub recording, which is said at start."""

    def __init__(self, path: str, rate: float = 1.0, log: Callable[[str], None] = print):
        from hub.log_format import FORMAT_METADATA, format_version, newer_format
        from hub.log_reader import LogReader, last_indexed_stamp
        from hub.recording import MOCAP_POSES, LogError

        self.description = f"replay {path}"
        self.not_the_real_robots = "a replay's poses come from a recording"
        self.path, self.rate, self.log = path, rate, log
        try:
            self.reader = LogReader(path)
        except LogError as err:      # it names the file already: say the problem once
            raise ConfigError("source.file", f"cannot read {path}: {err.problem}") from None
        self.records = self._pose_messages()
        self.pending: Optional[Tuple[int, Any]] = None     # (position among the pose records, MCAP message)
        self.first_stamp: Optional[float] = None
        self.played_stamp: Optional[float] = None      # the log stamp of the last pose record played
        self.started_at: Optional[float] = None
        self.finished = False
        self.skipped = 0
        self._skips_unsaid = 0
        self.passed_over = 0          # frames read but overtaken by a newer one in the same poll (latest-only)
        self._last_skip_line = -math.inf
        self._fetch()
        if self.pending is None:
            damaged = self.reader.damaged
            if damaged:          # the poses were most likely in what was skipped: not a log without any
                more = f", and {len(damaged) - 1} more" if len(damaged) > 1 else ""
                raise ConfigError("source.file", f"{path} holds no /mocap/poses records that can be read: its damaged "
                                                 f"records were skipped ({len(damaged)}: {damaged[0]}{more}; "
                                                 f"`khepri log info {path}` lists them)")
            if self.reader.stop_reason:           # a hub log cut short before its first poses, not another file
                raise ConfigError("source.file", f"{path} holds no /mocap/poses records: it is truncated "
                                                 f"({self.reader.stop_reason})")
            foreign = self.reader.foreign.get(MOCAP_POSES)
            if foreign is not None:
                raise ConfigError("source.file", f"{path} holds no /mocap/poses records the replay can read: that "
                                                 f"channel's message encoding is {foreign!r}, not JSON (another "
                                                 "tool's log, not a khepri hub recording?)")
            khepri = FORMAT_METADATA in self.reader.metadata     # a khepri.log record, its version read or not
            what = ("a khepri log with no motion-capture frames: nothing to replay" if khepri
                    else "not a khepri hub recording?")
            raise ConfigError("source.file", f"{path} holds no /mocap/poses records ({what})")
        version = format_version(self.reader.metadata)      # its record comes before the first poses
        newer = newer_format(version)
        if newer:
            log(f"hub: warning: {path} is in log format {version}, {newer}")
        last = last_indexed_stamp(path, MOCAP_POSES)
        # The log time the replay spans, for `ctl status`: known from a complete log's index; not from a log cut
        # short, whose end only reading it all would find.
        self.total_s = None if last is None else max(0.0, last - self._stamp(self.pending[1]))

    @property
    def untracked(self) -> str:
        return "the replay has ended" if self.finished else "not in the log's poses now"

    @property
    def ended(self) -> bool:
        return self.finished

    @property
    def pristine(self) -> bool:
        """Whether nothing has been played yet (a new run then starts the log from its first record anyway)."""
        return self.played_stamp is None

    def restart(self, now: float) -> Optional[PoseFrame]:
        """The log from its first pose record again, for a new run (``source.reset_each_run``): agents that had
        to connect first saw the replay only from where it was by then. Its first frame, stamped ``now``."""
        from hub.log_reader import LogReader
        from hub.recording import LogError

        try:
            self.reader = LogReader(self.path)
        except LogError as err:      # the file gone or replaced since the hub started: the replay goes on
            raise SourceRestartError(f"replay: cannot start {self.path} again for the new run ({err.problem}); "
                                     "it goes on from where it was") from None
        self.records = self._pose_messages()
        self.first_stamp = self.played_stamp = self.started_at = None
        self.finished = False
        self.skipped = self._skips_unsaid = self.passed_over = 0
        self._fetch()
        frames = self.poll(now)
        return frames[-1] if frames else None

    def never_placed(self, ids: List[int], scan_s: float = NEVER_PLACED_SCAN_S) -> Tuple[List[int], Optional[float]]:
        """Those of ``ids`` that no readable ``/mocap/poses`` record of the log places (the replay would hold them
        all along), and None; or, when reading took longer than ``scan_s`` of wall time before every one was
        seen, those not placed so far and how many seconds of the log that was. Reads with a second reader only
        until every one of ``ids`` has been seen: an hour-long log of many robots, one of them never placed,
        kept the hub from listening for a minute, saying nothing. ``placed_ids`` holds the ids the records read
        did place (when some of ``ids`` are missing, every id of what was read: which ids the log has)."""
        from hub.log_reader import LogReader
        from hub.recording import MOCAP_POSES, LogError

        missing = set(ids)
        self.placed_ids: List[int] = []
        placed = set()
        deadline = time.monotonic() + scan_s
        first = last = None
        try:
            reader = LogReader(self.path)
            for count, (_topic, message) in enumerate(reader.json_messages(MOCAP_POSES, warn=False)):
                if not missing:
                    break
                first = message.log_time if first is None else first
                last = message.log_time
                if count % 256 == 255 and time.monotonic() > deadline:
                    return sorted(missing), (last - first) / 1e9
                try:
                    record_ids = poses_from_record(message.data)[0]
                except (KeyError, TypeError, ValueError, AttributeError):
                    continue     # the replay skips it too, and says so when it gets there
                missing.difference_update(record_ids)
                placed.update(record_ids)
        except LogError:             # damaged beyond what the reader walks past: what was read is the log
            pass
        finally:
            self.placed_ids = sorted(placed)
        return sorted(missing), None

    def _pose_messages(self):
        from hub.recording import MOCAP_POSES

        # Another tool's channel of that name, not the hub's poses, is skipped: __init__ refuses such a file.
        for count, (_topic, message) in enumerate(self.reader.json_messages(MOCAP_POSES, warn=False)):
            yield count, message

    def _fetch(self) -> None:
        from hub.recording import LogError

        try:
            self.pending = next(self.records)
            return
        except StopIteration:
            reason = self.reader.stop_reason if not self.reader.complete else ""
        except LogError as err:      # damaged beyond what the reader walks past: what was read is the log
            reason = err.problem
        self.pending = None
        if not self.finished and self.first_stamp is not None:
            self.finished = True
            damaged = self.reader.damaged
            if damaged:      # skipped on the way, the records after them were replayed
                reason = "; ".join(filter(None, [reason, f"{len(damaged)} damaged record(s) skipped: {damaged[0]}"]))
            if self._skips_unsaid:
                reason = "; ".join(filter(None, [reason, f"{self.skipped} unreadable pose records skipped in all"]))
            if self.passed_over:
                reason = "; ".join(filter(None, [reason, passed_over_text(self.passed_over, self.rate)]))
            self.log("hub: replay reached the end of the log" + (f" ({reason})" if reason else ""))

    def _stamp(self, message) -> float:
        return message.log_time / 1e9

    def _due_at(self) -> float:
        return self.started_at + (self._stamp(self.pending[1]) - self.first_stamp) / self.rate

    def poll(self, now: float) -> List[PoseFrame]:
        out = []
        while self.pending is not None:
            if self.first_stamp is None:
                self.first_stamp, self.started_at = self._stamp(self.pending[1]), now
            if self._due_at() > now:
                break
            frame = self._to_frame(*self.pending, now)
            if frame is not None:
                self.passed_over += 1 if out else 0   # the one before is overtaken (counted before _fetch ends)
                out.append(frame)
            self.played_stamp = self._stamp(self.pending[1])
            self._fetch()
        return out[-1:]   # latest-only: a late hub skips to the newest frame (counted, and said at the end)

    def _to_frame(self, index: int, message, now: float) -> Optional[PoseFrame]:
        try:
            ids, poses, clock_s = poses_from_record(message.data)
        except (KeyError, TypeError, ValueError, AttributeError) as err:
            self._skip(index, message, str(err) or type(err).__name__)
            return None
        return PoseFrame(now, ids, poses, clock_s=clock_s)

    def _skip(self, index: int, message, reason: str) -> None:
        self.skipped += 1
        now = time.monotonic()
        if now - self._last_skip_line < 1.0:
            self._skips_unsaid += 1
            return
        self._last_skip_line = now
        more = f" (+{self._skips_unsaid} more skipped in the last second)" if self._skips_unsaid else ""
        self._skips_unsaid = 0
        into = self._stamp(message) - self.first_stamp
        self.log(f"hub: replay: skipping /mocap/poses record {index} ({into:.3f} s into the log): {reason}{more}")

    def progress(self) -> Dict[str, Any]:
        """How far the replay has got, in log time: ``played_s`` of ``total_s`` (None for a log cut short), and
        ``percent`` of that, or for a log cut short of the file's bytes read."""
        played = 0.0 if self.played_stamp is None else self.played_stamp - self.first_stamp
        if self.finished and self.total_s is not None:
            percent = 100.0     # a whole log, played to its end
        elif self.total_s is not None:
            percent = 100.0 * played / self.total_s if self.total_s > 0 else 0.0
        else:       # a log cut short, also once ended: as far as its bytes were read (not 100 % of a file 32 % read)
            percent = 100.0 * self.reader.readable_bytes / max(1, self.reader.file_bytes)
        return {"played_s": round(played, 3), "total_s": None if self.total_s is None else round(self.total_s, 3),
                "percent": round(min(percent, 100.0), 1), "rate": self.rate, "ended": self.finished,
                "passed_over": self.passed_over}

    def next_due(self, now: float) -> float:
        if self.pending is None:
            return 0.1
        if self.first_stamp is None:
            return 0.0
        return max(0.0, self._due_at() - now)


def passed_over_text(count: int, rate: float) -> str:
    return (f"{count} pose frame{'' if count == 1 else 's'} passed over: at {rate:g}x they came faster than the "
            "hub's loop, which sends only the newest (a smaller source.rate feeds them all)")


def poses_from_record(data: bytes) -> Tuple[List[int], np.ndarray, Optional[float]]:
    """Robot ids, world poses and sim clock of one recorded ``/mocap/poses`` message (its JSON bytes):
    ``{"bodies": {"<id>": [x, y, z, qx, qy, qz, qw], ...}, "clock_s": ...}``. ValueError, KeyError or
    TypeError for anything else, whose text names the field (the replay's skip line shows it)."""
    try:
        payload = parse_json(data)
    except ValueError as err:
        raise ValueError(f"not JSON ({err})") from None
    if not isinstance(payload, dict):
        raise ValueError(f"not a JSON object but {type(payload).__name__}")
    bodies = payload.get("bodies")
    if not isinstance(bodies, dict):       # was said in Python's words: 'list' object has no attribute 'items'
        raise ValueError(f"bodies: must be a mapping of robot id to {BODY_FIELDS} (got {_short(bodies)})")
    ids, poses = [], []
    for name, value in bodies.items():
        ids.append(_robot_id(name))
        if not isinstance(value, list) or len(value) != 7 \
                or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in value):
            raise ValueError(f"bodies[{name!r}]: must be {BODY_FIELDS}, 7 numbers (got {_short(value)})")
        x, y, _z, qx, qy, qz, qw = value
        if qx * qx + qy * qy + qz * qz + qw * qw < 1e-12:     # no rotation at all: it read as yaw 0
            raise ValueError(f"bodies[{name!r}]: the quaternion [qx, qy, qz, qw] is all zeros (no orientation)")
        poses.append(pose_from_mocap((x, y, 0.0), (qw, qx, qy, qz), "z"))
    array = np.asarray(poses, dtype=float).reshape(len(ids), 3)
    if not np.isfinite(array).all():
        raise ValueError("a pose is not finite")
    clock_s = payload.get("clock_s")
    if clock_s is not None and (isinstance(clock_s, bool) or not isinstance(clock_s, (int, float))
                                or not math.isfinite(clock_s)):
        raise ValueError(f"clock_s must be a finite number (got {clock_s!r})")
    return ids, array, clock_s


BODY_FIELDS = "[x, y, z, qx, qy, qz, qw]"


def _robot_id(name: str) -> int:
    """A ``bodies`` key as the hub writes it: a robot id in decimal (int() took '-1', ' 7' and '1_0' too)."""
    if not (is_whole_number(name) and int(name) <= MAX_ROBOT_ID):
        raise ValueError(f"bodies: {as_written(name)} is not a robot id 0..{MAX_ROBOT_ID}")
    return int(name)


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."
