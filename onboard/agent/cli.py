"""Command line of the agent, shared by ``khepri agent`` (lab PC, SIL) and ``python -m onboard.agent`` (robots,
where only ``onboard/`` is installed)."""
from __future__ import annotations

import argparse
import importlib
import os
import socket
import sys
from pathlib import Path
from typing import TYPE_CHECKING, List, Optional

import zmq

from onboard.behaviour import BehaviourError, behaviour_names
from onboard.config import ConfigError
from onboard.drivers import Driver, DriverError
from onboard.plugins import import_user_modules
from onboard.protocol import MAX_ROBOT_ID

from ..console import flush_quietly, say

if TYPE_CHECKING:
    from .link import HubLink

DEFAULT_ROBOT_PORT = 5560


def add_agent_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--id", dest="robot_id", type=int, required=True, help="this robot's id")
    parser.add_argument("--hub", default="127.0.0.1", help="the hub's host name or address (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=None,
                        help=f"the hub's robot port (default {DEFAULT_ROBOT_PORT})")
    parser.add_argument("--driver", choices=("kh4", "sim"), required=True,
                        help="kh4: this KheperaIV's hardware; sim: a robot simulated by the hub's sim source")
    parser.add_argument("--keys", type=Path, metavar="DIR",
                        help="key folder with robots/robot-<id>.key_secret and hub.key (CURVE); "
                             "without it the agent connects unencrypted, which only a hub run with --insecure accepts")
    parser.add_argument("--library", help="kh4: path to libkhepera.so")
    parser.add_argument("--calibration", help="kh4: this robot's IR calibration YAML")
    parser.add_argument("--watchdog", type=float, default=0.25, metavar="S",
                        help="stop the wheels after S seconds without a hub frame (default 0.25, at most 0.3)")
    parser.add_argument("--quiet", action="store_true",
                        help="log only problems and what stops the wheels (a run's stop, an e-stop, a hold)")
    parser.add_argument("--import", dest="agent_imports", action="append", default=[], metavar="MODULE",
                        help="import MODULE first: your behaviour's module name or .py file (repeatable)")


def run_agent(args: argparse.Namespace) -> int:
    from .link import exposed_secret, hub_endpoint, load_robot_keys, robot_secret_file
    from .loop import Agent
    from .parent import end_with_parent

    end_with_parent()

    if not 0 <= args.robot_id <= MAX_ROBOT_ID:     # the hub would drop every message of any other id
        raise ConfigError("--id", f"must be a robot id 0..{MAX_ROBOT_ID} (got {args.robot_id})")
    port = DEFAULT_ROBOT_PORT if args.port is None else args.port
    if not 1 <= port <= 65535:
        raise ConfigError("--port", f"must be a port 1..65535 (got {port})")
    for option in ("library", "calibration"):     # "" (an unset shell variable) must not mean the default
        if getattr(args, option) is not None and not getattr(args, option).strip():
            raise ConfigError(f"--{option}", "an empty path; leave the option out for the default")
    check_kh4_only_options(args)
    if not 0.0 < args.watchdog <= 0.3:
        raise ConfigError("--watchdog", f"must be in (0, 0.3] seconds (got {args.watchdog})")
    keys = load_robot_keys(args.keys, args.robot_id) if args.keys is not None else None
    exposed = exposed_secret(robot_secret_file(args.keys, args.robot_id)) if keys else None
    if exposed:
        print(f"agent {args.robot_id}: warning: {exposed}", file=sys.stderr, flush=True)
    for warning in import_user_modules(args.agent_imports):
        print(f"agent: warning: --import {warning}", file=sys.stderr, flush=True)
    behaviour_names()       # import the behaviours now, not when the hub says start (that takes a while)
    log = _logger(args.quiet)
    endpoint = hub_endpoint(args.hub, port, port_given=args.port is not None)
    link = open_link(args.robot_id, endpoint, keys, log)
    if keys is None and not args.quiet:
        log(f"agent {args.robot_id}: no --keys: connecting unencrypted (only a hub run with --insecure accepts this)")

    def make_driver(agent: Agent) -> Driver:
        return open_driver(args, agent)

    try:
        agent = Agent(args.robot_id, link, make_driver, watchdog_s=args.watchdog, log=log)
        log(f"agent {args.robot_id}: connecting to {endpoint} with the {args.driver} driver")
        agent.serve()
    finally:
        link.close()
        flush_quietly()        # a terminal closed under us (SIGHUP) must not fail the exit after a clean stop
    return 0


def check_kh4_only_options(args: argparse.Namespace) -> None:
    """Refuse --library and --calibration with --driver sim, which would ignore them: the notice that said so
    was dropped with --quiet, and the run went on as if the robot's IR calibration were in use."""
    if args.driver != "sim":
        return
    for name in ("calibration", "library"):
        if getattr(args, name):
            raise ConfigError(f"--{name}", "is only for --driver kh4: the sim driver's readings come from the "
                              "hub's simulation, so it would be ignored (leave it out, or use --driver kh4)")


def open_link(robot_id: int, endpoint: str, keys, log) -> HubLink:
    """The link to the hub, once ZeroMQ took the address and its host name resolves. A name the resolver says
    does not exist is an error; one it cannot look up now (no DNS server reachable yet, as on a robot booting
    before its Wi-Fi is up) is said, and the agent keeps trying: ZeroMQ resolves it again at each attempt."""
    from .link import HubLink, resolve_problem, unresolvable_host

    try:
        link = HubLink(robot_id, endpoint, keys, log=log)
    except zmq.ZMQError as err:     # e.g. a space or a stray colon in --hub: ZeroMQ refuses the address
        raise ConfigError("--hub", f"cannot connect to {endpoint!r}: {err.strerror}") from None
    unresolved = unresolvable_host(endpoint)
    if unresolved is None:
        return link
    if unresolved[1].errno == socket.EAI_AGAIN:
        log(f"agent {robot_id}: warning: {resolve_problem(*unresolved)}; still trying")
        return link
    link.close()
    raise ConfigError("--hub", resolve_problem(*unresolved))


def open_driver(args: argparse.Namespace, agent) -> Driver:
    if args.driver == "sim":
        from onboard.drivers.sim import SimDriver

        return SimDriver(agent.link.send, lambda: agent.state.sim, lambda: agent.state.sim_first)
    try:
        kh4 = importlib.import_module("onboard.drivers.kh4")
        calibration = importlib.import_module("onboard.drivers.calibration")
    except ImportError as err:
        raise ConfigError("--driver", f"the kh4 driver is not available here ({err})") from None
    try:
        driver = kh4.KheperaIV(library_path=args.library, calibration_path=args.calibration)
    except ConfigError as err:      # the calibration file: it already names itself and its field
        given_as = "--calibration" if args.calibration else f"${kh4.CALIBRATION_ENV}"
        # "--calibration: no such file: x.yaml", not "--calibration: calibration file: no such file: x.yaml"
        whole_file = err.field == calibration.CALIBRATION_LABEL
        raise ConfigError(given_as, err.problem if whole_file else str(err)) from None
    except (OSError, RuntimeError, ValueError) as err:
        # A library that would not load is the option that named it; any other failure is the robot's.
        loading = isinstance(err, kh4.LibkheperaError) and str(err).startswith("cannot load libkhepera")
        given_as = ("--library" if args.library else f"${kh4.LIBRARY_ENV}") \
            if loading and (args.library or os.environ.get(kh4.LIBRARY_ENV)) else "--driver kh4"
        raise ConfigError(given_as, f"cannot open the KheperaIV: {err}") from None
    driver.start_guard()      # stops the wheels should this process die without closing the driver (SIGKILL)
    measured_on = driver.calibration.robot
    if measured_on is not None and measured_on != args.robot_id:   # e.g. one file copied onto every robot
        given = args.calibration or os.environ.get(kh4.CALIBRATION_ENV)
        print(f"agent {args.robot_id}: warning: the IR calibration {given} was measured on robot {measured_on}, "
              f"not on this robot ({args.robot_id}): its readings follow robot {measured_on}'s sensors",
              file=sys.stderr, flush=True)
    return driver


def _logger(quiet: bool):
    def log(line: str) -> None:
        if quiet and not any(word in line for word in ("error", "stop", "hold", "estop", "no frame", "cannot")):
            return
        say(line)          # a line to a closed terminal is dropped: it must not stop the agent's way out
    return log


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m onboard.agent",
                                     description="Run this robot's agent: behaviour at 10 Hz, fed by the hub.")
    add_agent_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return run_agent(args)
    except ConfigError as err:
        say(f"agent: error: {err}")
        return 2
    except BehaviourError as err:      # already logged with its traceback; the wheels are stopped
        what = "the driver failed" if isinstance(err.exc, DriverError) else "the behaviour crashed"
        say(f"agent: error: {what}: {err}")
        return 1
    except DriverError as err:         # the robot's hardware, outside any behaviour call (a stop that failed)
        say(f"agent: error: the driver failed: {err}")
        return 1
    except KeyboardInterrupt:
        return 130
