"""The ``khepri`` command: a thin dispatcher over the project's folders. Nothing imports this package."""
from __future__ import annotations

import argparse
import os
import sys
from typing import List, Optional

from onboard.behaviour import BehaviourError
from onboard.config import ConfigError
from onboard.drivers import DriverError
from onboard.plugins import import_user_modules

from . import lab_commands, log_commands, sim_commands, study_commands


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="khepri", description="Swarm behaviours from simulation to KheperaIV robots.")
    parser.add_argument("--import", dest="imports", action="append", default=[], metavar="MODULE",
                        help="import MODULE first: a module name (wander, for wander.py in this folder) or a "
                             ".py file's path, holding your behaviour")
    groups = parser.add_subparsers(dest="group", metavar="COMMAND", required=True)
    sim_commands.add_sim(groups)
    bench_commands = sim_commands.add_bench(groups)
    lab_commands.add_bench_hub(bench_commands)
    lab_commands.add_lab(groups)
    log_commands.add_log(groups)
    study_commands.add_study(groups)
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    try:
        return _run(argv)
    except BrokenPipeError:
        # The reader went away (`khepri sim list | head`): stop quietly, as the Python docs recommend ("Note on
        # SIGPIPE"): point stdout at /dev/null so the interpreter's final flush does not fail a second time.
        _silence_stdout()
        return 1


def _silence_stdout() -> None:
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):   # stdout without a file descriptor (e.g. captured in tests)
        pass


def _run(argv: Optional[List[str]]) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit:
        sys.stdout.flush()          # --help into a closed pipe fails here, inside main(), not at exit
        raise
    try:
        if args.imports:
            import_user_modules(args.imports)
        code = int(args.func(args) or 0)
        sys.stdout.flush()          # buffered output meets a closed pipe here, inside main(), not at exit
        return code
    except ConfigError as err:
        print(f"khepri: error: {err}", file=sys.stderr)
        return 2
    except BehaviourError as err:     # the user's behaviour raised (before a run could start, or in an agent)
        what = "the robot's driver failed" if isinstance(err.exc, DriverError) else "the behaviour failed"
        print(f"khepri: error: {what}: {err}", file=sys.stderr)
        print("\n".join(err.lines), file=sys.stderr)
        return 1
    except DriverError as err:        # an agent's robot hardware, outside any behaviour call
        print(f"khepri: error: the robot's driver failed: {err}", file=sys.stderr)
        return 1
    except OSError as err:
        # A path the user gave that cannot be read or written (--record, keys folder, a full or read-only
        # disk, ...): one line that names it. An OS error without a path is a bug: keep its traceback.
        # Set KHEPRI_DEBUG=1 for the traceback in any case.
        if os.environ.get("KHEPRI_DEBUG") or err.filename is None:
            raise
        print(f"khepri: error: {err.strerror or err}: {err.filename}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("khepri: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
