"""``khepri bench hub`` and ``khepri bench estop``: the lab stack's benchmarks (``bench sim`` is with the sim
commands)."""
from __future__ import annotations

import argparse
import json
import math
import sys

from onboard.config import ConfigError, check_range

from .signals import sigterm_as_ctrl_c


def add_lab_benches(bench_commands) -> None:
    """Register ``khepri bench hub`` and ``khepri bench estop`` under the bench group."""
    _add_bench_hub(bench_commands)
    _add_bench_estop(bench_commands)


def _add_bench_hub(bench_commands) -> None:
    """Register ``khepri bench hub`` under the bench group."""
    bench = bench_commands.add_parser("hub", help="hub latency and CPU with many robots",
                                      description="Feed the hub synthetic motion capture for --robots bodies at "
                                                  "--rate Hz, receive its frames on light agents, and print "
                                                  "mocap-frame-to-agent latency p50/p99 and the hub's CPU use.")
    bench.add_argument("--robots", type=int, default=100, help="robots (default 100)")
    bench.add_argument("--rate", type=float, default=120.0, help="motion-capture frames per second (default 120)")
    bench.add_argument("--seconds", type=float, default=5.0, help="measurement time (default 5)")
    bench.add_argument("--telemetry-hz", type=float, default=0.0, metavar="HZ",
                       help="every agent also sends a small telemetry message at this rate, as a real agent does "
                            "at 10 (default 0: agents only receive)")
    bench.add_argument("--record", action=argparse.BooleanOptionalAction, default=False,
                       help="the hub records everything to an MCAP log in a temporary folder, as `khepri hub "
                            "--record` does (default --no-record)")
    bench.add_argument("--json", action="store_true", help="print JSON only")
    bench.set_defaults(func=cmd_bench_hub)



# The benchmark's agents are sockets in one process: 1000 run here (p99 ~19 ms); from about 1100, ZeroMQ runs
# out of sockets.
MAX_BENCH_ROBOTS = 1000
MAX_BENCH_RATE_HZ = 1000.0
MAX_BENCH_SECONDS = 3600.0
BENCH_MOCAP_PERIODS = 2     # the shortest --seconds, in motion-capture periods


def check_bench_options(args: argparse.Namespace) -> None:
    check_range("--robots", args.robots, 1, MAX_BENCH_ROBOTS)
    check_range("--rate", args.rate, 0, MAX_BENCH_RATE_HZ, low_open=True)     # nan and inf too
    if args.rate < 1 or not args.rate.is_integer():     # the mock backend's frequency is an integer; 0: unthrottled
        raise ConfigError("--rate", f"must be a whole number of Hz >= 1 (got {args.rate:g})")
    check_range("--seconds", args.seconds, 0, MAX_BENCH_SECONDS, low_open=True)
    # Only frames that carry a new pose count, one per motion-capture period: a shorter window may see none,
    # which read as "the hub sent no frames", blaming the hub for the window.
    shortest = BENCH_MOCAP_PERIODS / args.rate
    if args.seconds < shortest:
        raise ConfigError("--seconds", f"must be at least {shortest:g} s at --rate {args.rate:g} (got "
                          f"{args.seconds:g}): {BENCH_MOCAP_PERIODS} motion-capture periods, as only frames "
                          "with a new pose are measured")
    if not (math.isfinite(args.telemetry_hz) and 0 <= args.telemetry_hz <= MAX_BENCH_RATE_HZ):
        raise ConfigError("--telemetry-hz", f"give a rate 0..{MAX_BENCH_RATE_HZ:g} (0: no telemetry), "
                          f"not {args.telemetry_hz:g}")


def cmd_bench_hub(args: argparse.Namespace) -> int:
    from hub.bench import bench_hub
    from hub.control import ControlError

    check_bench_options(args)
    try:
        with sigterm_as_ctrl_c():       # `kill` cleans up the hub, its agents and the temporary folder
            result = bench_hub(args.robots, args.rate, args.seconds, telemetry_hz=args.telemetry_hz,
                               record=args.record)
    except (ControlError, RuntimeError) as err:     # the hub did not start, answer or send: said, not a traceback
        print(f"khepri: error: bench hub: {err}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps({key: result[key] for key in ("latency_p50_ms", "latency_p99_ms", "hub_cpu_percent")}))
        return 0
    load = "".join((f", agents sending telemetry at {args.telemetry_hz:g} Hz" if args.telemetry_hz > 0 else "",
                    ", recording to MCAP" if args.record else ""))
    robots = f"{args.robots} robot{'s' if args.robots != 1 else ''}"
    dropped = result["hub_drops"] + result["frames_dropped"]     # a loaded hub's: said, not left to --json readers
    print(f"hub with {robots} at {args.rate:g} Hz for {args.seconds:g} s{load}: "
          f"mocap-frame-to-agent latency p50 {result['latency_p50_ms']:.3f} ms, p99 {result['latency_p99_ms']:.3f} ms "
          f"(the last robot of each frame's burst: p50 {result['last_robot_p50_ms']:.3f} ms); "
          f"hub CPU {result['hub_cpu_percent']:.1f} % of a core ({result['frames_received']} frames received"
          f"{f', {dropped} dropped' if dropped else ''})")
    return 0


# --- estop ----------------------------------------------------------------------------------------------------
MAX_ESTOP_ROBOTS = 100      # real agent processes, each an interpreter: this PC's memory and cores set the limit
MAX_ESTOP_REPEATS = 100


def _add_bench_estop(bench_commands) -> None:
    bench = bench_commands.add_parser(
        "estop", help="e-stop to wheels stopped, with real agent processes",
        description="Start a hub (sim source) and --robots real agent processes running a behaviour, request "
                    "the e-stop as `khepri ctl estop` does, and print how long until every agent had stopped its "
                    "wheels (the request's transit plus the slowest acknowledgement), --repeats times. The agents "
                    "share this PC's cores, as they never do on a fleet.")
    bench.add_argument("--robots", type=int, default=25, help="agent processes (default 25)")
    bench.add_argument("--repeats", type=int, default=5, help="e-stops, each cleared and resumed (default 5)")
    bench.add_argument("--json", action="store_true", help="print JSON only")
    bench.set_defaults(func=cmd_bench_estop)


def cmd_bench_estop(args: argparse.Namespace) -> int:
    from hub.bench_estop import bench_estop
    from hub.control import ControlError

    check_range("--robots", args.robots, 1, MAX_ESTOP_ROBOTS)
    check_range("--repeats", args.repeats, 1, MAX_ESTOP_REPEATS)
    try:
        with sigterm_as_ctrl_c():       # `kill` stops the agent processes and removes their logs' folder
            result = bench_estop(args.robots, args.repeats)
    except (ControlError, RuntimeError) as err:     # the hub or an agent did not start or answer: said
        print(f"khepri: error: bench estop: {err}", file=sys.stderr)
        return 1
    summary = result.summary()
    if args.json:
        print(json.dumps(summary))
        return 0
    for k, trial in enumerate(result.trials, 1):
        print(f"e-stop {k}: request transit {trial.transit_ms:.1f} ms, acknowledgements p50 "
              f"{trial.acks_ms[len(trial.acks_ms) // 2]:.1f} ms, max {max(trial.acks_ms):.1f} ms: every agent "
              f"stopped within {trial.worst_ms:.1f} ms")
    agents = f"{args.robots} agent{'s' if args.robots != 1 else ''}"
    stops = f"{summary['repeats']} e-stop{'s' if summary['repeats'] != 1 else ''}"
    print(f"{agents}, {stops}: every agent stopped within {summary['worst_ms_p50']:.1f} ms (median of the "
          f"e-stops), {summary['worst_ms_max']:.1f} ms at worst")
    return 0
