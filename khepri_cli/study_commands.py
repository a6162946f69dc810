"""``khepri study``: the paper's grid of runs, locally or on Dask."""
from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path
from typing import Any, List, Tuple

from onboard.config import ConfigError
from sim_backend.study.text import counted, them

from .signals import sigterm_as_ctrl_c
from .sim_commands import folder_arg

DEFAULT_REPS = 30


def add_study(groups) -> None:
    """Register the ``study`` command group."""
    study = groups.add_parser(
        "study", help="run a grid of simulations (the paper's study) and compare with the paper",
        description="Run TARGET's grid of runs (scenarios x overrides x seeds), skipping runs already in --out, "
                    "then write summary.csv, report.md and figures/. TARGET is `paper` (the paper's 9 transport "
                    "cases and 3 irregular caging cases), a study YAML file, or `report DIR` to re-aggregate a "
                    "study folder without running anything (it takes only --no-figures). See docs/study.md.")
    study.add_argument("target", help="paper | STUDY.yaml | report")
    study.add_argument("folder", nargs="?", type=Path, help="with `report`: the study folder to re-aggregate")
    study.add_argument("--reps", type=int, metavar="N",
                       help=f"seeds 1..N per cell (default {DEFAULT_REPS} for paper; a YAML file's seeds otherwise)")
    study.add_argument("--scenarios", metavar="A,B", help="run only these scenarios of the study")
    study.add_argument("--executor", metavar="KIND",
                       help="local (a process pool, default), dask (a Dask LocalCluster) or dask:ADDRESS "
                            "(an existing Dask scheduler, e.g. dask:tcp://10.0.0.5:8786)")
    study.add_argument("--workers", type=int, metavar="N", help="worker processes (default: the number of cores)")
    study.add_argument("--out", type=folder_arg, help="study folder (default out/study-<name>)")
    study.add_argument("--time-limit", type=float, metavar="S",
                       help="stop every run at S simulated seconds instead of its scenario's own time_limit_s")
    study.add_argument("--wall-limit", type=float, metavar="S",
                       help="stop any run after S seconds of wall-clock time and record it as failed (a behaviour "
                            "that hangs would otherwise hold its worker forever)")
    study.add_argument("--retry-failed", action="store_true", help="run again the runs recorded as failed")
    study.add_argument("--merge", action="store_true",
                       help="write into an --out folder that holds another study (its finished runs of the same "
                            "cells and seeds are then taken as this study's)")
    study.add_argument("--dry-run", action="store_true", help="print the grid and what is done; run nothing")
    study.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    study.set_defaults(func=cmd_study, late_positional=("folder", Path))


def cmd_study(args: argparse.Namespace) -> int:
    if args.target == "report":
        return cmd_report(args)
    if args.folder is not None:
        raise ConfigError("study", f"unexpected argument {str(args.folder)!r} (only `report` takes a folder)")
    from sim_backend.study.executors import make_executor, parse_executor, worker_count
    from sim_backend.study.folder import check_out_folder

    choice = parse_executor(args.executor or "local")     # bad --executor / --workers: said before anything else
    workers = worker_count(args.workers)
    spec, runs = study_grid(args)
    out = args.out or Path("out") / f"study-{spec.name}"
    check_out_folder(out, spec.name, merge=args.merge)
    if args.dry_run:
        check_scheduler_name(choice)
        if out.exists() and not out.is_dir():      # said as the real run would say it (a dry run makes no folder)
            raise ConfigError("--out", f"{out} is a file, not a folder")
        return print_dry_run(runs, out, args.retry_failed)
    from khepri_cli.sim_commands import require_out_folder
    from sim_backend.study.driver import study_lock

    executor = make_executor(choice, workers)
    executor.prepare()          # a Dask scheduler that cannot be reached: said before the folder is touched
    require_out_folder(out)
    # One study at a time per folder, through to its report: a second would run every unfinished run again.
    with study_lock(out):
        return run_and_report(args, spec, runs, out, executor)


def check_scheduler_name(choice) -> None:
    """``--dry-run`` reaches no scheduler, but a host name that does not exist is told all the same."""
    from sim_backend.study.dask_address import unknown_host_reason

    reason = unknown_host_reason(choice.address) if choice.address else None
    if reason is not None:
        raise ConfigError("--executor", f"cannot use the Dask scheduler {choice.address}: {reason}")


def run_and_report(args: argparse.Namespace, spec, runs, out: Path, executor) -> int:
    from sim_backend.study.driver import run_study
    from sim_backend.study.report import write_study_outputs

    print(f"study {spec.name}: {counted(len(runs), 'run')} on {executor.describe()}, writing to {out}")
    # `kill` (SIGTERM) ends a study like Ctrl-C: workers stopped, finished runs kept, resumable. Without
    # this the driver died alone and its pool's workers ran on, orphaned, until their runs finished.
    with sigterm_as_ctrl_c():
        outcome = run_study(spec, runs, out, executor, retry_failed=args.retry_failed, command=command_line(args))
    print(f"ran {counted(outcome.ran, 'run')} ({outcome.failed} failed), skipped {outcome.skipped} finished"
          + (f" and {outcome.kept_failed} failed (re-run them with --retry-failed)" if outcome.kept_failed else "")
          + (f"; {len(outcome.unwritable)} could not write their result" if outcome.unwritable else ""))
    return print_outputs(write_study_outputs(out, figures=not args.no_figures))


def study_file_path(target: str) -> Path:
    """TARGET when it names a study file; else what it is instead, said (a typo in the name is the usual one)."""
    path = Path(target)
    if path.is_file():
        return path
    if path.is_dir():
        raise ConfigError("study", f"{target} is a folder: give `paper`, a study YAML file, or `report {target}` "
                                   "to re-aggregate a study folder")
    if path.suffix in (".yaml", ".yml") or os.sep in target or "/" in target:
        raise ConfigError("study", f"no such file: {target}")
    raise ConfigError("study", f"{target!r} is not `paper`, `report` or a study file (no such file)")


# The options that run a study, which `study report` (re-aggregating, running nothing) does not take.
RUN_OPTIONS = (("--reps", "reps"), ("--scenarios", "scenarios"), ("--executor", "executor"), ("--workers", "workers"),
               ("--out", "out"), ("--time-limit", "time_limit"), ("--wall-limit", "wall_limit"),
               ("--retry-failed", "retry_failed"), ("--merge", "merge"), ("--dry-run", "dry_run"))


def given_run_options(args: argparse.Namespace) -> List[Tuple[str, Any]]:
    """The RUN_OPTIONS given, as (flag, value); a flag's value is True."""
    values = [(flag, getattr(args, name)) for flag, name in RUN_OPTIONS]
    return [(flag, value) for flag, value in values if value is not None and value is not False]


def cmd_report(args: argparse.Namespace) -> int:
    from sim_backend.study.report import write_study_outputs

    given = given_run_options(args)
    if given:       # `study report DIR --reps 5` did nothing with it, without a word
        raise ConfigError(given[0][0], "is for running a study; `khepri study report DIR` runs nothing and takes only "
                                    "--no-figures")
    folder = args.folder
    if folder is None:
        raise ConfigError("study report", "give the study folder: khepri study report DIR")
    if folder.is_file():       # said `no such folder` of a file that is there
        raise ConfigError("study report", f"{folder} is a file: give the study's folder (its --out)")
    if not folder.is_dir():
        raise ConfigError("study report", f"no such folder: {folder}")
    if not (folder / "study.json").is_file() and not any(folder.glob("*/seed-*/result.json")):
        raise ConfigError("study report", f"{folder} holds no study (no study.json, no <cell>/seed-<n>/result.json)")
    return print_outputs(write_study_outputs(folder, figures=not args.no_figures))


def study_grid(args: argparse.Namespace):
    from khepri_cli.sim_commands import check_time_limit
    from sim_backend.study.grid import expand, restrict
    from sim_backend.study.study_file import check_limit_not_overridden, check_reps, load_study_file, paper_study

    if args.reps is not None:
        check_reps("--reps", args.reps)
    check_time_limit(args.time_limit)
    check_time_limit(args.wall_limit, "--wall-limit")
    if args.target == "paper":
        spec = paper_study(args.reps or DEFAULT_REPS)
    else:
        spec = load_study_file(study_file_path(args.target), args.reps)
    if args.time_limit is not None:
        check_limit_not_overridden(spec, "--time-limit")
        spec.time_limit_s = args.time_limit
    if args.scenarios is not None:
        names = [n.strip() for n in args.scenarios.split(",") if n.strip()]
        if not names:
            raise ConfigError("--scenarios", "give scenario names separated by commas")
        spec = restrict(spec, names)
    runs = expand(spec)
    for run in runs:   # workers import what `khepri --import` imported here (a user's behaviour)
        run.imports, run.import_dir = list(getattr(args, "imports", [])), os.getcwd()
        run.wall_limit_s = args.wall_limit
    warned = set()
    for run in runs:   # once per cell, before anything runs (each run's result.json keeps them too)
        if run.cell not in warned:
            warned.add(run.cell)
            for warning in run.warnings:
                print(f"khepri: warning: {run.cell}: {warning}", file=sys.stderr)
    return spec, runs


def print_dry_run(runs, out: Path, retry_failed: bool) -> int:
    from sim_backend.study.driver import plan_runs, plan_warnings
    from sim_backend.study.grid import adopt_reordered_cells, grid_table

    adopt_reordered_cells(runs, out)
    plan = plan_runs(runs, out, retry_failed)
    for warning in plan_warnings(plan, out):
        print(f"warning: {warning}", file=sys.stderr)
    done = {(r.cell, r.seed) for r in plan.finished}
    kept = {(r.cell, r.seed) for r in plan.kept_failed}
    print(f"{counted(len(runs), 'run')}, {len(plan.to_run)} to run, {len(done)} finished, {len(kept)} failed kept; "
          f"out {out}")
    table = grid_table(runs)
    width = max([40] + [len(cell) for cell, _ in table])
    for cell, seeds in table:
        cell_runs = [r for r in runs if r.cell == cell]
        finished = sum((r.cell, r.seed) in done for r in cell_runs)
        failed = sum((r.cell, r.seed) in kept for r in cell_runs)
        limit = cell_runs[0].time_limit_s
        limit_text = f"{limit:g} s" if limit else f"{cell_runs[0].scenario_data.get('time_limit_s'):g} s (scenario)"
        print(f"  {cell:{width}s} seeds {seeds:10s} time limit {limit_text:16s} finished {finished}, failed {failed}")
    return 0


def print_outputs(files) -> int:
    from sim_backend.study.aggregate import load_results
    from sim_backend.study.driver import read_study
    from sim_backend.study.report import unwritable_runs

    for name, path in files.items():
        print(f"  {name}: {path}")
    folder = files["summary"].parent
    results = load_results(folder)
    failed = sum(len(cell.failed) for cell in results.cells)
    unwritable = len(unwritable_runs(results, read_study(folder)))
    if failed:
        print(f"khepri: {counted(failed, 'run')} failed; report.md lists why (re-run {them(failed)} with "
              f"--retry-failed)",
              file=sys.stderr)
    if unwritable:
        print(f"khepri: {counted(unwritable, 'run')} {'has' if unwritable == 1 else 'have'} no result because "
              f"{'its' if unwritable == 1 else 'their'} folder could not be written; report.md lists "
              f"{them(unwritable)} (fix the folders and run the same command again)", file=sys.stderr)
    return 1 if failed or unwritable else 0


def command_line(args: argparse.Namespace) -> str:
    """The command as it could be typed again (recorded in study.json and quoted by report.md)."""
    words = ["khepri"] + [f"--import={name}" for name in getattr(args, "imports", [])] + ["study", args.target]
    for flag, value in given_run_options(args):
        if flag == "--dry-run" or (flag == "--executor" and value == "local"):
            continue        # a dry run records nothing; the default executor goes unsaid
        words += [flag] if value is True else [flag, format(value, "g") if isinstance(value, float) else str(value)]
    return " ".join(shlex.quote(word) for word in words)
