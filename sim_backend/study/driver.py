"""Runs a study: skips finished runs, sends the rest to an executor, records every result, shows progress.

Resumable by construction: a run is done when its ``<out>/<cell>/seed-<n>/result.json`` exists (it is
written atomically). A failed run (``failed: true``) is done too, unless ``retry_failed`` asks to run it
again.
"""
from __future__ import annotations

import contextlib
import fcntl
import os
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional, Sequence, Set, TextIO, Tuple

from onboard.config import ConfigError, to_mapping

from .folder import LOCK_FILE, UNWRITABLE_KEY, load_study, read_study, write_study_json
from .grid import RunSpec, StudySpec, adopt_reordered_cells
from .text import are, counted, first_few, them
from .worker import RESULT_FILE, failed_result, read_result, write_result


@dataclass
class StudyPlan:
    to_run: List[RunSpec] = field(default_factory=list)
    finished: List[RunSpec] = field(default_factory=list)       # result.json present: skipped
    kept_failed: List[RunSpec] = field(default_factory=list)    # failed before, not retried: skipped
    other_limit: List[RunSpec] = field(default_factory=list)    # skipped, but ran with another time limit
    other_scenario: List[RunSpec] = field(default_factory=list)  # skipped, but the scenario changed since
    other_code: List[RunSpec] = field(default_factory=list)      # skipped, but the behaviour's code changed since
    other_seed: List[RunSpec] = field(default_factory=list)      # its result.json is another seed's: run again


@dataclass
class StudyOutcome:
    ran: int = 0
    failed: int = 0
    skipped: int = 0
    kept_failed: int = 0
    unwritable: Dict[str, str] = field(default_factory=dict)   # run folder -> why it has no result.json


def plan_runs(runs: List[RunSpec], out_dir: Path, retry_failed: bool = False) -> StudyPlan:
    plan = StudyPlan()
    for run in runs:
        previous = read_result(out_dir / run.run_dir)
        if previous and previous.get("seed") != run.seed:    # copied from another seed's folder: not this run
            plan.other_seed.append(run)
            previous = {}
        if not previous or (previous.get("failed") and retry_failed):
            plan.to_run.append(run)
            continue
        (plan.kept_failed if previous.get("failed") else plan.finished).append(run)
        recorded = previous.get("study") or {}
        if recorded.get("time_limit_s") != run.time_limit_s:
            plan.other_limit.append(run)
        # None: written before runs recorded it; the full fingerprint: what runs recorded before 2026-11-29
        as_run = run.scenario_sha1_as_run(study_limit=recorded.get("time_limit_s") is not None)
        if recorded.get("scenario_sha1") not in (None, as_run, run.full_scenario_sha1):
            plan.other_scenario.append(run)
        if recorded.get("behaviour_sha1") not in (None, "", run.behaviour_sha1):
            plan.other_code.append(run)
    return plan


def plan_warnings(plan: StudyPlan, out_dir: Path) -> List[str]:
    """Finished runs that are kept although they do not match what the study asks now, and results in a run's
    folder that are another seed's (run again)."""
    found = []
    if plan.other_seed:
        folders = [str(run.run_dir) for run in plan.other_seed]
        files = "1 result.json" if len(folders) == 1 else f"{len(folders)} result.json files"
        found.append(f"{files} in {out_dir} ({first_few(folders)}) "
                     f"{are(len(folders))} another seed's and will be replaced: "
                     f"{'that run runs' if len(folders) == 1 else 'those runs run'} again")
    if plan.other_limit:
        found.append(f"{counted(len(plan.other_limit), 'run')} already in {out_dir} "
                     f"ran with another time limit and {are(len(plan.other_limit))} "
                     f"kept; use another --out to run {them(len(plan.other_limit))} again")
    if plan.other_scenario:
        cells = sorted({run.cell for run in plan.other_scenario})
        found.append(f"{counted(len(plan.other_scenario), 'run')} already in {out_dir} "
                     f"ran a scenario that has changed since "
                     f"(cells {first_few(cells)}) and "
                     f"{are(len(plan.other_scenario))} kept; use another --out, or delete those cells' folders, to run "
                     f"{them(len(plan.other_scenario))} again")
    if plan.other_code:
        cells = sorted({run.cell for run in plan.other_code})
        found.append(f"{counted(len(plan.other_code), 'run')} already in {out_dir} "
                     f"ran another version of {'its' if len(plan.other_code) == 1 else 'their'} behaviour's "
                     f"code (its files changed since; cells {first_few(cells)}"
                     f") and {are(len(plan.other_code))} kept; use another --out, or delete those cells' folders, to "
                     f"run {them(len(plan.other_code))} again")
    return found


def expected_cost(run: RunSpec) -> float:
    """Robots x simulated seconds allowed: how long a run may take, roughly (a step's cost grows with the
    robots; most paper runs end well before their limit, but the 100-robot ones go on for thousands of s)."""
    data = run.scenario_data
    robots = (data.get("robots") or {}).get("count", 6)
    limit = run.time_limit_s or data.get("time_limit_s", 900.0)
    try:
        return float(robots) * float(limit)
    except (TypeError, ValueError):
        return 0.0


def longest_first(runs: List[RunSpec]) -> List[RunSpec]:
    """The runs, those that may take longest first (stable within equals), so that a pool of workers does
    not finish the short runs together and then wait for three 100-robot runs on one worker each."""
    return sorted(runs, key=expected_cost, reverse=True)


@contextlib.contextmanager
def study_lock(out_dir: Path) -> Iterator[None]:
    """Hold ``<out_dir>/study.lock`` while a study runs into ``out_dir``; ConfigError naming --out and the holder's
    pid if another process holds it. Two studies in one folder would both run every run not yet finished.

    An OS lock (flock), not a file's existence: the kernel drops it when its holder ends, however it ends
    (``kill -9`` included), so a crashed study leaves nothing to clean before the resume. The file itself stays."""
    path = out_dir / LOCK_FILE
    try:
        handle = open(path, "a+", encoding="utf-8")     # not "w": that would empty the holder's pid before we know
    except OSError as err:
        raise ConfigError("--out", f"cannot open the lock file {path}: {err.strerror or err}") from None
    with handle:
        if lock_exclusively(handle, path, out_dir):
            handle.truncate(0)
            handle.write(f"{os.getpid()}\n")
            handle.flush()
        yield     # the lock goes with the file's closing


def lock_exclusively(handle: TextIO, path: Path, out_dir: Path) -> bool:
    """Take the lock (True); ConfigError if another study holds it; False, said, on a file system without locks."""
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        raise ConfigError("--out", f"{out_dir} is in use by another study ({lock_holder_text(handle)}, "
                                   f"holding {path}): wait for it to end, or give another --out") from None
    except OSError as err:   # e.g. ENOLCK, NFS without its lock service: run unlocked, as before there were locks
        print(f"khepri: warning: --out: cannot lock {path} ({err.strerror or err}): a second study started into "
              f"{out_dir} meanwhile would not be refused", file=sys.stderr)
        return False
    return True


def lock_holder_text(handle: TextIO) -> str:
    """``pid N`` from the lock file, read by a process that did not get the lock."""
    handle.seek(0)
    pid = handle.read().strip()
    # Empty: the holder took the lock a moment ago and has not written its pid yet.
    return f"pid {pid}" if pid.isdigit() else "pid not yet written"


def run_study(spec: StudySpec, runs: List[RunSpec], out_dir: Path, executor, retry_failed: bool = False,
              command: str = "", stream: Optional[TextIO] = None) -> StudyOutcome:
    out_dir.mkdir(parents=True, exist_ok=True)
    adopt_reordered_cells(runs, out_dir)
    record_study(spec, out_dir, command, [run.run_dir for run in runs])
    plan = plan_runs(runs, out_dir, retry_failed)
    outcome = StudyOutcome(skipped=len(plan.finished), kept_failed=len(plan.kept_failed))
    stream = stream or sys.stderr
    for warning in plan_warnings(plan, out_dir):
        stream.write(f"warning: {warning}\n")
    problems = {run.run_dir: run_dir_problem(out_dir / run.run_dir) for run in plan.to_run}
    runnable = [run for run in plan.to_run if not problems[run.run_dir]]
    # A run that is not run takes no time: only the runnable ones weigh in the ETA.
    progress = StudyProgress(len(plan.to_run), stream,
                             costs={(run.cell, run.seed): expected_cost(run) for run in runnable})
    try:
        for run in plan.to_run:
            if problems[run.run_dir]:     # nothing it computed could be kept: said now, not run, the study goes on
                record_unwritable(outcome, run, problems[run.run_dir], progress)
        collect_results(executor, runnable, out_dir, outcome, progress)
    finally:
        progress.close()
        record_unwritable_runs(out_dir, [run.run_dir for run in plan.to_run], outcome.unwritable)
    return outcome


def collect_results(executor, runs: List[RunSpec], out_dir: Path, outcome: StudyOutcome,
                    progress: StudyProgress) -> None:
    """Send the runs to the executor and record each result as it comes back."""
    by_key = {(run.cell, run.seed): run for run in runs}
    versions_said: Set[Tuple[Any, str]] = set()
    for result in executor.results(longest_first(runs), str(out_dir.resolve())):
        run = by_key[(result["study"]["cell"], result["seed"])]
        warn_of_other_code(result, run, versions_said, progress)
        run_dir = out_dir / run.run_dir
        outcome.ran += 1
        try:
            if not (run_dir / RESULT_FILE).is_file():
                write_result(result, run_dir)   # the worker had no access to this folder
        except OSError as err:
            reason = f"ran, but its result could not be written and is lost ({os_error_text(err, run_dir)})"
            record_unwritable(outcome, run, reason, progress)
            continue
        outcome.failed += bool(result.get("failed"))
        progress.update(result)


def warn_of_other_code(result: Dict[str, Any], run: RunSpec, said: Set[Tuple[Any, str]],
                       progress: StudyProgress) -> None:
    """Say (once per version) that a worker ran another version of the behaviour's code than this machine has:
    a Dask worker on a machine with another checkout, or a file edited while the study runs. Its result is
    kept, and report.md flags the mix."""
    theirs = (result.get("study") or {}).get("behaviour_sha1")
    ours = run.behaviour_sha1
    behaviour = run.scenario_data.get("behaviour")
    if not theirs or not ours or theirs == ours or (behaviour, theirs) in said:
        return
    said.add((behaviour, theirs))
    progress.say(f"warning: {run.run_dir} ran another version of the code of behaviour {behaviour!r} "
                 f"(behaviour_sha1 {theirs}) than this machine has ({ours}): the study mixes code versions; give "
                 f"every worker the same commit, and restart long-lived dask workers after changing the code "
                 f"(they keep what they imported)")


def run_dir_problem(run_dir: Path) -> Optional[str]:
    """Make the run's folder and remove a retried run's old result.json (so that a missing one means "the worker
    could not write it"); why the folder cannot take the run's files, or None. Checked before the run, since
    a run whose result cannot be kept is minutes of a worker for nothing."""
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / RESULT_FILE).unlink(missing_ok=True)
        handle, probe = tempfile.mkstemp(prefix=".probe-", dir=run_dir)
        os.close(handle)
        os.unlink(probe)
    except OSError as err:
        return f"not run: its folder cannot be written ({os_error_text(err, run_dir)})"
    return None


def os_error_text(err: OSError, path: Path) -> str:
    return f"{err.strerror or err}: {err.filename or path}"


def record_unwritable(outcome: StudyOutcome, run: RunSpec, reason: str, progress: StudyProgress) -> None:
    outcome.unwritable[run.run_dir] = reason
    progress.update(failed_result(run, reason))


def record_unwritable_runs(out_dir: Path, attempted: Sequence[str], unwritable: Dict[str, str]) -> None:
    """study.json ``unwritable``: the runs whose result.json could not be written, and why, for report.md and the
    exit status (they have no result.json to say it). The runs this command attempted replace their entries."""
    study = read_study(out_dir)
    if not study:
        return
    earlier = study.get(UNWRITABLE_KEY)
    earlier = earlier if isinstance(earlier, dict) else {}
    attempted_set = set(attempted)
    kept = {run_dir: why for run_dir, why in earlier.items() if run_dir not in attempted_set}
    if UNWRITABLE_KEY not in study and not unwritable:
        return       # nothing to say, nor to take back: study.json as it was
    study[UNWRITABLE_KEY] = dict(kept, **unwritable)
    write_study_json(out_dir, study)


def record_study(spec: StudySpec, out_dir: Path, command: str, run_dirs: Sequence[str] = ()) -> None:
    """study.json: the latest command's grid, every command that ran into this folder (the report quotes
    them) and every run folder they asked for (``planned``: the report counts those without a result)."""
    previous = load_study(out_dir)      # a damaged one is said, not replaced: its history would be lost
    commands = previous.get("commands", []) + ([command] if command else [])
    planned = previous.get("planned", [])
    known = set(planned)
    planned += [d for d in run_dirs if d not in known]
    data = dict(to_mapping(spec), commands=commands, planned=planned)
    if UNWRITABLE_KEY in previous:
        data[UNWRITABLE_KEY] = previous[UNWRITABLE_KEY]
    write_study_json(out_dir, data)


def outcome_text(result: Dict[str, Any]) -> str:
    """A run in a few words: FAILED and why, or whether it caged and completed."""
    if result.get("failed"):
        return f"FAILED: {result.get('error', 'unknown reason')}"
    parts = []
    if "caged" in result:
        cage = result.get("time_to_cage_s")
        parts.append(f"caged at {cage:.0f} s" if result["caged"] and cage is not None else "not caged")
    if "completed" in result:
        parts.append("completed" if result["completed"] else "not completed")
    return ", ".join(parts) or f"stopped: {result.get('stop_reason', '?')}"


def duration_text(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


class StudyProgress:
    """Runs done out of the total, failures and an ETA from the pace so far.

    ``costs`` (run key (cell, seed) -> :func:`expected_cost`) weighs the runs: after one 100-robot run the
    pace is that of 600 000 robot-seconds, not of one run in twelve. Without it every run weighs the same.
    On a terminal: one bar redrawn in place. Otherwise (a log file, a CI job): one line per finished run.
    """

    def __init__(self, total: int, stream: TextIO, clock=time.monotonic,
                 costs: Optional[Dict[Tuple[str, int], float]] = None):
        self.total = total
        self.stream = stream
        self.clock = clock
        self.started = clock()
        self.done = 0
        self.failed = 0
        self.is_terminal = stream.isatty()
        self.costs = costs or {}
        self.total_cost = sum(self.costs.values()) if costs else float(total)
        self.done_cost = 0.0

    def eta_text(self) -> str:
        if self.done == 0 or self.done_cost <= 0.0:
            return "ETA --:--:--"
        remaining = (self.clock() - self.started) / self.done_cost * max(0.0, self.total_cost - self.done_cost)
        return f"ETA {duration_text(remaining)}"

    def update(self, result: Dict[str, Any]) -> None:
        self.done += 1
        self.failed += bool(result.get("failed"))
        key = ((result.get("study") or {}).get("cell"), result.get("seed"))
        self.done_cost += self.costs.get(key, 0.0) if self.costs else 1.0
        failed = f", {self.failed} failed" if self.failed else ""
        if self.is_terminal:
            width = 30
            filled = int(width * self.done / max(self.total, 1))
            self.stream.write(f"\r[{'#' * filled}{'.' * (width - filled)}] {self.done}/{self.total} runs"
                              f"{failed} | {self.eta_text()} ")
        else:
            wall = result.get("wall_time_s")
            wall_text = f" ({wall:.1f} s wall)" if isinstance(wall, (int, float)) else ""
            self.stream.write(f"[{self.done}/{self.total}] {result['study']['cell']} seed {result['seed']}: "
                              f"{outcome_text(result)}{wall_text}{failed} | {self.eta_text()}\n")
        self.stream.flush()

    def say(self, line: str) -> None:
        """A line of its own between progress updates (on a terminal, below the bar, which is redrawn next)."""
        self.stream.write(("\n" if self.is_terminal and self.done else "") + line + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.is_terminal and self.done:
            self.stream.write("\n")
            self.stream.flush()
