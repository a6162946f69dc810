"""``khepri hub``, ``khepri agent``, ``khepri ctl``, ``khepri sil`` (and ``khepri keys``, from keys_commands.py)."""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

from onboard.config import ConfigError

from .keys_commands import add_keys_commands
from .sim_commands import add_set_argument, folder_arg


def add_lab(groups) -> None:
    """Register the lab-stack commands."""
    _add_hub(groups)
    _add_agent(groups)
    _add_ctl(groups)
    add_keys_commands(groups)
    _add_sil(groups)


# --- hub ------------------------------------------------------------------------------------------------------
def _add_hub(groups) -> None:
    hub = groups.add_parser("hub", help="run the lab hub (motion capture -> robots)",
                            description="Run the hub: poses from the configured source, virtual sensors and radio "
                                        "relay for every robot, operator control. Prints `listening <role> "
                                        "<endpoint>` per socket.")
    source = hub.add_mutually_exclusive_group()
    source.add_argument("--config", type=Path, metavar="FILE", help="lab config YAML (see docs/lab.md)")
    source.add_argument("--demo", action="store_true",
                        help="no files needed: sim source on lab-6, loopback only, insecure")
    hub.add_argument("--insecure", action="store_true", help="run without CURVE encryption and authentication")
    hub.add_argument("--record", metavar="FILE", help="record everything in and out to this MCAP file")
    hub.add_argument("--bind", help="interface to listen on (overrides network.bind)")
    hub.add_argument("--robot-port", type=int, metavar="PORT",
                     help="port the agents connect to (overrides network.robot_port; 0: any free port)")
    hub.add_argument("--control-port", type=int, metavar="PORT",
                     help="port khepri ctl connects to (overrides network.control_port; 0: any free port)")
    hub.set_defaults(func=cmd_hub)


# The options that override a config setting, by the field an error names (`port 5560 ... is already in use`,
# `record: rp.mcap exists`): the error names the option the user typed instead.
OVERRIDING_OPTIONS = {"network.bind": "bind", "network.robot_port": "robot_port",
                      "network.control_port": "control_port", "record": "record"}


def cmd_hub(args: argparse.Namespace) -> int:
    from hub.binding import is_loopback
    from hub.config import demo_config, load_config, parse_config
    from hub.runner import serve_hub

    if args.demo:
        config = demo_config()
    elif args.config is not None:
        config = load_config(args.config)
    else:
        config = parse_config({})
        print("khepri hub: no --config: sim source on lab-6 (see docs/lab.md for a lab config)", file=sys.stderr)
    if args.insecure:
        config.security.insecure = True
    if args.record is not None:
        if not args.record.strip():    # an unset shell variable: say so rather than record nothing
            raise ConfigError("--record", "is empty: name the MCAP file (e.g. logs/run-{time}.mcap)")
        config.record = args.record
    if args.bind:
        if args.demo and not is_loopback(args.bind):
            raise ConfigError("--bind", f"--demo runs without encryption or authentication, so it listens on "
                              f"loopback only (got {args.bind!r}); for a lab network use a config with keys "
                              f"(khepri keys init, docs/lab.md)")
        config.network.bind = args.bind
    # A demo on other ports (5560 or 5561 taken), or one lab config run twice on one PC.
    for name in ("robot_port", "control_port"):
        if getattr(args, name) is not None:
            setattr(config.network, name, getattr(args, name))
    try:
        config.network.validate("network")
        return serve_hub(config)
    except ConfigError as err:
        option = OVERRIDING_OPTIONS.get(err.field)
        # Name the option the user typed, or with --demo (which has no config file) the one that would change it.
        if option and (getattr(args, option) is not None or (args.demo and option != "record")):
            raise ConfigError("--" + option.replace("_", "-"), err.problem) from None
        if args.config is not None and err.field.split(".")[0].split("[")[0] in lab_config_keys():
            # A key of the file, found wrong as the hub starts (a keys folder, the run's params): name the file
            # too, as load_config does for what it finds.
            raise ConfigError(f"{args.config}: {err.field}", err.problem) from None
        raise


def lab_config_keys() -> set:
    from dataclasses import fields

    from hub.config import LabConfig

    return {f.name for f in fields(LabConfig) if f.init}


def keys_here_hint() -> str:
    """`keys init` and the hub's security.keys both default to ./keys: a ctl run without --keys beside such a
    folder most likely meant it."""
    operators = Path("keys") / "operators"
    if operators.is_dir() and any(operators.glob("*.key_secret")):
        return " This folder has operator keys in keys/: try again with --keys keys."
    return ""


# --- agent ----------------------------------------------------------------------------------------------------
def _add_agent(groups) -> None:
    from onboard.agent.cli import add_agent_arguments

    agent = groups.add_parser("agent", help="run a robot's agent",
                              description="Run one robot's agent: the behaviour the hub starts, at 10 Hz, with the "
                                          "kh4 (real robot) or sim (hub-simulated) driver. On a robot without the "
                                          "khepri command: python -m onboard.agent with the same options.")
    add_agent_arguments(agent)
    agent.set_defaults(func=cmd_agent)


def cmd_agent(args: argparse.Namespace) -> int:
    from onboard.agent.cli import run_agent

    return run_agent(args)


DEFAULT_CONTROL_PORT = 5561


# --- ctl ------------------------------------------------------------------------------------------------------
def _add_ctl(groups) -> None:
    ctl = groups.add_parser("ctl", help="operator control: status, start, stop, estop, clear",
                            description="Talk to a running hub's control socket.")
    ctl.add_argument("command", choices=("status", "start", "stop", "estop", "clear"))
    ctl.add_argument("--hub", default="127.0.0.1", help="hub host (default 127.0.0.1)")
    ctl.add_argument("--port", type=int, default=None, help=f"hub control port (default {DEFAULT_CONTROL_PORT})")
    ctl.add_argument("--keys", type=Path, metavar="DIR", help="key folder with operators/<name>.key_secret, hub.key")
    ctl.add_argument("--operator", help="operator key name when the folder holds several")
    ctl.add_argument("--timeout", type=float, default=2.0, metavar="S", help="wait this long for the hub (default 2)")
    ctl.add_argument("--json", action="store_true", help="print JSON: the status, or what the command did")
    ctl.set_defaults(func=cmd_ctl)


def cmd_ctl(args: argparse.Namespace) -> int:
    from hub.control import BadEndpoint, ControlError, refusals_after_start, request, status_table
    from hub.keyfiles import operator_client_keys
    from onboard.agent.link import hub_endpoint, resolve_problem, unresolvable_host
    from onboard.console import one_line

    port = DEFAULT_CONTROL_PORT if args.port is None else args.port
    check_port("--port", port)
    check_timeout("--timeout", args.timeout)
    if args.operator is not None and args.keys is None:    # it only picks a key pair: without one, it was dropped
        raise ConfigError("--operator", "names an operator key in the --keys folder: give --keys DIR too "
                          "(without --keys, ctl connects unencrypted, as a hub run with --insecure takes)")
    keys = operator_client_keys(args.keys, args.operator) if args.keys is not None else None
    endpoint = hub_endpoint(args.hub, port, port_given=args.port is not None)
    unresolved = unresolvable_host(endpoint)       # else a typo waits out --timeout as if no hub ran
    if unresolved is not None:
        raise ConfigError("--hub", resolve_problem(*unresolved))
    try:
        reply = request(endpoint, args.command, keys=keys, timeout_s=args.timeout)
    except BadEndpoint as err:
        raise ConfigError("--hub", str(err)) from None
    except ControlError as err:      # no answer, or the hub refused (an e-stop latched, ...)
        said = str(err) + (keys_here_hint() if keys is None and err.keys_may_help else "")
        if args.json:     # a script reading stdout learns it failed, and why (status printed nothing there)
            print(json.dumps({"command": args.command, "ok": False, "error": said}))
        # An e-stop that did not arrive must not read like any other error at a demo: the robots still run.
        loud = "E-STOP NOT DELIVERED: " if args.command == "estop" else ""
        print(one_line(f"khepri: error: {loud}{said}"), file=sys.stderr)
        return 1
    if args.command == "status":
        print(json.dumps(reply["status"], indent=2) if args.json else status_table(reply["status"]))
        return 0
    refused, unknown = [], None
    if args.command == "start":      # the hub is in run mode now; which robots will not run it?
        try:
            refused = refusals_after_start(endpoint, keys, args.timeout)
        except ControlError as err:
            unknown = str(err)
    if args.json:
        said = {key: reply[key] for key in ("note", "nothing_done") if key in reply}
        if args.command == "start":
            said["refused"] = None if unknown else [{"robot": rid, "error": error} for rid, error in refused]
        print(json.dumps({"command": args.command, "ok": True, **said, **({"error": unknown} if unknown else {})}))
    else:
        print(one_line(ctl_reply_line(args.command, reply, len(refused))))
    for robot_id, error in refused:      # the agent's own text: its newline would make a line of its own
        print(one_line(f"khepri: error: robot {robot_id}: {error}"), file=sys.stderr)
    if unknown:
        print(one_line(f"khepri: error: the run started, but whether every robot took it is unknown: {unknown}"),
              file=sys.stderr)
    return 1 if refused or unknown else 0


def ctl_reply_line(command: str, reply: dict, refused: int) -> str:
    """``start: ok (...)``; a start some robots refused says so, rather than "ok" above their errors."""
    note = reply.get("note")
    if reply.get("nothing_done"):
        return f"{command}: {note}"
    if refused:
        return (f"{command}: the hub is running, but {refused} robot{'s' if refused > 1 else ''} refused to start "
                f"(the errors follow){'; ' + note if note else ''}")
    return f"{command}: ok{' (' + note + ')' if note else ''}"


MAX_TIMEOUT_S = 3600.0


def check_port(option: str, port: int) -> None:
    if not 1 <= port <= 65535:
        raise ConfigError(option, f"must be a port 1..65535 (got {port})")


def check_timeout(option: str, seconds: float) -> None:
    """argparse's float() takes nan, inf and -1; ZeroMQ takes milliseconds as a C int."""
    if not (math.isfinite(seconds) and 0 < seconds <= MAX_TIMEOUT_S):
        raise ConfigError(option, f"must be a number of seconds > 0 and <= {MAX_TIMEOUT_S:g} (got {seconds:g})")


# --- sil ------------------------------------------------------------------------------------------------------
def _add_sil(groups) -> None:
    sil = groups.add_parser("sil", help="software in the loop: hub + one real agent process per robot",
                            description="Run SCENARIO through the lab stack: the hub's sim source plays robots and "
                                        "cameras, one agent process per robot runs the behaviour over loopback "
                                        "sockets. Writes result.json (as `khepri sim run`, plus hub and agent "
                                        "figures), trajectory.npz/png and the MCAP log.")
    sil.add_argument("scenario", help="built-in scenario name or YAML file")
    sil.add_argument("--out", type=folder_arg, help="output folder (default out/sil-<scenario>-seed<N>)")
    sil.add_argument("--seed", help="random seed (default: the scenario's)")
    add_set_argument(sil)
    sil.add_argument("--time-limit", type=float, metavar="S", help="override the scenario's time_limit_s")
    sil.add_argument("--realtime", action="store_true", help="pace by the wall clock instead of lockstep")
    sil.add_argument("--no-record", action="store_true", help="skip the MCAP log")
    sil.add_argument("--no-plot", action="store_true", help="skip trajectory.png")
    sil.add_argument("--agent-python", metavar="PYTHON",
                     help="run the agents with this Python interpreter, e.g. one like the robots' (3.9 or newer, "
                          "with numpy, pyzmq, pyyaml and filterpy); default: the one running khepri")
    sil.set_defaults(func=cmd_sil)


def cmd_sil(args: argparse.Namespace) -> int:
    from hub.sil import SilOptions, run_sil
    from hub.sil_agents import check_agent_python
    from hub.sil_report import sil_summary_lines
    from khepri_cli.signals import sigterm_as_ctrl_c
    from khepri_cli.sim_commands import (
        RUN_FILES,
        check_time_limit,
        out_folder_problem,
        print_evaluation_error,
        print_summary,
        require_out_folder,
        seed_value,
    )
    from sim_backend.scenario_settings import load_with_settings

    given_seed = seed_value(args.seed)
    scenario, settings = load_with_settings(args.scenario, args.settings)
    check_time_limit(args.time_limit)
    seed = scenario.seed if given_seed is None else given_seed
    out = args.out or Path("out") / f"sil-{scenario.name}-seed{seed}"

    python = None if args.agent_python is None else os.path.abspath(args.agent_python)
    version = None if python is None else check_agent_python(python)      # before --out is made
    require_out_folder(out, RUN_FILES + ("hub.log", "hub.mcap"))     # what sil writes there
    problem = out_folder_problem(out / "agents")     # else a file of that name stops sil once the hub is up
    if problem:
        raise ConfigError("--out", f"{problem} (sil writes the agents' logs into it)")
    options = SilOptions(seed=seed, time_limit_s=args.time_limit, realtime=args.realtime,
                         record=not args.no_record, plot=not args.no_plot, imports=list(args.imports),
                         scenario_ref=args.scenario, agent_python=python, agent_python_version=version,
                         settings=settings)
    with sigterm_as_ctrl_c():      # `kill` stops the agents and the hub and closes the log, as Ctrl-C does
        result = run_sil(scenario, out, options)
    print_summary(result)
    for line in sil_summary_lines(result.get("sil", {})):
        print(line)
    print(f"  results: {out}")
    if result.get("stop_reason") == "interrupted":     # what was recorded is written, and where the run was
        print(f"khepri: {result['error']}", file=sys.stderr)
        return 130
    if "error" in result:
        print(f"khepri: error: {result['error']}", file=sys.stderr)
        print_evaluation_error(result)
        return 1
    return 0
