"""``khepri log info FILE...``: summarise recorded MCAP logs; ``khepri log console FILE``: the hub's console lines."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from .parsing import command_group


def add_log(groups) -> None:
    """Register the ``log`` command group."""
    commands = command_group(groups, "log", "inspect hub recordings (MCAP logs)",
                             "Inspect the MCAP logs the hub records (see docs/recording.md).")
    info = commands.add_parser("info", help="summarise a log: duration, robots, message counts, drops",
                               description="Print a log's start, duration, robots, messages per topic, dropped "
                                           "frames by reason, and whether the file was cut short (a killed hub).")
    info.add_argument("files", nargs="+", metavar="FILE",
                      help="an .mcap log written by the hub (several: one summary each, logs/*.mcap)")
    info.add_argument("--json", action="store_true",
                      help="print the summary as JSON (several files: a list of them, in the order given; a file "
                           "that cannot be read is {\"path\": ..., \"error\": ...} there)")
    info.add_argument("--check", action="store_true",
                      help="read every record, check every chunk's CRC and decode every JSON message, also in a "
                           "complete log (slower; by default a complete log is summarised from its index); exit "
                           "code 1 when the log is truncated, has damaged records, or has messages read_log refuses")
    info.add_argument("--all-topics", action="store_true",
                      help="list every robot's topics (default: one line per kind, e.g. /robot/*/frame)")
    info.set_defaults(func=cmd_info)
    console = commands.add_parser("console", help="print the lines the hub printed while it recorded, with times",
                                  description="Print the hub's console lines recorded in a log (/hub/log): "
                                              "robots connecting, agents restarting, e-stops, refused keys, "
                                              "drops, each with the lab PC's date and time.")
    console.add_argument("file", metavar="FILE", help="an .mcap log written by the hub")
    console.set_defaults(func=cmd_console)


def cmd_info(args: argparse.Namespace) -> int:
    from onboard.config import ConfigError
    from onboard.console import say

    if len(args.files) == 1:
        return _info(args, args.files[0], lambda summary: print(json.dumps(summary, indent=2)))
    # Several: each file's summary, or its one error line, and on with the next (a folder's logs, one damaged).
    summaries, code = [], 0
    for number, name in enumerate(args.files):
        if number and not args.json:
            print()
        try:
            code = max(code, _info(args, name, summaries.append))
        except ConfigError as err:
            say(f"khepri: error: {err}")
            code = 2
            # One entry per file given, in order: a list without it paired the next file's summary with its name.
            summaries.append({"path": name, "error": str(err)})
    if args.json:
        print(json.dumps(summaries, indent=2))
    return code


def _info(args: argparse.Namespace, name: str, print_json) -> int:
    from hub.log_summary import summarise
    from hub.log_text import format_summary, printable_metadata
    from onboard.console import say

    # LogError (a ConfigError) naming the file for missing, empty or non-MCAP files
    summary = summarise(log_path(name), use_index=not args.check, check_payloads=args.check)
    summary, unprintable = printable_metadata(summary, indent=2 if args.json else None)
    if args.json:
        print_json(summary.to_dict())
    else:
        print(format_summary(summary, all_topics=args.all_topics))
    for field in unprintable:
        say(f"khepri: error: {field}: nested too deeply to print (hundreds of levels, one inside another); the "
            "summary shows a note in its place")
    # With --check a script can tell a sound log from a damaged one by the exit code, not only by reading.
    unsound = args.check and (summary.truncated or summary.damaged_records or summary.refused_messages)
    return 1 if unprintable or unsound else 0


def cmd_console(args: argparse.Namespace) -> int:
    """One line per /hub/log record: '2026-11-29 20:27:01.123  hub: robot 3 connected from 10.0.0.13'."""
    from datetime import datetime

    from hub.log_reader import LogReader
    from hub.recording import HUB_LOG
    from onboard.console import one_line, say

    count = 0
    reader = LogReader(log_path(args.file))         # LogError (a ConfigError) names the file
    for record in reader.records([HUB_LOG]):
        message = record.payload.get("message")
        if not isinstance(message, str):
            continue         # not a console line (another tool's /hub/log): nothing to print
        when = datetime.fromtimestamp(record.stamp_s).astimezone().strftime("%Y-%m-%d %H:%M:%S.%f")[:-3]
        print(f"{when}  {one_line(message)}")      # a line an older hub recorded unescaped, a robot's text in it
        count += 1
    damaged_end = not reader.complete and not reader.cut_short    # log info calls it DAMAGED: so is it here
    if not reader.complete:         # a killed hub's log: its last lines are not there, and the reader is told
        ends = "is damaged at its end" if damaged_end else "ends early"
        say(f"khepri: {args.file}: the log {ends} ({reader.stop_reason}): the lines printed are those "
            "recovered up to there")
    if reader.damaged:              # skipped chunks may have held console lines: said, not left to be missed
        say(f"khepri: {args.file}: damaged, {len(reader.damaged)} part(s) skipped ({reader.damaged[0]}"
            f"{'; ...' if len(reader.damaged) > 1 else ''}): console lines in them are missing "
            "(`khepri log info` lists them)")
    if not count:
        say(f"khepri: {args.file}: no console lines in this log (/hub/log: recorded by hubs since 2026-11-29)")
        return 1
    return 1 if reader.damaged or damaged_end else 0


def log_path(name: str) -> Path:
    """The log's path; an empty one is refused (Path("") is ".", which would be reported as a folder)."""
    from onboard.config import ConfigError

    if not name.strip():
        raise ConfigError("FILE", "an empty path: name the .mcap log")
    return Path(name)

