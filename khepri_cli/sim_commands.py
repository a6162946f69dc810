"""``khepri sim ...`` and ``khepri bench sim``."""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path
from typing import Any, Optional, Sequence

from .parsing import command_group
from .signals import sigterm_as_ctrl_c


def check_time_limit(seconds: Optional[float], option: str = "--time-limit") -> None:
    """``--time-limit`` (or ``--wall-limit``) of sim run, sil and study: argparse's float() also takes ``nan``
    and ``inf``."""
    from onboard.config import ConfigError

    if seconds is not None and not (math.isfinite(seconds) and seconds > 0):
        raise ConfigError(option, f"must be a finite number of seconds > 0 (got {seconds:g})")


def folder_arg(text: str) -> Path:
    """``--out``: an empty string (an unset shell variable, say) would mean the current folder; refuse it."""
    if not text.strip():
        raise argparse.ArgumentTypeError("must name a folder (got an empty string)")
    return Path(text)


def add_sim(groups) -> None:
    commands = command_group(groups, "sim", "run scenarios in the physics simulator",
                             "Run scenarios in the pymunk simulator.")

    run = commands.add_parser("run", help="run one scenario headless and write results",
                              description="Run SCENARIO (a built-in name or a YAML file) and write result.json, "
                                          "trajectory.npz and trajectory.png to --out.")
    run.add_argument("scenario", help="built-in scenario name (see `khepri sim list`) or path to a YAML file")
    run.add_argument("--seed", help="random seed (default: the scenario's)")
    add_set_argument(run)
    run.add_argument("--out", type=folder_arg, help="output folder (default: out/<scenario>-seed<N>)")
    run.add_argument("--time-limit", type=float, metavar="S", help="override the scenario's time_limit_s")
    run.add_argument("--wall-limit", type=float, metavar="S",
                     help="stop the run after S seconds of wall-clock time (a behaviour that hangs), keeping "
                          "what was recorded")
    # Kept as typed (not type=Path, which drops a trailing slash): video_problem refuses `out.gif/`.
    run.add_argument("--video", metavar="FILE", help="also write an animation (.gif, or .mp4 with ffmpeg)")
    run.add_argument("--no-plot", action="store_true", help="skip trajectory.png")
    run.set_defaults(func=cmd_run)

    listing = commands.add_parser("list", help="list built-in scenarios",
                                  description="List the built-in scenarios with their description.")
    listing.set_defaults(func=cmd_list)

    show = commands.add_parser("show", help="print a scenario as loaded (defaults filled in)",
                               description="Validate SCENARIO and print it with every default filled in.")
    show.add_argument("scenario", help="built-in scenario name (see `khepri sim list`) or path to a YAML file")
    add_set_argument(show)
    show.set_defaults(func=cmd_show)


def add_set_argument(parser: argparse.ArgumentParser) -> None:
    """``--set KEY=VALUE`` (``sim run``, ``sim show``, ``sil``): sim_backend/scenario_settings.py."""
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="settings",
                        help="change one field of the scenario, e.g. params.cruise_speed_m_s=0.15 or "
                             "robots.count=8 (a dotted key, a YAML value; repeatable)")


def seed_value(text: Optional[str]) -> Optional[int]:
    """``--seed`` as given (a string: argparse's own error would print the usage, not the one line every other
    bad input gets), or None; ConfigError naming ``--seed``. Numpy's seeds are whole numbers >= 0."""
    from onboard.config import MAX_SEED, ConfigError, as_written, check_seed

    if text is None:
        return None
    digits = text.strip().lstrip("+")
    if digits.isascii() and digits.isdigit() and len(digits) > len(str(MAX_SEED)):   # int() refuses 4300 digits
        raise ConfigError("--seed", f"must be <= {MAX_SEED} (got an integer of {len(digits)} digits)")
    try:
        value = int(text)
    except ValueError:
        raise ConfigError("--seed", f"must be a whole number >= 0 (got {as_written(text)})") from None
    return check_seed("--seed", value)


def add_bench(groups):
    commands = command_group(groups, "bench", "measure speed", "Benchmarks that print numbers.")
    sim = commands.add_parser("sim", help="simulator steps/s and real-time factor",
                              description="Simulate the paper's boxes with 25, 50 and 100 robots and print "
                                          "physics steps per second, the real-time factor (wall and CPU "
                                          "time) and the milliseconds each phase takes per simulated "
                                          "second.")
    sim.add_argument("--robots", default="25,50,100", help="comma-separated robot counts (default 25,50,100)")
    sim.add_argument("--seconds", type=float, default=30.0, help="simulated seconds per case (default 30)")
    sim.add_argument("--behaviour", default="transport", help="behaviour to run (default transport)")
    sim.add_argument("--json", action="store_true", help="print JSON instead of a table")
    sim.set_defaults(func=cmd_bench_sim)
    return commands


def cmd_run(args: argparse.Namespace) -> int:
    from sim_backend.outputs import ProgressBar, write_run
    from sim_backend.runner import Simulation
    from sim_backend.scenario_settings import load_with_settings

    scenario, settings = load_with_settings(args.scenario, args.settings)
    check_time_limit(args.time_limit)
    check_time_limit(args.wall_limit, "--wall-limit")
    problem = video_problem(args.video) if args.video is not None else None
    if problem:
        print(f"khepri: error: --video: {problem}", file=sys.stderr)
        return 2
    sim = Simulation(scenario.with_time_limit(args.time_limit), seed=seed_value(args.seed))
    out = args.out or Path("out") / f"{scenario.name}-seed{sim.seed}"
    problem = out_folder_problem(out, RUN_FILES)
    if problem:                 # said now, not after a long run whose results could not be written
        print(f"khepri: error: --out: {problem}", file=sys.stderr)
        return 2
    for warning in sim.warnings:
        print(f"khepri: warning: {warning}", file=sys.stderr)
    bar = ProgressBar(f"{scenario.name} seed {sim.seed}")
    sim.say = lambda note: bar.say(f"khepri: warning: {note}")
    try:
        with sigterm_as_ctrl_c():   # `kill` keeps what was recorded, as Ctrl-C does
            result = sim.run(time_limit_s=args.time_limit, progress=bar, wall_limit_s=args.wall_limit,
                             keep_on_interrupt=True)
    finally:
        bar.close()
    interrupted = result.get("stop_reason") == "interrupted"
    video = Path(args.video) if args.video is not None and not interrupted else None
    if settings:                # which values of the scenario file this run did not use
        result["settings"] = settings
    files = write_run(sim, result, out, video=video, plot=not args.no_plot)
    print_summary(result)
    for name, path in files.items():
        print(f"  {name}: {path}")
    if interrupted:             # Ctrl-C: what was recorded is written, and where the run was is said
        print(f"khepri: {result['error']}", file=sys.stderr)
        if args.video is not None:
            print(f"khepri: no video written (interrupted){earlier_file_note(Path(args.video))}", file=sys.stderr)
        return 130
    if "error" in result:
        reason = result.get("stop_reason")
        when = "the run crashed" if reason == "crashed" else "the run was stopped" if reason == "wall-clock limit" \
            else f"after the run ({reason})"      # the behaviour's stop() raised at the end
        print(f"khepri: error: {when}: {result['error']}", file=sys.stderr)
        if result.get("traceback"):
            print("\n".join(result["traceback"]), file=sys.stderr)
        print_evaluation_error(result)
        return 1
    return 0


def earlier_file_note(path: Path) -> str:
    """A file the run did not rewrite is an earlier run's: say so, or it passes for this run's."""
    return f"; {path} is from an earlier run" if path.is_file() else ""


def print_evaluation_error(result: dict) -> None:
    """The evaluator's result() that raised after the run had already failed (its own error comes first)."""
    if result.get("evaluation_error"):
        print(f"khepri: error: the evaluator failed too: {result['evaluation_error']}", file=sys.stderr)


def require_out_folder(out: Path, files: Sequence[str] = ()) -> None:
    """Create the output folder before a long job; ConfigError naming --out when that cannot be done."""
    from onboard.config import ConfigError

    problem = out_folder_problem(out, files)
    if problem:
        raise ConfigError("--out", problem)


RUN_FILES = ("result.json", "trajectory.npz", "trajectory.png")    # what `sim run` writes into --out


def out_folder_problem(out: Path, files: Sequence[str] = ()) -> Optional[str]:
    """Create the output folder now; what is wrong with it, or None. ``files``: names the command will write
    there, so that a folder of that name is said now rather than as "Is a directory" after the run."""
    try:      # exists() itself raises on a name too long for the file system
        if out.exists() and not out.is_dir():      # mkdir would only say "File exists"
            return f"{out} is a file, not a folder"
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        return f"cannot create the folder {out}: {err.strerror or err}"
    if not os.access(out, os.W_OK | os.X_OK):
        return f"cannot write into {out}"
    for name in files:
        if (out / name).is_dir():
            return f"{out / name} is a folder, where the run writes its {name} (move it or choose another --out)"
    return None


def video_problem(text: str) -> Optional[str]:
    """Check the video target, as typed, before a long run, not after it."""
    from onboard.config import folder_not_file

    folder = folder_not_file(text)
    if folder:
        return f"{folder}; give a file name ending in .gif or .mp4"
    path = Path(text)
    suffix = path.suffix.lower()
    if suffix not in (".gif", ".mp4"):
        return f"unsupported file type {path.suffix!r} (use .gif or .mp4)"
    if suffix == ".mp4":
        import matplotlib.animation

        if not matplotlib.animation.writers.is_available("ffmpeg"):
            return "mp4 needs ffmpeg, which is not installed; use a .gif file name"
    if path.parent.exists() and not path.parent.is_dir():
        return f"{path.parent} is not a folder"
    if path.parent.is_dir():           # try to write it now: a read-only place fails here, not after the run
        existed = path.exists()
        try:
            with open(path, "ab"):
                pass
        except OSError as err:
            return f"cannot write {path}: {err.strerror or err}"
        if not existed:
            path.unlink()
    return None


def print_summary(result: dict) -> None:
    print(summary_line(result))
    if result.get("failures"):      # "behaviour finished" is what the robots believe; this is the evaluator
        print(f"  not completed: {'; '.join(result['failures'])}")
    if result.get("faults_fired"):  # the scenario's own faults: said apart, since a run may complete despite them
        print(f"  faults: {'; '.join(result['faults_fired'])}")


def seconds_text(seconds: float) -> str:
    """``1.1 s``; under a second with two digits that say something (``0.04 s``, not ``0.0 s`` beside 212x)."""
    return f"{seconds:.1f} s" if seconds >= 1.0 else f"{seconds:.2g} s"


def summary_line(result: dict) -> str:
    robots = "1 robot" if result["robots"] == 1 else f"{result['robots']} robots"
    parts = [f"{result['scenario']} seed {result['seed']}: {robots}, "
             f"{result['sim_time_s']:.1f} s simulated in {seconds_text(result['wall_time_s'])} "
             f"({result['real_time_factor']}x real time), stopped: {result['stop_reason']}"]
    for key in ("caged", "completed", "final_position_error_m", "spread_ratio"):
        if key in result:
            value = result[key]
            parts.append(f"{key}={value:.3f}" if isinstance(value, float) else f"{key}={value}")
    return "; ".join(parts)


def cmd_list(args: argparse.Namespace) -> int:
    from sim_backend.scenario import builtin_names, load_scenario

    for name in builtin_names():
        scenario = load_scenario(name)
        summary = first_sentence(scenario.description)
        print(f"{name:28s} {scenario.robots.count:4d} robots  {scenario.behaviour:10s} {summary}")
    return 0


def first_sentence(text: str) -> str:
    return text.split(". ")[0].rstrip(".")


def cmd_show(args: argparse.Namespace) -> int:
    from onboard.behaviour import build_params, get_behaviour
    from onboard.config import to_mapping
    from onboard.yamlfile import dump_yaml
    from sim_backend.runner import Simulation
    from sim_backend.scenario_settings import load_with_settings

    scenario, _ = load_with_settings(args.scenario, args.settings)
    for warning in Simulation(scenario).warnings:     # what `sim run` would warn about, on stderr
        print(f"khepri: warning: {warning}", file=sys.stderr)
    shown = to_mapping(scenario)
    # Every parameter of the behaviour, the scenario's own values over the defaults. The mission (path, the
    # object's starting estimate) is left out unless the scenario sets it: the runner takes it from `path`
    # and `object`.
    params = to_mapping(build_params(get_behaviour(scenario.behaviour, "behaviour"), scenario.params))
    shown["params"] = {key: value for key, value in params.items()
                       if (key not in MISSION_PARAMS or key in scenario.params) and not _non_finite(value)}
    print(dump_yaml(shown), end="")
    return 0


MISSION_PARAMS = ("path", "object_estimate")     # filled in by the runner from the scenario (mission_params)


def _non_finite(value: Any) -> bool:
    """A value no scenario file can give (the loader refuses .inf and .nan), so only the Params' own validate
    set it (the faithful profile's attach_timeout_s = inf), and it sets it again when the file shown is loaded:
    printed, it made that file fail with `must be a finite number (got inf)`."""
    return isinstance(value, float) and not math.isfinite(value)


def cmd_bench_sim(args: argparse.Namespace) -> int:
    from sim_backend.bench import bench_sim

    check_time_limit(args.seconds, "--seconds")
    try:
        counts = [int(c) for c in args.robots.split(",")]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1:
        print(f"khepri: error: --robots: give positive robot counts, e.g. 25,50,100 (got {args.robots!r})",
              file=sys.stderr)
        return 2
    results = bench_sim(counts, args.seconds, args.behaviour)
    crashed = [r for r in results if r.get("error")]
    for r in crashed:
        print(f"khepri: error: {r['robots']} robots: the run {r['stop_reason']} after {r['sim_seconds']:g} of the "
              f"{args.seconds:g} simulated seconds: {r['error']} (its figures are of that shorter run)",
              file=sys.stderr)
    if args.json:
        print(json.dumps({"results": results}, indent=2))
        return 1 if crashed else 0
    phases = list(results[0]["phase_ms_per_sim_s"]) if results else []
    print(f"{'robots':>6} {'behaviour':>10} {'sim s':>7} {'wall s':>7} {'steps/s':>9} {'real-time x':>11} "
          f"{'cpu x':>7} | ms per simulated second: " + " ".join(f"{name:>10}" for name in phases))
    for r in results:
        cpu_factor = r["cpu_real_time_factor"] or 0.0
        phase_ms = " ".join(f"{r['phase_ms_per_sim_s'][name]:10.1f}" for name in phases)
        print(f"{r['robots']:6d} {r['behaviour']:>10} {r['sim_seconds']:7.1f} {r['wall_seconds']:7.2f} "
              f"{r['physics_steps_per_s']:9.0f} {r['real_time_factor']:11.1f} {cpu_factor:7.1f} | {'':24} {phase_ms}")
    return 1 if crashed else 0
