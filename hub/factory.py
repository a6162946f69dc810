"""From a validated :class:`LabConfig` to a ready :class:`Hub`: source, robot list, run, sensing, keys, log."""
from __future__ import annotations

import re
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional

import zmq

from onboard.agent.link import exposed_secret
from onboard.behaviour import build_params, get_behaviour
from onboard.config import ConfigError, folder_not_file
from onboard.hal import RobotSpec
from onboard.protocol_schema import MAX_PAYLOAD_BYTES

from .binding import check_ports_free
from .config import LabConfig, check_watchdog
from .console import as_console
from .housekeeping import format_ids
from .keyfiles import KeyRing, load_keyring, writable_by_others
from .replay_source import ReplaySource
from .sensors import SensingModel
from .server import Hub, RunTemplate
from .sources import MotionCaptureSource, PoseSource


def build_hub(config: LabConfig, log: Callable[[str], None] = print, context: Optional[zmq.Context] = None,
              recorder=None, scenario=None) -> Hub:
    """``scenario`` (sim source only) replaces loading ``source.scenario``, e.g. with overrides applied."""
    context = context or zmq.Context.instance()
    log = as_console(log)       # what is said while building goes into the log too, once the hub opens it
    seed = None
    scenario_ref = None          # the scenario's file or built-in name, when loaded here from the config
    if config.source.type == "sim" and scenario is None:
        from sim_backend.scenario import load_scenario

        scenario_ref = config.source.scenario
        try:
            scenario = load_scenario(config.source.scenario)
        except ConfigError as err:
            # The lab config's field, and for a field inside the scenario file, which file and field.
            problem = err.problem if err.field == "scenario" else f"{config.source.scenario}: {err}"
            if problem.startswith("no such file") and not Path(config.source.scenario).is_absolute():
                problem += f" (a lab config's paths are relative to the folder the hub is started in, {Path.cwd()})"
            raise ConfigError("source.scenario", problem) from None
    # Checked before the source connects: with a motion-capture system that does not answer, a missing
    # run.behaviour or key folder was said only after the connection timed out.
    run = run_template(config, scenario, scenario_ref)
    if recorder is None and config.record is not None:
        record_path(config)         # a bad name ({tim}, an existing file), said before a connection's timeout
    net = config.network            # likewise a port another process (a hub left running) listens on
    check_ports_free(net.bind, [("robot_port", net.robot_port), ("control_port", net.control_port)])
    keyring = None if config.security.insecure else load_keyring(Path(config.security.keys))
    if keyring:
        folder = Path(config.security.keys)
        for warning in filter(None, (exposed_secret(folder / "hub.key_secret"), writable_by_others(folder))):
            log(f"hub: warning: {warning}")
    if config.source.type == "sim":
        from .sim_source import SimSource, not_simulated_here

        source: PoseSource = SimSource(scenario, config.source.seed, config.source.frame_hz)
        seed = source.hub_seed
        log(f"hub: source {source.description}: the simulator plays the robots and the motion capture")
        for line in not_simulated_here(scenario):
            log(f"hub: warning: {line}")
    elif config.source.type == "motioncapture":
        src = config.source
        source = MotionCaptureSource(context, src.system, src.options, src.bodies, src.up_axis, log,
                                     connect_timeout_s=src.connect_timeout_s)
    else:
        source = ReplaySource(config.source.file, config.source.rate, log)
    try:
        ids = robot_ids(config, source)
        say_untracked_bodies(config, ids, log)
        if config.source.type == "sim":
            say_idle_sim_robots(source.robot_ids(), ids, log)
        if isinstance(source, ReplaySource):
            say_unplaced_replay_robots(source, ids, log)
        if keyring is not None:
            say_missing_keys(ids, keyring, log, ids_from=lab_ids_origin(config))
        if config.relay.max_bytes < MAX_PAYLOAD_BYTES:
            # The agents do not know this limit: a behaviour tried in `sim run` (8192 bytes) sends as it did there.
            log(f"hub: relay.max_bytes is {config.relay.max_bytes}: a broadcast over it is dropped here, and its "
                f"behaviour is not told (in `khepri sim run` a payload may be {MAX_PAYLOAD_BYTES} bytes; the "
                "transport's tuple-space messages are up to 6000)")
        if recorder is None and config.record is not None:
            path = record_path(config)
            recorder = open_recorder(path, {"source": source.description, "behaviour": run.behaviour},
                                     next_name_if_taken="{time}" in str(config.record))
    except Exception:
        source.close()
        raise
    progress = None
    if config.source.type == "sim":       # the hub holds the world: it can tell how the object is doing
        from .progress import RunProgress

        progress = RunProgress(run.behaviour, scenario, source.world, log)
    return Hub(config, source, ids, run, sensing_model(config, scenario), relay_drop(config, scenario), seed=seed,
               keyring=keyring, recorder=recorder, log=log, context=context, progress=progress)


def robot_ids(config: LabConfig, source: PoseSource):
    known = source.robot_ids()
    if config.robots is None:
        if known is None:
            raise ConfigError("robots", "list the robot ids, e.g. robots: [0, 1, 2]")
        return known
    if config.source.type == "sim":
        check_sim_robots(config.robots, known, source.description)
    return list(config.robots)


def say_untracked_bodies(config: LabConfig, ids: List[int], log: Callable[[str], None]) -> None:
    """Bodies of robots not in this run are fine (four of six robots out today), but said: it may be a typo."""
    if config.source.type != "motioncapture":
        return
    others = [f"{name} (robot {rid})" for name, rid in config.source.bodies.items() if rid not in ids]
    if others:
        log(f"hub: source.bodies {', '.join(others)}: not in robots, so not served (their poses are ignored)")


def say_idle_sim_robots(scenario_ids: List[int], ids: List[int], log: Callable[[str], None]) -> None:
    """The scenario's robots left off ``robots`` stay in the simulated world, with no agent: said at start, since
    they are still there for the others' IR and the object, like robots switched off on the lab floor."""
    idle = [rid for rid in scenario_ids if rid not in set(ids)]
    if idle:
        several = len(idle) > 1
        log(f"hub: robot{'s' if several else ''} {format_ids(idle)} of the scenario {'are' if several else 'is'} not "
            f"in robots: {'they stay' if several else 'it stays'} in the world, still, with no agent (the others' "
            f"IR sees {'them' if several else 'it'}; range and bearing and the radio do not)")


def say_unplaced_replay_robots(source: ReplaySource, ids: List[int], log: Callable[[str], None]) -> None:
    """A lab robot the log never places would be held for the whole replay, with nothing said at start."""
    missing, scanned_s = source.never_placed(ids)
    if not missing:
        return
    several = len(missing) > 1
    who = (f"robot{'s' if several else ''} {', '.join(map(str, missing))} of this lab (robots) "
           f"ha{'ve' if several else 's'}")
    has = (f"; the log places {format_ids(source.placed_ids)}" if source.placed_ids
           else "; the log places no robot")
    if scanned_s is not None:      # a long log, looked through only so far
        log(f"hub: warning: {who} no pose in the first {scanned_s:.0f} s of {source.path} (source.file): "
            f"{'they are' if several else 'it is'} held until the replay places {'them' if several else 'it'}"
            f"{has.replace('the log places', 'so far the log places')}")
    else:
        log(f"hub: warning: {who} no pose in {source.path} (source.file): the replay never places "
            f"{'them' if several else 'it'}, so {'they stay' if several else 'it stays'} held{has}")


def say_missing_keys(ids: List[int], keyring: KeyRing, log: Callable[[str], None], ids_from: str = "robots") -> None:
    """A lab robot whose key the hub does not hold can never connect, and the hub never hears from it (its
    handshake is refused before any message): said once at start, not left to a robot that stays silent."""
    keyed = set(keyring.robots.values())
    missing = [rid for rid in ids if rid not in keyed]
    if missing:
        which = ", ".join(map(str, missing))
        several = len(missing) > 1
        log(f"hub: robot{'s' if several else ''} {which} of this lab ha{'ve' if several else 's'} no key in "
            f"{keyring.folder / 'robots'}, so cannot connect (add {'their keys' if several else 'its key'} with "
            f"`khepri keys add {keyring.folder} --robots {robots_option(missing)}`, which leaves the other keys "
            f"as they are, or take {'them' if several else 'it'} off {ids_from})")
    if not keyring.operators:
        log(f"hub: no operator key in {keyring.folder / 'operators'}: `khepri ctl` cannot reach this hub (add one "
            f"with `khepri keys add {keyring.folder} --operator NAME`; the hub accepts it without a restart)")


def lab_ids_origin(config: LabConfig) -> str:
    """Where the lab's robot ids come from, for "take it off ...": the robots list, else the source's own."""
    if config.robots is not None:
        return "robots"
    return {"motioncapture": "source.bodies", "sim": "the scenario (or list robots)"}.get(
        config.source.type, "robots")


def robots_option(ids: List[int]) -> str:
    """``keys init --robots`` for exactly these ids: one number alone would be a count (3: robots 0, 1, 2)."""
    return ",".join(map(str, ids)) + ("," if len(ids) == 1 else "")


def check_sim_robots(wanted: List[int], scenario_ids: List[int], description: str) -> None:
    """The sim source's world has only the scenario's robots: any other id would fail in the physics mid-run."""
    extra = sorted(set(wanted) - set(scenario_ids))
    if extra:
        raise ConfigError("robots", f"{description} has robots {scenario_ids[0]}..{scenario_ids[-1]}; "
                          f"no robot {', '.join(map(str, extra))}")


def run_template(config: LabConfig, scenario, scenario_ref: Optional[str] = None) -> RunTemplate:
    """What ``ctl start`` runs. ``scenario_ref``: how the user named the scenario (its file), for its errors; else
    its ``name:``."""
    run = config.run
    name = run.behaviour or (scenario.behaviour if scenario is not None else None)
    if name is None:
        raise ConfigError("run.behaviour", "name the behaviour to run (e.g. aggregate)")
    cls = get_behaviour(name, "run.behaviour")
    params: Dict[str, Any] = {}
    if scenario is not None and name == scenario.behaviour:
        from sim_backend.runner import mission_params

        # run.params go on top: replacing them dropped the scenario's mission (transport's path and object
        # estimate), and the robots idled for ever after tuning one gain.
        params = mission_params(cls, scenario)
    params.update(run.params or {})
    built = build_params(cls, params, "run.params")     # reject bad parameters here, not on every robot
    if scenario is not None and scenario.object is None and getattr(built, "object_estimate", "") is None:
        # The lab field would name a key the user of `khepri sil` never wrote: name the scenario's.
        raise ConfigError("object", f"{scenario.name} has none, and the {name} behaviour needs to know where one "
                                    "starts to run through a hub (`khepri hub` or `khepri sil`): give the scenario "
                                    "an object (a lab config may give run.params.object_estimate instead); "
                                    "`khepri sim run` runs it as it is, warning that no cage will close")
    check_required(name, built)
    if scenario is not None and "path" in (run.params or {}):
        check_path_inside_walls(scenario, getattr(built, "path", None) or [])
    spec = RobotSpec() if scenario is None else RobotSpec(max_wheel_speed_m_s=scenario.robots.max_wheel_speed_m_s)
    control_hz = scenario.physics.control_hz if scenario is not None else run.control_hz
    if scenario is not None:       # the config checked watchdog_s against run.control_hz, which sim replaces
        check_watchdog(config.watchdog_s, control_hz, f"{scenario_ref or scenario.name}: physics.control_hz",
                       config.watchdog_written, instead="; `khepri sim run` runs the scenario as it is")
    seed = config.source.seed if config.source.seed is not None else getattr(scenario, "seed", None)
    return RunTemplate(name, params, control_hz, lockstep=config.source.type == "sim" and config.source.lockstep,
                       spec=dict(spec.__dict__), seed=seed)


def check_path_inside_walls(scenario, path) -> None:
    """``run.params.path`` for the sim source: every waypoint inside the scenario's walls, as `sim run` requires
    of a scenario's own path (outside, the run could only fail, at its time limit)."""
    from sim_backend.scenario import check_inside_walls

    if scenario.arena.walls is None:
        return
    for i, waypoint in enumerate(path):
        check_inside_walls(scenario.arena.walls, f"run.params.path[{i}]", float(waypoint[0]), float(waypoint[1]),
                           whose=f"{scenario.name}'s")


def check_required(behaviour: str, params: Any) -> None:
    """A behaviour's Params may name what a run cannot do without (``REQUIRED_FOR_A_RUN``: field -> why)."""
    for name, why in getattr(params, "REQUIRED_FOR_A_RUN", {}).items():
        if getattr(params, name, None) is None:
            raise ConfigError(f"run.params.{name}", f"the {behaviour} behaviour needs it: {why}")


def sensing_model(config: LabConfig, scenario) -> SensingModel:
    s = config.sensing
    model = SensingModel()
    if scenario is not None:
        c, sens = scenario.comm, scenario.sensors
        model = SensingModel(c.range_m, c.range_noise_m, c.bearing_noise_rad, sens.pose_noise_m, sens.pose_noise_rad)
    for name in ("range_m", "range_noise_m", "bearing_noise_rad", "pose_noise_m", "pose_noise_rad"):
        if getattr(s, name) is not None:
            setattr(model, name, getattr(s, name))
    return model


def relay_drop(config: LabConfig, scenario) -> float:
    if config.relay.drop is not None:
        return config.relay.drop
    return scenario.comm.drop if scenario is not None else 0.0


BRACES = re.compile(r"\{[^{}]*\}")


def record_path(config: LabConfig, now: Optional[float] = None) -> Path:
    """The log file for ``record``: ``{time}`` in it becomes the local start time (``logs/run-{time}.mcap`` ->
    ``logs/run-20261121-201502.mcap``). An existing file is refused: the hub never writes over a log (an
    earlier run's, the one being replayed, or one another hub is still writing)."""
    record = str(config.record)
    for found in BRACES.finditer(record):
        braces = found.group(0)
        if record[found.start() - 1:found.start()] == "{" and record[found.end():found.end() + 1] == "}":
            # a template habit (Jinja, str.format escapes): the file name kept the outer braces
            raise ConfigError("record", f"{{{braces}}}: write {braces} with single braces "
                                        "(e.g. logs/run-{time}.mcap)")
        if braces != "{time}":      # a typo ({tim}, {Time}) named one fixed file: the next start stopped at `exists`
            raise ConfigError("record", f"{braces} is not something the hub fills in: only {{time}} is (the start "
                                        "time, e.g. logs/run-{time}.mcap)")
    unpaired = record.replace("{time}", "")
    if "{" in unpaired or "}" in unpaired:       # 'x-{time.mcap' was kept in the file name as written
        raise ConfigError("record", f"{record}: a {{ or }} without its pair; only {{time}} is filled in (e.g. "
                                    "logs/run-{time}.mcap)")
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(now))
    text = str(config.record).replace("{time}", stamp)
    folder = folder_not_file(text)
    if folder:
        raise ConfigError("record", f"{folder}: give the log's file name, e.g. {Path(text) / 'run-{time}.mcap'}")
    path = Path(text)
    if config.source.type == "replay" and path.exists() and path.resolve() == Path(config.source.file).resolve():
        raise ConfigError("record", f"{path} is the log being replayed (source.file): recording would erase it; "
                          "name another file")
    if "{time}" in str(config.record):
        path = first_free(path)      # two hubs started within one second (two labs, a script) each get a log
    if path.exists() or path.is_symlink():
        raise ConfigError("record", f"{path} exists (an earlier run's log, or one a hub is writing): the hub does "
                          "not write over a log. Remove it, name another file, or put {time} in the name "
                          "(e.g. logs/run-{time}.mcap)")
    return path


def first_free(path: Path, tries: int = 100) -> Path:
    """``path``, or ``run-20261121-201502-2.mcap`` and on for the first name no file has (``path`` if none is)."""
    for n in range(1, tries):
        candidate = path if n == 1 else path.with_name(f"{path.stem}-{n}{path.suffix}")
        if not (candidate.exists() or candidate.is_symlink()):
            return candidate
    return path


def open_recorder(path: Path, metadata: Dict[str, Any], next_name_if_taken: bool = False):
    """``next_name_if_taken``: a {time} name another hub took between record_path's look and the open (two hubs
    started in the same instant) becomes the next free one, as record_path gives one taken earlier."""
    try:
        from hub.recording import LogExistsError, Recorder
    except ImportError as err:
        raise ConfigError("record", f"recording is not available in this installation ({err})") from None
    folder = Path(path).parent
    blocker = next((p for p in (folder, *folder.parents) if p.exists() and not p.is_dir()), None)
    if blocker is not None:      # mkdir would say "File exists", which points at the wrong problem
        raise ConfigError("record", f"cannot make the folder {folder}: {blocker} is a file, not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        for _ in range(10 if next_name_if_taken else 0):
            try:
                return Recorder(path, flush_period_s=1.0, metadata={k: str(v) for k, v in metadata.items()},
                                exclusive=True)
            except LogExistsError:
                path = first_free(path)
        return Recorder(path, flush_period_s=1.0, metadata={k: str(v) for k, v in metadata.items()}, exclusive=True)
    except OSError as err:                 # a folder it may not make (permissions, a read-only disk)
        raise ConfigError("record", f"cannot make the folder {folder}: {err.strerror or err}") from None
    except ConfigError as err:             # the Recorder's LogError names the file: say it is the record option's
        raise ConfigError("record", str(err)) from None
