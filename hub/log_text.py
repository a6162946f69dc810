"""The text ``khepri log info`` prints for a :class:`~hub.log_summary.LogSummary`."""
from __future__ import annotations

import dataclasses
import json
from collections import Counter
from datetime import datetime
from typing import Any, Dict, List, Optional, Tuple

from hub.log_format import newer_format, split_robot_topic
from hub.log_summary import LogSummary
from hub.run_events import outcome_text
from onboard.config import as_written
from onboard.jsontext import dump_json

#: What ``khepri log info`` prints in place of a metadata value it cannot print (see printable_metadata).
UNPRINTABLE_NOTE = "(not shown: nested too deeply to print, hundreds of levels one inside another)"
_SPARE_LEVELS = 10     # a value is checked this much deeper than it stands in the summary's JSON


def printable_metadata(summary: LogSummary, *, indent: Optional[int] = None) -> Tuple[LogSummary, List[str]]:
    """The summary with each metadata value that json cannot print (with ``indent``) replaced by
    :data:`UNPRINTABLE_NOTE`, and those fields (``metadata.<key>``). The reader keeps any value json parses,
    and json parses values nested deeper than it can print back (on Python 3.12 its encoder's limit is lower
    than its parser's): printing the summary ended in a RecursionError traceback, the rest of it lost."""
    shown: Dict[str, Any] = {}
    unprintable: List[str] = []
    for key, value in summary.metadata.items():
        wrapped = value
        for _ in range(_SPARE_LEVELS):
            wrapped = [wrapped]
        try:
            dump_json(wrapped, indent=indent)
            shown[key] = value
        except ValueError:
            shown[key] = UNPRINTABLE_NOTE
            unprintable.append(f"metadata.{key}")
    return (dataclasses.replace(summary, metadata=shown) if unprintable else summary), unprintable


def format_summary(summary: LogSummary, *, all_topics: bool = False) -> str:
    """The text ``khepri log info`` prints. Robot topics are grouped by kind unless ``all_topics``."""
    lines = [f"log:       {summary.path} ({_size(summary.file_bytes)})", f"status:    {_status(summary)}",
             f"format:    {_format_text(summary)}"]
    if summary.start_s is None:
        lines.append("messages:  none")
    else:
        lines += [f"start:     {_clock(summary.start_s)}", f"end:       {_clock(summary.end_s)}",
                  f"duration:  {summary.duration_s:.3f} s"]
        if summary.sim_start_s is not None:     # a sim-source hub (sil): duration is wall clock, this is not
            lines.append(f"simulated: {summary.sim_end_s - summary.sim_start_s:.3f} s (clock_s "
                         f"{summary.sim_start_s:.3f} to {summary.sim_end_s:.3f} s in /mocap/poses)")
    robots = ", ".join(str(robot) for robot in summary.robots) or "none"
    lines.append(f"robots:    {len(summary.robots)} ({robots})" if summary.robots else "robots:    none")
    if summary.posed_robots and summary.posed_robots != summary.robots:   # a motion-capture log: what it places
        posed = ", ".join(str(robot) for robot in summary.posed_robots)
        lines.append(f"posed:     {len(summary.posed_robots)} ({posed}) in the first and last /mocap/poses records")
    if summary.start_s is not None:
        lines.append(f"messages:  {summary.message_count}")
        rows = list(summary.topic_counts.items() if all_topics else _grouped_topic_counts(summary.topic_counts))
        if rows:            # none when every channel is foreign
            width = max(len(topic) for topic, _ in rows)
            lines += [f"  {topic:<{width}}  {count:>10}" for topic, count in rows]
    lines += _foreign_lines(summary)
    lines += [f"run:       {_run_text(run)}" for run in summary.runs]
    lines += [f"e-stop:    {_estop_text(estop)}" for estop in summary.estops[:MAX_ESTOP_LINES]]
    if len(summary.estops) > MAX_ESTOP_LINES:
        lines.append(f"e-stop:    ... {len(summary.estops) - MAX_ESTOP_LINES} more (all of them with --json)")
    lines.append(f"drops:     {_drops_text(summary)}")
    for key, value in summary.metadata.items():
        lines.append(f"metadata:  {key or '(empty key)'} = {_shortened(json.dumps(value))}")
    return "\n".join(lines)


METADATA_SHOWN_CHARS = 300     # a value written by another tool can be megabytes: the rest is in --json


def _shortened(text: str) -> str:
    if len(text) <= METADATA_SHOWN_CHARS:
        return text
    return f"{text[:METADATA_SHOWN_CHARS]}... ({len(text):,} characters; all of it with --json)"


def _format_text(summary: LogSummary) -> str:
    version, truncated = summary.format_version, summary.truncated
    if summary.format_version_text is not None:     # a khepri.log record all the same: not another tool's file
        return f"khepri-log of an unreadable version, {as_written(summary.format_version_text)} (not a whole number)"
    if version is None and truncated:      # a hub's log cut before its metadata: not a sign of another writer
        return "no khepri.log record in what was recovered"
    if version is None:
        return "no khepri.log record (not written by a khepri hub?)"
    newer = newer_format(version)
    return f"khepri-log {version}" + (f", {newer}" if newer else "")


def _foreign_lines(summary: LogSummary) -> List[str]:
    """Channels that are not JSON, which read_log and the replay skip: said, as they are not in the counts."""
    if not summary.foreign_topics:
        return []
    rows = summary.foreign_topics.items()
    width = max(len(topic) for topic in summary.foreign_topics)
    return ([f"foreign:   {len(summary.foreign_topics)} channel(s) not JSON, skipped by read_log and the replay:"]
            + [f"  {topic:<{width}}  {row['messages']:>10}  ({row['encoding'] or 'no encoding'})"
               for topic, row in rows])


def _run_text(run: Dict[str, Any]) -> str:
    """'3f2a... (transport): started 20:26:41 by operator at 127.0.0.1; ended 20:27:40 by SIGTERM: not completed
    (cage did not close); object at ...': a run as its /hub/run records tell it."""
    said = [f"started {_time(run['started_s'])}{_by(run.get('started_by'))}"] if run.get("started_s") else []
    if run.get("arrived_s"):
        said.append(f"all waypoints reached {_time(run['arrived_s'])}")
    if run.get("ended_s"):
        how = "stopped" if run.get("end_cause") == "stop" else "ended"      # else by a signal, named
        said.append(f"{how} {_time(run['ended_s'])}{_by(run.get('ended_by'))}"
                    + (f" ({_shortened(run['end_note'])})" if run.get("end_note") else ""))
    else:
        said.append("no end in the log (the hub was killed, or is still running)")
    outcome = outcome_text(run)       # a row has a /hub/run record's outcome, failures and object
    if outcome:
        said[-1] += f": {outcome}"
    return f"{run['run_id']} ({run.get('behaviour') or '?'}): {'; '.join(said)}"


MAX_ESTOP_LINES = 10


def _estop_text(estop: Dict[str, Any]) -> str:
    """'20:27:01 by alice in run 3f2a...; cleared 20:27:09 by alice; run resumed 20:27:12 by alice'."""
    run = f" in run {estop['run_id']}" if estop.get("run_id") else " (no run going)"
    said = [f"{_time(estop['at_s'])}{_by(estop.get('by'))}{run}"]
    if estop.get("cleared_s") is None:
        said.append("not cleared in the log")
    else:
        said.append(f"cleared {_time(estop['cleared_s'])}{_by(estop.get('cleared_by'))}")
        if estop.get("resumed_s") is not None:
            said.append(f"run resumed {_time(estop['resumed_s'])}{_by(estop.get('resumed_by'))}")
    return "; ".join(said)


def _by(who: Any) -> str:
    """' by operator at ...', or nothing for a record that names nobody (another tool's, or an older hub's)."""
    return f" by {who}" if who not in (None, "") else ""


def _time(stamp_s: float) -> str:
    return datetime.fromtimestamp(stamp_s).astimezone().strftime("%H:%M:%S")


def _status(summary: LogSummary) -> str:
    damaged, refused = summary.damaged_records, summary.refused_messages
    skipped = (f"; DAMAGED, skipped {len(damaged)}: {damaged[0]}" + (" ..." if len(damaged) > 1 else "")
               if damaged else "")
    skipped += (f"; read_log STOPS with an error at {refused[0]}" + (" ..." if len(refused) > 1 else "")
                if refused else "")
    if not summary.truncated:
        return "complete" + skipped
    recovered = f"recovered up to {_clock(summary.end_s)}" if summary.end_s is not None else "no message recovered"
    label = "TRUNCATED" if summary.cut_short else "DAMAGED"
    return (f"{label}, {recovered} ({summary.readable_bytes} of {summary.file_bytes} bytes): "
            f"{summary.stop_reason}{skipped}")


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
