"""The lab config (``khepri hub --config lab.yaml``): validated records with errors that name the field.

Every key is documented in docs/lab.md; ``hub/examples/lab.yaml`` is a commented example.
"""
from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

from hub.mocap_options import DEGENERATE_QUATERNION, check_mock_options, did_you_mean
from onboard.config import ConfigError, as_written, check_range, check_seed, from_mapping, is_whole_number, join
from onboard.filekinds import LAB_CONFIG, wrong_kind
from onboard.protocol import IDLE_TELEMETRY_HZ, MAX_CONTROL_HZ, MAX_ROBOT_ID
from onboard.yamlfile import read_yaml

SOURCE_TYPES = ("sim", "motioncapture", "replay")
DEFAULT_WATCHDOG_S = 0.3
MAX_WATCHDOG_S = 10.0          # a robot silent longer than this is gone, whatever its rate
# The source fields each type reads (``type``, ``seed`` and ``stale_s`` are every type's: the seed also seeds the
# agents' ``random``): a field of another type would be ignored without a word, e.g. a Vicon hostname under a
# sim source, which then runs the simulation.
SOURCE_FIELDS = {"sim": ("scenario", "lockstep", "frame_hz", "reset_each_run"),
                 "motioncapture": ("system", "options", "bodies", "up_axis", "connect_timeout_s"),
                 "replay": ("file", "rate", "reset_each_run")}
UP_AXES = ("z", "y")


MIN_REPLAY_RATE = 0.001       # source.rate: a thousandth of real time, 17 minutes for a second of the log


@dataclass
class SourceConfig:
    """Where poses come from. ``sim``: the pymunk world of ``scenario``; ``motioncapture``: the motioncapture
    library (``system`` vicon, qualisys, optitrack, vrpn, mock, ...); ``replay``: a recorded MCAP log."""

    type: str = "sim"
    scenario: str = "lab-6"                 # sim: built-in name or YAML file
    seed: Optional[int] = None              # sim: overrides the scenario's seed
    lockstep: bool = False                  # sim: advance physics only when every agent answered
    frame_hz: float = 50.0                  # sim, real time: pose frames per second (physics in between)
    # sim: each run starts at the scenario's start (false: where the last ended); replay: at the log's start
    reset_each_run: bool = True
    system: str = "mock"                    # motioncapture: the library's backend name
    options: Dict[str, Any] = field(default_factory=dict)   # motioncapture: passed to connect(), as strings
    # motioncapture: rigid body name -> robot id (checked by check_robot_id, whose message names the range)
    bodies: Dict[str, Any] = field(default_factory=dict)
    up_axis: str = "z"                      # motioncapture: which axis of the mocap frame points up
    stale_s: float = 0.1                    # a body not seen for this long has no pose
    connect_timeout_s: float = 10.0         # motioncapture: give up on a system that does not answer
    file: Optional[str] = None              # replay: the MCAP log
    rate: float = 1.0                       # replay: playback speed (2 = twice as fast)

    def validate(self, where: str) -> None:
        if self.type not in SOURCE_TYPES:
            raise ConfigError(join(where, "type"),
                              f"must be one of {', '.join(SOURCE_TYPES)} (got {as_written(self.type)})")
        if self.up_axis not in UP_AXES:
            raise ConfigError(join(where, "up_axis"), f"must be z or y (got {as_written(self.up_axis)})")
        check_range(join(where, "frame_hz"), self.frame_hz, 0.0, 1000.0, low_open=True)
        check_range(join(where, "stale_s"), self.stale_s, 0.0, low_open=True)
        check_range(join(where, "connect_timeout_s"), self.connect_timeout_s, 0.0, 300.0, low_open=True)
        # Below 0.001 a minute's log takes days: a typo (1e-9 took 190 years for 6 s), not a slow replay.
        check_range(join(where, "rate"), self.rate, MIN_REPLAY_RATE, 100.0)
        if self.seed is not None:
            check_seed(join(where, "seed"), self.seed)
        if self.type == "motioncapture" and not self.bodies:
            raise ConfigError(join(where, "bodies"), "map each rigid body name to a robot id, e.g. {kh0: 0}")
        # The SDK names bodies with strings: a YAML key like 7 must match the body "7".
        self.bodies = {str(name): rid for name, rid in self.bodies.items()}
        first_body: Dict[Any, str] = {}
        for name, rid in self.bodies.items():
            check_robot_id(join(join(where, "bodies"), name), rid)
            if rid in first_body:
                raise ConfigError(join(join(where, "bodies"), name),
                                  f"robot {rid} is already the body {as_written(first_body[rid])}: one body per robot")
            first_body[rid] = name
        check_option_values(join(where, "options"), self.options)
        if self.type == "motioncapture" and self.system == "mock":
            check_mock_options(join(where, "options"), self.options)
        if self.type == "motioncapture" and self.system == "mock" and "frequency" in self.options:
            # The mock backend parses it in C++ (a bad one is a traceback there) and spins without a wait at
            # 0 or below, starving the hub.
            check_mock_frequency(join(join(where, "options"), "frequency"), self.options["frequency"])
        if self.type == "motioncapture" and self.system == "mock" and "rigid_bodies" in self.options:
            # The mock skips an entry it cannot parse without a word: the robot would just never be placed.
            bodies = mock_bodies(join(join(where, "options"), "rigid_bodies"), self.options["rigid_bodies"])
            # The mock would keep a space after ';' in the name, and "kh1" would match no body.
            self.options["rigid_bodies"] = ";".join(entry for _, entry in bodies)
            names = [name for name, _ in bodies]
            for name in self.bodies:
                if name not in names:
                    listed = ", ".join(map(repr, names))     # quoted: 'kh0 ' with its space showed as kh0
                    raise ConfigError(join(join(where, "bodies"), name),
                                      f"the mock has no body {as_written(name)} (its rigid_bodies: {listed})")
        if self.type == "replay" and not self.file:
            raise ConfigError(join(where, "file"), "a replay source needs file: <log.mcap>")


def check_option_values(where: str, options: Dict[str, Any]) -> None:
    """Each option goes to the library as a string: a list or mapping would be written out as its Python repr
    (the whole of it: an alias bomb's took minutes), which no backend reads."""
    for name, value in options.items():
        if isinstance(value, (list, tuple, dict)):
            raise ConfigError(join(where, name), f"must be a string or a number, passed to the motion-capture "
                                                 f"library as text (got {as_written(value)})")


_NUMBER = r"\s*[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?\s*"
MOCK_BODY = re.compile(rf"([^\s(),;][^(),;]*?)\(({_NUMBER}(?:,{_NUMBER}){{6}})\)")


def mock_bodies(where: str, value: Any) -> List[Tuple[str, str]]:
    """(name, entry) of each of the mock's ``rigid_bodies``: ``name(x,y,z,qw,qx,qy,qz)`` entries separated by
    ``;``, trimmed."""
    entries = [entry.strip() for entry in str(value).split(";") if entry.strip()]
    bodies = []
    for i, entry in enumerate(entries):
        match = MOCK_BODY.fullmatch(entry)
        if not match:
            raise ConfigError(where, f"entry {i + 1} ({as_written(entry)}) must be name(x,y,z,qw,qx,qy,qz): a name, "
                                     "then 7 numbers in brackets; entries are separated by ;")
        qw, qx, qy, qz = (float(v) for v in match.group(2).split(",")[3:])
        if qw * qw + qx * qx + qy * qy + qz * qz < DEGENERATE_QUATERNION:
            raise ConfigError(where, f"entry {i + 1} ({as_written(entry)}): its quaternion qw,qx,qy,qz is not a "
                                     "rotation (1,0,0,0 faces +x; 0.7071,0,0,0.7071 faces +y)")
        if any(name == match.group(1) for name, _ in bodies):     # the mock took the first, said nothing
            raise ConfigError(where, f"entry {i + 1} ({as_written(entry)}): the body {as_written(match.group(1))} is "
                                     "given twice")
        bodies.append((match.group(1), entry))
    if not bodies:
        raise ConfigError(where, "has no body: give name(x,y,z,qw,qx,qy,qz) entries separated by ;")
    return bodies


def check_mock_frequency(where: str, value: Any) -> None:
    text = str(value).strip()
    if isinstance(value, bool) or not is_whole_number(text) or not 1 <= int(text) <= 1000:
        raise ConfigError(where, f"must be a whole number of frames per second, 1 to 1000 (got {as_written(value)})")


# The hub's frames are the agents' heartbeat: they come at most 1.5 downlink periods apart (a late motion-capture
# frame waits half a period), and an agent's watchdog stops the wheels after 0.25 s (--watchdog, at most 0.3 s)
# without one. 10 Hz keeps the longest gap (0.15 s) well inside it; at 2 Hz the robots stopped between frames.
MIN_DOWNLINK_HZ = 10.0


@dataclass
class NetworkConfig:
    bind: str = "*"                 # interface to listen on ("*" = all IPv4, "localhost" = both loopbacks)
    robot_port: int = 5560          # agents' DEALER sockets connect here (0: any free port)
    control_port: int = 5561        # khepri ctl connects here (0: any free port)
    downlink_hz: float = 20.0       # frames per second to each robot (latest data; spread over robots)

    def validate(self, where: str) -> None:
        for name in ("robot_port", "control_port"):
            check_range(join(where, name), getattr(self, name), 0, 65535)
        if self.robot_port == self.control_port != 0:
            raise ConfigError(join(where, "control_port"),
                              f"must differ from the robot port (both are {self.robot_port})")
        check_range(join(where, "downlink_hz"), self.downlink_hz, 1.0, 1000.0)
        if self.downlink_hz < MIN_DOWNLINK_HZ:
            raise ConfigError(join(where, "downlink_hz"), f"must be >= {MIN_DOWNLINK_HZ:g} (got {self.downlink_hz:g}): "
                              "frames can come 1.5 periods apart, and an agent stops its wheels after 0.25 s "
                              "without one, so slower frames stop the robots between every two")


@dataclass
class SecurityConfig:
    keys: str = "keys"              # folder made by `khepri keys init`
    insecure: bool = False          # true: no encryption, no authentication (loopback demos only)


@dataclass
class SensingConfig:
    """Virtual sensors. ``None`` means: take it from the scenario (sim source) or the default shown."""

    range_m: Optional[float] = None             # d_C; default 3.0
    range_noise_m: Optional[float] = None       # default 0.01
    bearing_noise_rad: Optional[float] = None   # default 0.02
    pose_noise_m: Optional[float] = None        # extra noise on relayed poses; default 0 (mocap is real)
    pose_noise_rad: Optional[float] = None      # default 0

    def validate(self, where: str) -> None:
        for name in ("range_m", "range_noise_m", "bearing_noise_rad", "pose_noise_m", "pose_noise_rad"):
            value = getattr(self, name)
            if value is not None:
                check_range(join(where, name), value, 0.0, low_open=name == "range_m")


@dataclass
class RelayConfig:
    drop: Optional[float] = None    # probability a message to one receiver is lost; default 0
    # Messages waiting per receiver; the oldest is dropped beyond. As many as the agent (and the simulator)
    # keeps between two steps (Radio.INBOX_LIMIT): 64 dropped 11 % of the messages of 25 robots sending 3
    # each per step, which the simulator delivers all of.
    queue: int = 256
    max_bytes: int = 8192           # largest payload (compact JSON)

    def validate(self, where: str) -> None:
        if self.drop is not None:
            check_range(join(where, "drop"), self.drop, 0.0, 1.0)
        check_range(join(where, "queue"), self.queue, 1, 100_000)
        check_range(join(where, "max_bytes"), self.max_bytes, 2, 8192)


@dataclass
class RunConfig:
    """What ``khepri ctl start`` runs. For the sim source, unset fields come from the scenario."""

    behaviour: Optional[str] = None
    params: Optional[Dict[str, Any]] = None
    control_hz: float = 10.0
    autostart: bool = False          # start as soon as the hub is up (SIL)

    def validate(self, where: str) -> None:
        check_range(join(where, "control_hz"), self.control_hz, 0.0, MAX_CONTROL_HZ, low_open=True)


@dataclass
class LabConfig:
    source: SourceConfig = field(default_factory=SourceConfig)
    robots: Optional[List[int]] = None          # robot ids; default: the bodies' ids, or 0..N-1 for sim
    network: NetworkConfig = field(default_factory=NetworkConfig)
    security: SecurityConfig = field(default_factory=SecurityConfig)
    sensing: SensingConfig = field(default_factory=SensingConfig)
    relay: RelayConfig = field(default_factory=RelayConfig)
    run: RunConfig = field(default_factory=RunConfig)
    geofence: Optional[Tuple[float, float, float, float]] = None   # [xmin, ymin, xmax, ymax], metres
    watchdog_s: float = DEFAULT_WATCHDOG_S   # hub side: an agent silent this long is "not connected"
    record: Optional[str] = None    # MCAP file for everything in and out
    # Not a key: whether watchdog_s was written or is the default. A rate too fast for the default is then the
    # rate's to say (the sim source's rate is the scenario's, checked again in hub/factory.py).
    watchdog_written: bool = field(default=True, init=False, repr=False)

    def validate(self, where: str) -> None:
        if self.geofence is not None:
            xmin, ymin, xmax, ymax = self.geofence
            if xmax <= xmin or ymax <= ymin:
                raise ConfigError("geofence", f"must be [xmin, ymin, xmax, ymax] with min < max (got "
                                              f"{[float(v) for v in self.geofence]})")
        check_range("watchdog_s", self.watchdog_s, 0.0, MAX_WATCHDOG_S, low_open=True)
        if not self.security.insecure and not str(self.security.keys).strip():
            raise ConfigError("security.keys", "is empty: name the key folder `khepri keys init` made (default keys)")
        if self.record is not None and not str(self.record).strip():
            raise ConfigError("record", "is empty: name the MCAP file (e.g. logs/run-{time}.mcap), or leave it out")
        if self.robots is not None:
            if not self.robots:
                raise ConfigError("robots", "is empty: list the robot ids of this lab, e.g. robots: [0, 1, 2] "
                                            "(or leave it out: the bodies' ids, or the scenario's robots)")
            for i, rid in enumerate(self.robots):
                check_robot_id(f"robots[{i}]", rid)
            if len(set(self.robots)) != len(self.robots):
                twice = sorted({rid for rid in self.robots if self.robots.count(rid) > 1})
                raise ConfigError("robots", f"lists robot id{'s' if len(twice) > 1 else ''} "
                                            f"{', '.join(map(str, twice))} twice")
            if self.source.type == "motioncapture":
                check_every_robot_has_a_body(self.robots, self.source.bodies)


# The hub counts a robot connected while it heard from it within watchdog_s, and agents speak once per loop
# step (telemetry). Within one or two periods, one late step turns the robot "not connected" and back: at
# watchdog_s 0.05 and 10 Hz telemetry, the flag flapped all the time (and with the sim source, the wheels).
WATCHDOG_TELEMETRY_PERIODS = 3
# So the slowest loop a hub serves: a scenario may run slower in `khepri sim run` (physics.control_hz 0.1), and a
# hub then asked for a watchdog_s it refuses ("add watchdog_s: 30", then "watchdog_s: must be <= 10").
MIN_HUB_CONTROL_HZ = WATCHDOG_TELEMETRY_PERIODS / MAX_WATCHDOG_S


def min_watchdog_s(control_hz: float) -> float:
    """The shortest ``watchdog_s`` for agents looping at ``control_hz`` (and at IDLE_TELEMETRY_HZ without a run);
    never above MAX_WATCHDOG_S (a rate too slow for that is check_watchdog's to say)."""
    return min(MAX_WATCHDOG_S, WATCHDOG_TELEMETRY_PERIODS / min(control_hz, IDLE_TELEMETRY_HZ))


def check_hub_rate(control_hz: float, rate_field: str, instead: str = "") -> None:
    """Refuse a loop rate slower than any watchdog_s the hub takes allows (MIN_HUB_CONTROL_HZ); ``instead``: what
    can run it."""
    if control_hz < MIN_HUB_CONTROL_HZ - 1e-9:
        raise ConfigError(rate_field, f"{control_hz:g} Hz is too slow to run through a hub: it takes "
                          f"{MIN_HUB_CONTROL_HZ:g} Hz or faster (agents speak once per loop step, and the hub counts a "
                          f"robot silent for watchdog_s, at most {MAX_WATCHDOG_S:g} s, as not connected: "
                          f"{WATCHDOG_TELEMETRY_PERIODS} steps must fit in it){instead}")


def check_watchdog(watchdog_s: float, control_hz: float, rate_field: str, written: bool = True,
                   instead: str = "") -> None:
    """``written``: watchdog_s is in the config; else it is the default, and the rate is what the user set."""
    check_hub_rate(control_hz, rate_field, instead)
    least = min_watchdog_s(control_hz)
    if watchdog_s < least - 1e-9 and not written:     # the error named a key the config did not have
        raise ConfigError(rate_field, f"{control_hz:g} Hz needs a watchdog_s of at least {least:g} s, and watchdog_s "
                          f"is {watchdog_s:g} s by default: add watchdog_s: {least:g} to the config (agents send "
                          f"telemetry once per loop, and the hub counts a robot silent for watchdog_s as not "
                          f"connected)")
    if watchdog_s < least - 1e-9:
        raise ConfigError("watchdog_s", f"must be at least {least:g} s (got {watchdog_s:g}): agents send telemetry "
                          f"at {min(control_hz, IDLE_TELEMETRY_HZ):g} Hz ({rate_field} {control_hz:g}, and "
                          f"{IDLE_TELEMETRY_HZ:g} Hz without a run), so a shorter watchdog_s shows robots as "
                          f"connected and not connected in turn; give at least {WATCHDOG_TELEMETRY_PERIODS} "
                          "telemetry periods")


def check_every_robot_has_a_body(robots: List[int], bodies: Dict[str, int]) -> None:
    """A robot without a rigid body would never get a pose: the hub would hold it for the whole run."""
    tracked = set(bodies.values())
    for i, rid in enumerate(robots):
        if rid not in tracked:
            raise ConfigError(f"robots[{i}]", f"robot {rid} has no rigid body in source.bodies (add e.g. "
                                              f"kh{rid}: {rid} there, or take it off this list)")


def check_robot_id(where: str, value: Any) -> int:
    """A robot id the wire protocol can carry. ``source.bodies`` leaves its values to this check (its message
    names the range), so a string, a float or a boolean (YAML ``true``) is refused here too."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_ROBOT_ID:
        raise ConfigError(where, f"must be an integer robot id 0..{MAX_ROBOT_ID} (got {as_written(value)})")
    return value


def parse_config(data: Any) -> LabConfig:
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError("", f"a lab config must be a mapping of keys (got {type(data).__name__})")
    check_unknown_source_keys(data.get("source"))
    config = from_mapping(LabConfig, data, "")
    config.watchdog_written = "watchdog_s" in data
    if config.source.type != "sim":          # the sim source's agents run at the scenario's rate: build_hub
        check_watchdog(config.watchdog_s, config.run.control_hz, "run.control_hz", config.watchdog_written)
    check_source_fields(data.get("source") or {}, config.source.type)
    check_run_fields(data.get("run") or {}, config.source.type)
    source = config.source
    if source.type == "motioncapture" and source.system == "mock" and "rigid_bodies" not in source.options:
        # The mock then has no bodies at all: the hub ran, saying only that no robot was in the frames.
        raise ConfigError("source.options.rigid_bodies", "is required for the mock, which has no bodies without it: "
                          "give name(x,y,z,qw,qx,qy,qz) entries separated by ;, one per body in source.bodies, e.g. "
                          "kh0(0,0,0.05,1,0,0,0)")
    return config


def check_unknown_source_keys(source: Any) -> None:
    """An unknown ``source`` key, said with the keys of that source's type (the loader listed all 14 of every
    type, for `rat:` under a replay, which takes 5) and the nearest of them."""
    kind = source.get("type", "sim") if isinstance(source, dict) else None
    if not isinstance(kind, str) or kind not in SOURCE_FIELDS:
        return                       # not a mapping, or an unknown type: the loader's own error says it
    known = {f.name for f in dataclasses.fields(SourceConfig)}
    for name in source:
        if isinstance(name, str) and name not in known:
            takes = ["type", "seed", "stale_s", *SOURCE_FIELDS[kind]]
            raise ConfigError(join("source", name), f"unknown key (a {kind} source takes {', '.join(takes)})"
                              + did_you_mean(name, takes))


def check_source_fields(source: Dict[str, Any], kind: str) -> None:
    """Refuse a ``source`` field that ``kind`` does not read (the loader has refused unknown keys already)."""
    for name in source:
        owners = [other for other, names in SOURCE_FIELDS.items() if name in names]
        if owners and kind not in owners:
            raise ConfigError(join("source", name), f"is for a {' or '.join(owners)} source, and this one is "
                              f"type {kind}, which would ignore it; a {kind} source takes type, seed, stale_s, "
                              f"{', '.join(SOURCE_FIELDS[kind])} (remove it, or change source.type)")


def check_run_fields(run: Dict[str, Any], kind: str) -> None:
    """Refuse ``run.control_hz`` under a sim source: its agents loop at the scenario's ``physics.control_hz``
    (the physics steps in whole control periods), so a rate given here was ignored without a word."""
    if kind == "sim" and "control_hz" in run:
        raise ConfigError("run.control_hz", "is for a motioncapture or replay source, and this one is type sim, "
                          "which would ignore it: the scenario's physics.control_hz sets the agents' rate "
                          "(remove it, or set physics.control_hz in the scenario)")


def load_config(path: Path) -> LabConfig:
    data = read_yaml(path, "--config")
    if data is None:
        # Not the defaults: an empty file is more likely a failed copy than a wish for lab-6 in simulation.
        raise ConfigError("--config", f"{path} is empty; hub/examples/lab.yaml is a commented example "
                                      "(`khepri hub --demo` runs the defaults)")
    other = wrong_kind(data, LAB_CONFIG)     # a scenario given as the config: "description: unknown key" said
    if other:
        raise ConfigError(str(path), other)
    try:
        if isinstance(data, dict) and "source" in data and data["source"] in (None, {}):
            # Its lines commented out: taking the defaults would serve simulated lab-6 robots to a real lab.
            raise ConfigError("source", "is empty: give source.type (motioncapture, sim or replay) and its fields; "
                                        "hub/examples/lab.yaml shows each")
        return parse_config(data)
    except ConfigError as err:
        # The file is named too: a lab keeps several configs, and the hub's console scrolls.
        raise ConfigError(f"{path}: {err.field}" if err.field else str(path), err.problem) from None


def demo_config() -> LabConfig:
    """``khepri hub --demo``: the sim source on lab-6, loopback only, no keys."""
    return parse_config({"source": {"type": "sim", "scenario": "lab-6"},
                         "network": {"bind": "127.0.0.1"}, "security": {"insecure": True}})
