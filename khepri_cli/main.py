"""The ``khepri`` command: a thin dispatcher over the project's folders. Nothing imports this package."""
from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from typing import Any, List, Optional

from onboard.behaviour import BehaviourError
from onboard.config import ConfigError
from onboard.console import say
from onboard.drivers import DriverError
from onboard.plugins import import_user_modules
from sim_backend.evaluator_error import EvaluatorError

from . import bench_commands, lab_commands, log_commands, sim_commands, study_commands


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="khepri", description="Swarm behaviours from simulation to KheperaIV robots.")
    parser.add_argument("--import", dest="imports", action="append", default=[], metavar="MODULE",
                        help="import MODULE first: a module name (wander, for wander.py in this folder) or a "
                             ".py file's path, holding your behaviour (repeatable)")
    parser.add_argument("--version", action="version", version=f"khepri {_version()}")
    groups = parser.add_subparsers(dest="group", metavar="COMMAND", required=True)
    sim_commands.add_sim(groups)
    benches = sim_commands.add_bench(groups)
    bench_commands.add_lab_benches(benches)
    lab_commands.add_lab(groups)
    log_commands.add_log(groups)
    study_commands.add_study(groups)
    _accept_import_after_the_command(parser)
    return parser


def _version() -> str:
    """The installed package's version; a source tree run without installing it says so."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("khepri")
    except PackageNotFoundError:
        return "(not installed: run from a source tree)"


def _accept_import_after_the_command(parser: argparse.ArgumentParser) -> None:
    """``khepri sim run wander.yaml --import wander`` as well as ``khepri --import wander sim run ...``: every
    command takes ``--import`` too (``agent`` has its own, as on a robot)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for command in set(action.choices.values()):
                _accept_import_after_the_command(command)
            return
    if not any("--import" in action.option_strings for action in parser._actions):
        parser.add_argument("--import", dest="late_imports", action="append", default=[], metavar="MODULE",
                            help="as `khepri --import MODULE`")


def main(argv: Optional[List[str]] = None) -> int:
    """``argv`` None: the ``khepri`` command itself, which exits when this returns."""
    if argv is None:
        escape_unencodable_output()
        if sys.stdout is not None:
            sys.stdout = OutputNamedInErrors(sys.stdout)
    with PatientInterrupts(exiting=argv is None):
        try:
            return _run(argv)
        except BrokenPipeError:
            # The reader went away (`khepri sim list | head`): stop quietly, as the Python docs recommend ("Note
            # on SIGPIPE"): point stdout at /dev/null so the interpreter's final flush does not fail again.
            _silence_stdout()
            return 1


def escape_unencodable_output() -> None:
    """Print what the terminal's encoding cannot hold escaped (``\\udcff``), as Python's stderr already does: a
    robot's state holding a lone surrogate (a file name read with surrogateescape) ended `ctl status` with a
    UnicodeEncodeError."""
    reconfigure = getattr(sys.stdout, "reconfigure", None)
    if reconfigure is not None:
        reconfigure(errors="backslashreplace")


STANDARD_OUTPUT = "standard output"


class OutputNamedInErrors:
    """stdout, whose write errors name it: `khepri log info LOG > summary.txt` on a full disk ended in a
    traceback (an OSError without a file name is taken for a bug), and is now one line that says what failed."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except OSError as err:
            raise self._named(err) from None

    def flush(self) -> None:
        try:
            self._stream.flush()
        except OSError as err:
            raise self._named(err) from None

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)

    @staticmethod
    def _named(err: OSError) -> OSError:
        if err.filename is None and not isinstance(err, BrokenPipeError):   # a closed pipe stops quietly (main)
            err.filename = STANDARD_OUTPUT
        return err


class PatientInterrupts:
    """Ctrl-C stops a command cleanly: the first raises KeyboardInterrupt, so its ``finally`` blocks stop the
    runs, workers and agents it started. A second one while that cleanup runs would cut it short (orphaned
    processes, an agent's wheels not yet stopped) and print a traceback from the middle of it: it only says
    that khepri is stopping. A third quits at once, for a cleanup that hangs.

    Installed only over Python's default handler in the main thread; a command that sets its own (the hub, an
    agent) replaces it while it runs. ``exiting``: the process ends when the command returns, so Ctrl-C
    stays quiet until then (the interpreter's own shutdown would print a traceback for it)."""

    def __init__(self, exiting: bool):
        self.exiting, self.count, self.installed = exiting, 0, False

    def __enter__(self) -> PatientInterrupts:
        if threading.current_thread() is threading.main_thread() \
                and signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            signal.signal(signal.SIGINT, self._on_interrupt)
            self.installed = True
        return self

    def _on_interrupt(self, signum: int, frame: Any) -> None:
        self.count += 1
        if self.count == 1:
            raise KeyboardInterrupt
        if self.count == 2:
            say("khepri: stopping; press Ctrl-C again to quit at once")
            return
        os._exit(130)

    def __exit__(self, *exc: Any) -> None:
        if self.installed:
            interrupted_exit = self.exiting and self.count
            signal.signal(signal.SIGINT, signal.SIG_IGN if interrupted_exit else signal.default_int_handler)


def _silence_stdout() -> None:
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):   # stdout without a file descriptor (e.g. captured in tests)
        pass


def _path_error(err: OSError, default: Optional[str] = None) -> int:
    """One line for an OSError that names its file, or standard output (OutputNamedInErrors)."""
    where = err.filename if err.filename is not None else default
    if where == STANDARD_OUTPUT:
        _silence_stdout()           # else the interpreter's flush at exit fails on it again
    say(f"khepri: error: {err.strerror or err}: {where}")
    return 2


def _take_late_positional(args: argparse.Namespace, extras: List[str]) -> List[str]:
    """An optional positional given after an option (``study report --no-figures DIR``): argparse has already
    matched it to nothing with the positional before it, and leaves DIR over. A command names such a positional
    with ``set_defaults(late_positional=(dest, type))``; the first leftover that is not an option fills it."""
    late = getattr(args, "late_positional", None)
    if late is None or not extras or extras[0].startswith("-"):
        return extras
    dest, kind = late
    if getattr(args, dest, None) is not None:
        return extras
    setattr(args, dest, kind(extras[0]))
    return extras[1:]


def _command_parser(parser: argparse.ArgumentParser, argv: List[str]) -> argparse.ArgumentParser:
    """The (sub)command's parser that ``argv`` names: ``sim run`` for ``khepri sim run x.yaml extra``."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for index, word in enumerate(argv):
                if word in action.choices:
                    return _command_parser(action.choices[word], argv[index + 1:])
    return parser


def _run(argv: Optional[List[str]]) -> int:
    parser = build_parser()
    if not (sys.argv[1:] if argv is None else argv):    # plain `khepri`: the commands, not an error about them
        parser.print_help()
        return 2
    try:
        args, extras = parser.parse_known_args(argv)
        extras = _take_late_positional(args, extras)
        if extras:    # with the command's own usage line, as argparse gives for its other errors
            _command_parser(parser, sys.argv[1:] if argv is None else argv).error(
                f"unrecognized arguments: {' '.join(extras)}")
    except SystemExit:
        try:
            sys.stdout.flush()      # --help into a closed pipe fails here, inside main(), not at exit
        except BrokenPipeError:
            raise
        except OSError as err:      # --help onto a full disk (a file error: the stream names itself)
            return _path_error(err, default=STANDARD_OUTPUT)
        raise
    args.imports = args.imports + getattr(args, "late_imports", [])
    try:
        if args.imports:
            for warning in import_user_modules(args.imports):
                say(f"khepri: warning: --import {warning}")
            from sim_backend.metrics import evaluators_of_no_behaviour

            for warning in evaluators_of_no_behaviour():
                say(f"khepri: warning: --import: {warning}")
        code = int(args.func(args) or 0)
        sys.stdout.flush()          # buffered output meets a closed pipe here, inside main(), not at exit
        return code
    except ConfigError as err:
        say(f"khepri: error: {err}")
        return 2
    except BehaviourError as err:     # the user's behaviour raised (before a run could start, or in an agent)
        what = "the robot's driver failed" if isinstance(err.exc, DriverError) else "the behaviour failed"
        say(f"khepri: error: {what}: {err}")
        if not getattr(err, "traceback_logged", False):      # an agent logged it already, line by line
            say("\n".join(err.lines))
        return 1
    except EvaluatorError as err:     # a user's evaluator raised before the run could start (__init__, warnings)
        say(f"khepri: error: the evaluator failed: {err}")
        say("\n".join(err.lines))
        return 1
    except DriverError as err:        # an agent's robot hardware, outside any behaviour call
        say(f"khepri: error: the robot's driver failed: {err}")
        return 1
    except OSError as err:
        # A path the user gave that cannot be read or written (--record, keys folder, a full or read-only
        # disk, ...): one line that names it. An OS error without a path is a bug: keep its traceback.
        # Set KHEPRI_DEBUG=1 for the traceback in any case.
        if os.environ.get("KHEPRI_DEBUG") or err.filename is None:
            raise
        return _path_error(err)
    except KeyboardInterrupt:
        say("khepri: interrupted")
        return 130


if __name__ == "__main__":
    sys.exit(main())
