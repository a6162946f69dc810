"""Scenarios: YAML files describing a run, validated on load with errors that name the field.

The schema is documented in docs/scenarios.md. Built-in scenarios live in ``sim_backend/scenarios/``;
wherever a built-in name is accepted, a path to a YAML file works too.
"""
from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

from onboard.behaviour import build_params, get_behaviour, takes_param
from onboard.config import (
    MAX_NAME_LENGTH,
    ConfigError,
    as_written,
    check_range,
    check_seed,
    from_mapping,
    has_control_character,
    join,
)
from onboard.filekinds import SCENARIO, wrong_kind
from onboard.yamlfile import read_yaml

from .object_spec import ObjectSpec, check_extent, check_point, check_yaw

BUILTIN_DIR = Path(__file__).parent / "scenarios"


@dataclass
class SpawnArea:
    """Robots start uniformly in this rectangle, non-overlapping, with random headings."""

    x: Tuple[float, float] = (-1.2, -0.6)
    y: Tuple[float, float] = (-1.2, -0.6)

    def validate(self, where: str) -> None:
        for axis in ("x", "y"):
            low, high = getattr(self, axis)
            for i, value in enumerate((low, high)):
                check_extent(join(join(where, axis), i), value)
            if high < low:
                raise ConfigError(join(where, axis), f"must be [min, max] with min <= max (got [{low}, {high}])")


# Sensing is all pairs (N x N every step) and every robot hears every broadcast in range: 5000 robots would
# take hours per simulated minute. The bound turns a typo (count: 100000000000) into an error, not a hang.
MAX_ROBOTS = 5000
# A robot heavier than this is a typo (a KheperaIV is 0.54 kg); from about 1e150 kg pymunk gives NaN poses.
MAX_ROBOT_MASS_KG = 1e3


@dataclass
class RobotsSpec:
    count: int = 6
    spawn: SpawnArea = field(default_factory=SpawnArea)
    max_wheel_speed_m_s: float = 0.81   # KheperaIV spec top speed (K-Team); the HAL clamps to this
    # Tyre-floor friction coefficient. Rubber on a smooth lab floor is about 0.8-1.0; it bounds the force a
    # robot can push with to mu * m * g = 0.9 * 0.54 * 9.81 = 4.8 N.
    traction: float = 0.9
    mass_kg: float = 0.54               # KheperaIV with battery (K-Team spec, ~540 g)

    def validate(self, where: str) -> None:
        check_range(join(where, "count"), self.count, 1, MAX_ROBOTS)
        check_range(join(where, "max_wheel_speed_m_s"), self.max_wheel_speed_m_s, 0.0, 2.0, low_open=True)
        check_range(join(where, "traction"), self.traction, 0.0, 3.0, low_open=True)
        check_range(join(where, "mass_kg"), self.mass_kg, 0.0, MAX_ROBOT_MASS_KG, low_open=True)


MAX_DISTANCE_NOISE_M = 10.0          # noise std (m) of ranges and of poses
MAX_ANGLE_NOISE_RAD = 2.0 * math.pi  # noise std (rad) of bearings and headings: a full turn says nothing already


@dataclass
class CommSpec:
    range_m: float = 3.0            # d_C; the paper's simulations used 7 m
    drop: float = 0.0               # probability that a message to one receiver is lost
    latency_s: float = 0.0          # extra delivery delay (messages always arrive one control step later)
    range_noise_m: float = 0.01     # std of the range-and-bearing range error
    bearing_noise_rad: float = 0.02  # std of the range-and-bearing bearing error

    def validate(self, where: str) -> None:
        check_range(join(where, "range_m"), self.range_m, 0.0, low_open=True)
        check_range(join(where, "drop"), self.drop, 0.0, 1.0)
        check_range(join(where, "latency_s"), self.latency_s, 0.0, 10.0)
        # Upper bounds: far beyond any sensor, so that a typo (1e300) is said instead of a run that does nothing.
        check_range(join(where, "range_noise_m"), self.range_noise_m, 0.0, MAX_DISTANCE_NOISE_M)
        check_range(join(where, "bearing_noise_rad"), self.bearing_noise_rad, 0.0, MAX_ANGLE_NOISE_RAD)


@dataclass
class SensorsSpec:
    proximity_noise: float = 0.01   # std of additive noise on each normalised IR reading
    # Motion capture as the hub relays it: a few mm of noise, some latency, occasional dropouts.
    pose_noise_m: float = 0.003
    pose_noise_rad: float = 0.01
    pose_latency_s: float = 0.0
    pose_dropout: float = 0.0       # probability that a control step gets no new pose

    def validate(self, where: str) -> None:
        # Upper bounds as in CommSpec: a proximity reading lies in [0, 1], and a pose 10 s late is useless.
        for name, high in (("proximity_noise", 1.0), ("pose_noise_m", MAX_DISTANCE_NOISE_M),
                           ("pose_noise_rad", MAX_ANGLE_NOISE_RAD), ("pose_latency_s", 10.0)):
            check_range(join(where, name), getattr(self, name), 0.0, high)
        check_range(join(where, "pose_dropout"), self.pose_dropout, 0.0, 1.0)


MIN_CONTROL_HZ = 0.1     # a control period of at most 10 s


@dataclass
class PhysicsSpec:
    dt_s: float = 0.01        # physics step
    control_hz: float = 10.0  # behaviour rate (the authors' simulations ran at 10 Hz; the paper gives none)
    iterations: int = 10      # pymunk solver iterations

    def validate(self, where: str) -> None:
        # From 0.1 ms: a finer step is a typo, not a wish (1e-7 s would take a day for a 600 s run).
        check_range(join(where, "dt_s"), self.dt_s, 1e-4, 0.05)
        # At least 0.1 Hz: a slower rate (1e-300 passed the old "> 0") made a control period longer than any
        # run, which then ended after 0 steps as if it had succeeded.
        check_range(join(where, "control_hz"), self.control_hz, MIN_CONTROL_HZ, 100.0)
        check_range(join(where, "iterations"), self.iterations, 1, 100)
        steps = 1.0 / (self.control_hz * self.dt_s)
        if abs(steps - round(steps)) > 1e-6:
            raise ConfigError(join(where, "control_hz"), f"the control period must be a whole number of "
                              f"physics steps (dt_s={self.dt_s:g} gives {steps:g})")


@dataclass
class ArenaSpec:
    """Optional walls: an axis-aligned rectangle [xmin, ymin, xmax, ymax] in metres."""

    walls: Optional[Tuple[float, float, float, float]] = None

    def validate(self, where: str) -> None:
        if self.walls is not None:
            xmin, ymin, xmax, ymax = self.walls
            for i, value in enumerate(self.walls):
                check_extent(join(join(where, "walls"), i), value)
            if xmax <= xmin or ymax <= ymin:
                raise ConfigError(join(where, "walls"), "must be [xmin, ymin, xmax, ymax] with min < max")


@dataclass
class Fault:
    robot: int
    at_s: float
    # None: the robot fails for good. A number: its agent restarts instead, down this long (docs/scenarios.md).
    restart_after_s: Optional[float] = None

    def validate(self, where: str) -> None:
        check_range(join(where, "robot"), self.robot, 0)
        check_range(join(where, "at_s"), self.at_s, 0.0)
        if self.restart_after_s is not None:
            check_range(join(where, "restart_after_s"), self.restart_after_s, 0.0)

    def describe(self) -> str:
        """What happened, for result.json's faults_fired."""
        if self.restart_after_s is None:
            return f"robot {self.robot} failed at {self.at_s:g} s"
        return f"robot {self.robot}'s agent restarted at {self.at_s:g} s (down {self.restart_after_s:g} s)"


@dataclass
class Scenario:
    name: str
    behaviour: str = "transport"
    description: str = ""
    seed: int = 1
    robots: RobotsSpec = field(default_factory=RobotsSpec)
    object: Optional[ObjectSpec] = None
    path: List[Tuple[float, float, float]] = field(default_factory=list)   # [x, y, yaw_deg] per waypoint
    params: Dict[str, Any] = field(default_factory=dict)
    time_limit_s: float = 900.0
    comm: CommSpec = field(default_factory=CommSpec)
    sensors: SensorsSpec = field(default_factory=SensorsSpec)
    physics: PhysicsSpec = field(default_factory=PhysicsSpec)
    arena: ArenaSpec = field(default_factory=ArenaSpec)
    faults: List[Fault] = field(default_factory=list)

    def with_time_limit(self, seconds: Optional[float]) -> Scenario:
        """This scenario with the time limit a run actually gets (``--time-limit``, a study's ``time_limit_s``;
        None: its own). Given before the Simulation is built, so that its warnings (a fault that never fires)
        go by it."""
        return self if seconds is None else dataclasses.replace(self, time_limit_s=seconds)

    def validate(self, where: str) -> None:
        if not self.name.strip():
            raise ConfigError("name", "must not be empty")
        if "/" in self.name or "\\" in self.name or self.name.strip(".") == "" or has_control_character(self.name):
            raise ConfigError("name", "names the output folder: no / or \\, no control characters, and not only "
                                      f"dots (got {as_written(self.name)})")
        if len(self.name) > MAX_NAME_LENGTH:     # the folder name-seedN: "File name too long", blamed on --out
            raise ConfigError("name", f"names the output folder: at most {MAX_NAME_LENGTH} characters (got "
                                      f"{len(self.name)})")
        check_seed("seed", self.seed)
        check_range("time_limit_s", self.time_limit_s, 0.0, low_open=True)
        behaviour_cls = get_behaviour(self.behaviour, "behaviour")
        build_params(behaviour_cls, self.params, "params")
        if "path" in self.params and takes_param(behaviour_cls, "path"):
            # It would replace the mission the robots follow while the evaluator judges `path`, and skip its
            # checks (inside the walls, an object to move).
            raise ConfigError("params.path", "the path is the scenario's own key: move it to `path:` (the run "
                                             "is judged against that one)")
        if self.path and not takes_param(behaviour_cls, "path"):
            raise ConfigError("path", f"the {self.behaviour} behaviour does not follow a path (its params have "
                                      f"no 'path'): the path would be ignored")
        failing: Dict[int, int] = {}
        for i, fault in enumerate(self.faults):
            if fault.robot >= self.robots.count:
                raise ConfigError(f"faults[{i}].robot",
                                  f"no robot {fault.robot} (robots are 0..{self.robots.count - 1})")
            if fault.robot in failing:      # one fault per robot: a second is a typo for another robot
                raise ConfigError(f"faults[{i}].robot", f"robot {fault.robot} already has a fault in "
                                                        f"faults[{failing[fault.robot]}]")
            failing[fault.robot] = i
        for i, (x, y, yaw) in enumerate(self.path):
            check_point(f"path[{i}]", (x, y))
            if not math.isfinite(yaw):
                raise ConfigError(f"path[{i}]", "yaw must be finite")
            check_yaw(f"path[{i}][2]", yaw)
        if self.path and self.object is None:
            raise ConfigError("path", "a path needs an object to move")
        if self.path and self.object is not None and self.object.static:
            raise ConfigError("path", "a static object cannot follow a path (object.static is true)")
        if self.arena.walls is not None:
            self._check_inside_walls(self.arena.walls)

    def _check_inside_walls(self, walls: Tuple[float, float, float, float]) -> None:
        """The spawn area must reach inside the walls, and the object's start and every waypoint lie inside
        them: a run with any of them outside cannot succeed, and would only say so at its time limit."""
        xmin, ymin, xmax, ymax = walls
        spawn = self.robots.spawn     # robots are placed inside the walls: the area must only reach inside
        if spawn.x[1] <= xmin or spawn.x[0] >= xmax or spawn.y[1] <= ymin or spawn.y[0] >= ymax:
            raise ConfigError("robots.spawn", f"x {list(spawn.x)}, y {list(spawn.y)} lies outside the "
                                              f"{walls_text(walls)}")
        if self.object is not None:
            check_inside_walls(walls, "object.position", *self.object.position)
        for i, (x, y, _yaw) in enumerate(self.path):
            check_inside_walls(walls, f"path[{i}]", x, y)

    def with_overrides(self, **changes: Any) -> Scenario:
        return dataclasses.replace(self, **changes)


def walls_text(walls: Tuple[float, float, float, float]) -> str:
    return "arena walls [" + ", ".join(f"{v:g}" for v in walls) + "]"


def check_inside_walls(walls: Tuple[float, float, float, float], field_name: str, x: float, y: float,
                       whose: str = "the") -> None:
    """A point (the object's start, a waypoint) strictly inside the walls; else an error naming the field."""
    xmin, ymin, xmax, ymax = walls
    if not (xmin < x < xmax and ymin < y < ymax):
        raise ConfigError(field_name, f"({x:g}, {y:g}) is outside {whose} {walls_text(walls)}")


def builtin_names() -> List[str]:
    return sorted(p.stem for p in BUILTIN_DIR.glob("*.yaml"))


def resolve(name_or_path: str) -> Path:
    """A built-in scenario's file, or the given path; ConfigError when neither exists."""
    if not name_or_path.strip():    # Path("") is the current folder: "is a folder" of an unset $SCENARIO
        raise ConfigError("scenario", "is empty (an unset shell variable?): give a built-in name or a YAML file")
    try:
        return _resolve(name_or_path)
    except OSError as err:          # a name longer than the file system allows: "File name too long"
        raise ConfigError("scenario", f"{as_written(name_or_path)}: {err.strerror or err}") from None


def _resolve(name_or_path: str) -> Path:
    path = Path(name_or_path)
    builtin = BUILTIN_DIR / f"{name_or_path}.yaml"
    if path.is_file():
        if _is_bare_name(name_or_path) and not looks_like_path(name_or_path) and builtin.is_file():
            # `khepri sim show lab-6 > lab-6` makes such a file; either choice would surprise someone.
            raise ConfigError("scenario", f"{as_written(name_or_path)} is both a built-in scenario and a file in "
                              f"this folder: write ./{name_or_path} for the file, or rename the file")
        return path
    if not looks_like_path(name_or_path) and builtin.is_file():
        return builtin     # even when a folder of that name is here (a run's output, say)
    if path.is_dir():      # with any name: `sim run ./my-runs` said `no such file` of a folder that is there
        raise ConfigError("scenario", f"{name_or_path} is a folder, not a file")
    if path.exists():               # /dev/null, a FIFO: there, but not a file to read a scenario from
        raise ConfigError("scenario", f"{name_or_path} is not a regular file")
    if path.is_symlink():           # exists() follows it: a link to nowhere, or to itself
        raise ConfigError("scenario", f"{name_or_path} is a symbolic link to nothing that exists")
    if looks_like_path(name_or_path):
        raise no_such_file(name_or_path, name_or_path)
    raise unknown_scenario(name_or_path)


def looks_like_path(text: str) -> bool:
    """Whether a scenario is given as a file: a folder part (./lab-6, runs/big), a home or hidden name (~/x,
    .x), or a YAML suffix. Such a text names that file or nothing: ./lab-6 without a file ./lab-6 ran the
    built-in lab-6, which the docs tell users to write ./lab-6 to avoid."""
    return "/" in text or os.sep in text or text.startswith((".", "~")) or text.endswith((".yaml", ".yml"))


def no_such_file(shown: str, given: str) -> ConfigError:
    """``no such file: SHOWN``, and the built-in's name when ``given`` is one behind a folder part (./lab-6) or
    with the suffix of its file in sim_backend/scenarios/ (lab-6.yaml, which a new user copies from there)."""
    name = os.path.basename(given)
    stem, suffix = os.path.splitext(name)
    hint = ""
    if name in builtin_names():
        hint = f" (the built-in scenario is {name}, without a folder)"
    elif suffix in (".yaml", ".yml") and stem in builtin_names():
        folder = "a folder or " if name != given else ""
        hint = f" (the built-in scenario is {stem}, without {folder}{suffix})"
    return ConfigError("scenario", f"no such file: {shown}{hint}")


def unknown_scenario(name: str) -> ConfigError:
    return ConfigError("scenario",
                       f"unknown scenario {as_written(name)}: not a file and not built in (see `khepri sim list`)")


def _is_bare_name(text: str) -> bool:
    """No folder part: `lab-6`, not `./lab-6` (which Path would shorten to the same name)."""
    return "/" not in text and os.sep not in text


def load_scenario(name_or_path: str) -> Scenario:
    """Load and validate a scenario by built-in name or path. Raises ConfigError (one line) on bad input."""
    path = resolve(name_or_path)
    data = read_yaml(path, "scenario")
    if data is None:
        raise ConfigError(str(path), "the file is empty (a scenario is a mapping of keys such as behaviour: and "
                                     "robots:; {} takes every default)")
    return _parse_file(data, path, default_name=path.stem)


def load_builtin(name: str) -> Scenario:
    """A built-in scenario by name alone, whatever files the current folder holds: a study names built-ins
    by name and its own scenario files by path, and `lab-6` in the folder it is run from is neither."""
    path = BUILTIN_DIR / f"{name}.yaml"
    if not _is_bare_name(name) or not path.is_file():
        raise unknown_scenario(name)
    return _parse_file(read_yaml(path, "scenario"), path, default_name=name)


def _parse_file(data: Any, path: Path, default_name: str) -> Scenario:
    other = wrong_kind(data, SCENARIO)      # a study or lab config given as the scenario: say so, and which file
    if other:
        raise ConfigError(str(path), other)
    try:
        return parse_scenario(data, default_name=default_name)
    except ConfigError as err:
        if err.field:
            raise
        raise ConfigError(str(path), err.problem) from None     # the whole file is wrong: name it


def parse_scenario(data: Any, default_name: str = "scenario") -> Scenario:
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError("", f"a scenario must be a mapping of keys (got {type(data).__name__})")
    data = dict(data)
    data.setdefault("name", default_name)
    return from_mapping(Scenario, data, "")
