"""The behaviour interface and registry.

A behaviour is a class with a per-step method. The backend (simulator or onboard agent) owns the loop and
calls :meth:`Behaviour.step` at the control rate (10 Hz by default). A behaviour sees only the
:class:`~onboard.hal.Robot` it is given and its own parameters.

Writing your own::

    @dataclass
    class WanderParams:
        speed_m_s: float = 0.1

    @register("wander")
    class Wander(Behaviour):
        Params = WanderParams

        def step(self) -> None:
            self.robot.wheels.set_speeds(self.params.speed_m_s, self.params.speed_m_s)
"""
from __future__ import annotations

import copy
import dataclasses
import inspect
import json
import math
import os
import traceback
from typing import Any, Callable, Dict, List, Mapping, Optional, Type

from .config import SHOWN_CHARS, ConfigError, as_written, from_mapping, join
from .hal import Robot
from .hal.payload import a_kind
from .protocol_schema import short
from .tracebacks import traceback_lines, where_in_users_code

# What a behaviour's code may raise that is its own failure, reported as a BehaviourError naming the robot
# and the line: every Exception, and SystemExit, so that a stray sys.exit() in step() does not end a run
# (or an agent) without a word. KeyboardInterrupt stays the operator's.
USER_CODE_ERRORS = (Exception, SystemExit)


@dataclasses.dataclass
class NoParams:
    """For behaviours without parameters."""


class Behaviour:
    """Base class. Subclasses set ``Params`` (a dataclass of documented defaults) and implement ``step``."""

    Params: Type[Any] = NoParams

    def __init__(self, robot: Robot, params: Optional[Any] = None):
        self.robot = robot
        self.params = params if params is not None else self.Params()
        self.state = "init"

    def step(self) -> None:
        """Read sensors, decide, command actuators. Called once per control period."""
        raise NotImplementedError

    def stop(self) -> None:
        """Called when the run ends (an e-stop or the watchdog only pauses step()). Stops the wheels."""
        self.robot.wheels.stop()

    @property
    def finished(self) -> bool:
        """True when this robot considers the job done; a run ends when every live robot is finished."""
        return False

    def telemetry(self) -> Dict[str, Any]:
        """Small JSON-compatible summary of this robot's internal state, for logs and result files."""
        return {"state": self.state}


def telemetry_of(behaviour: Behaviour, robot_id: int) -> Dict[str, Any]:
    """The behaviour's telemetry plus ``finished`` as plain JSON values: what a robot reports each step (sim
    runner and agent), so an evaluator sees the same values in ``sim run`` as in ``sil``, where they came over
    the wire (NaN as None, numpy as Python). BehaviourError names which of the two raised."""
    try:
        reported = behaviour.telemetry()
        if type(reported) is not dict and not isinstance(reported, Mapping):   # a plain dict skips the ABC check
            raise TypeError(f"telemetry() must return a dict (got {type(reported).__name__})"
                            f"{defined_at(type(behaviour).telemetry)}")
        data = dict(reported)
    except USER_CODE_ERRORS as exc:
        raise BehaviourError(robot_id, "telemetry()", exc) from exc
    try:
        data["finished"] = bool(behaviour.finished)
    except USER_CODE_ERRORS as exc:
        raise BehaviourError(robot_id, "finished", exc) from exc
    # The check first: most telemetry is plain already, and copying every robot's every step costs the
    # simulator several times as much as looking.
    if is_plain_json(data):
        return data
    try:
        return plain_json(data)
    except TypeError as exc:    # a value JSON has no form for: name its field here, in sim run as on a robot
        # A fresh exception, without plain_json's frames: the line to point at is the user's method, not ours.
        raise BehaviourError(robot_id, "telemetry()",
                             TypeError(f"{exc}{defined_at(type(behaviour).telemetry)}")) from None
    except RecursionError:      # plain_json's walk is recursive, as are JSON's encoders
        raise BehaviourError(robot_id, "telemetry()", TypeError(
            "telemetry nests lists or mappings hundreds of levels deep, which JSON cannot carry")) from None


_PLAIN_SCALARS = frozenset((str, int, bool, type(None)))


def is_plain_json(values: Any) -> bool:
    """Whether a dict's or list's values (and a dict's keys) are all plain JSON already: what ``plain_json``
    would leave as is."""
    if type(values) is dict:
        for key in values:
            if type(key) is not str:            # JSON makes it a string: plain_json does so now
                return False
        values = values.values()
    for item in values:
        kind = type(item)
        if kind is float:
            if item - item != 0.0:              # NaN or infinity (math.isfinite costs a call per value)
                return False
        elif kind is dict or kind is list:
            if not is_plain_json(item):
                return False
        elif kind not in _PLAIN_SCALARS:
            return False
    return True


def plain_json(value: Any, where: str = "telemetry") -> Any:
    """A behaviour's telemetry as plain JSON values, as the hub gets it from an agent: numpy numbers and
    arrays become Python ones, tuples lists, NaN or infinity (which JSON cannot carry) None, and dict keys
    the strings JSON makes of them (``{3: x}`` arrives as ``{"3": x}``, so an evaluator must not see ``3``
    in ``sim run`` and ``"3"`` in ``sil``). TypeError names the first value JSON has no form for
    (``telemetry['seen']``), which the wire would refuse far from the cause."""
    if isinstance(value, dict):
        return {_json_key(key, where): plain_json(item, f"{where}[{key!r}]") for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain_json(item, f"{where}[{index}]") for index, item in enumerate(value)]
    if hasattr(value, "tolist"):            # numpy arrays and scalars, without importing numpy here
        return plain_json(value.tolist(), where)
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if value is None or isinstance(value, (str, int, float)):
        return value
    # Short: an agent's error line to the hub keeps 200 characters, the robot and the call before this.
    raise TypeError(f"{where} is {a_kind(value)}, which JSON cannot carry: send dicts, lists, "
                    f"strings, numbers, booleans or None")


def _json_key(key: Any, where: str) -> str:
    """The key a receiver of the JSON gets: json.dumps writes 3 as "3", True as "true", None as "null"."""
    if isinstance(key, str):
        return str(key)
    if hasattr(key, "tolist"):
        key = key.tolist()
    if key is None or isinstance(key, (int, float)):
        return json.dumps(key)
    raise TypeError(f"{where} has the key {key!r}, {a_kind(key)}, which JSON cannot carry: use a "
                    f"string")


def defined_at(function: Any) -> str:
    """`` (returned by telemetry() at flock.py:40)``: where a method that returned a bad value is written, for
    an error found after it returned (no traceback leads there); "" when Python cannot tell."""
    try:
        path, line = inspect.getsourcefile(function), inspect.getsourcelines(function)[1]
    except (OSError, TypeError):
        return ""
    return f" (returned by {function.__name__}() at {os.path.basename(path or '?')}:{line})"


class BehaviourError(RuntimeError):
    """A behaviour's own code raised: which robot, in which call, what, and where in the user's file. The
    simulator and the agent report it the same way; ``lines`` keeps the end of the traceback."""

    def __init__(self, robot_id: int, call: str, exc: BaseException):
        self.robot_id, self.call, self.exc = robot_id, call, exc
        frames = traceback.extract_tb(exc.__traceback__)[1:]    # [0] is the caller's frame (runner, agent)
        self.lines: List[str] = traceback_lines(frames, exc)
        at = where_in_users_code(frames)
        super().__init__(f"robot {robot_id}, {call}: {type(exc).__name__}: {exc}{at}")




def make_behaviours(cls: Type[Behaviour], robots: List[Robot], params: Any) -> List[Behaviour]:
    """One behaviour per robot, each with its own copy of the parameters: on robots each agent has its own,
    so a behaviour that changes ``self.params`` must not change its neighbours' in simulation either."""
    made = []
    for robot in robots:
        try:
            made.append(cls(robot, copy.deepcopy(params)))
        except USER_CODE_ERRORS as exc:                # the user's __init__: one line naming the robot and the line
            raise BehaviourError(robot.id, f"{cls.__name__}.__init__", exc) from exc
    return made


_REGISTRY: Dict[str, Type[Behaviour]] = {}


def register(name: str) -> Callable[[Type[Behaviour]], Type[Behaviour]]:
    """Class decorator: make a behaviour available by name to scenarios and agents. A name already taken by
    another class is an error (the second would silently replace the first, or be replaced by it)."""

    def decorate(cls: Type[Behaviour]) -> Type[Behaviour]:
        _check_behaviour_class(cls)
        # A scenario names it in its behaviour: text. @register(3) was taken, and every later list of the names
        # ended in "'<' not supported between instances of 'int' and 'str'"; @register("") could never be named.
        if not isinstance(name, str) or not name.strip():
            raise ConfigError("register", f"@register({short(name)}) above {_qualified(cls)}: a behaviour's "
                                          "name must be a non-empty string, e.g. @register(\"wander\")")
        if getattr(cls, "step", None) is Behaviour.step:
            raise ConfigError("register", f"{_qualified(cls)} has no step(self): define it (it is called once "
                                          "per control period)")
        if inspect.isgeneratorfunction(getattr(cls, "step", None)):    # calling it would only make a generator
            raise ConfigError("register", f"{_qualified(cls)}.step contains `yield`: it would never run")
        if inspect.isfunction(inspect.getattr_static(cls, "finished", None)):   # a method is always truthy
            raise ConfigError("register", f"{_qualified(cls)}.finished must be a property: put @property above "
                                          "`def finished(self)` (as a method it would end every run at once)")
        taken = _REGISTRY.get(name)
        if taken is not None and _qualified(taken) != _qualified(cls):   # the same class imported again is fine
            raise ConfigError("register", f"the behaviour name {name!r} is taken by {_qualified(taken)}; "
                                          f"{_qualified(cls)} needs another name")
        _REGISTRY[name] = cls
        cls.name = name
        return cls

    return decorate


def ignored_return_text(returned: Any) -> str:
    """What a step() that returned something is told (once a run, in sim run and by the agent)."""
    return (f"{short(returned)} (said once a run): its return value is ignored; drive the wheels with "
            "self.robot.wheels.set_speeds(left_m_s, right_m_s)")


def _check_behaviour_class(cls: Any) -> None:
    """What would otherwise fail only once a run starts (a wrong signature, at t = 0 in every robot), or never
    run at all (``async def step``: a coroutine made and dropped each step, the robots standing still)."""
    if not (isinstance(cls, type) and issubclass(cls, Behaviour)):
        what = _qualified(cls) if isinstance(cls, type) else repr(cls)
        raise ConfigError("register", f"{what} is not a Behaviour: write `class {getattr(cls, '__name__', 'X')}"
                                      "(Behaviour):` (from onboard.behaviour import Behaviour)")
    step = getattr(cls, "step", None)
    if inspect.iscoroutinefunction(step):
        raise ConfigError("register", f"{_qualified(cls)}.step is `async def`: it would never run (it is called, "
                                      "not awaited); make it a plain `def step(self)`")
    _check_signature(cls, "step", step, "step(self)", 1)
    _check_signature(cls, "__init__", cls.__init__, "__init__(self, robot, params=None), calling "
                                                    "super().__init__(robot, params)", 3)


def _check_signature(cls: type, name: str, method: Any, wanted: str, arguments: int) -> None:
    """``method`` (a plain function) must take ``arguments`` positional arguments, self included."""
    if not inspect.isfunction(method):
        return                     # inherited from Behaviour, a builtin, or a wrapped callable: not ours to judge
    try:
        inspect.signature(method).bind(*([None] * arguments))
    except TypeError:
        raise ConfigError("register", f"{_qualified(cls)}.{name} must be {wanted}; it is "
                                      f"{name}{inspect.signature(method)} "
                                      f"(at {_where(method)})") from None
    except ValueError:             # no signature to read
        return


def _where(function: Any) -> str:
    code = function.__code__
    return f"{os.path.basename(code.co_filename)}:{code.co_firstlineno}"


def _qualified(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def behaviour_names() -> list:
    _load_builtin()
    return sorted(_REGISTRY)


def get_behaviour(name: str, where: str = "behaviour") -> Type[Behaviour]:
    _load_builtin()
    try:
        return _REGISTRY[name]
    except KeyError:
        from .behaviours import BROKEN

        hints = "".join(f"; {file} did not import: {why}" for file, why in BROKEN.items())
        raise ConfigError(where, f"unknown behaviour {as_written(name)} (known: {', '.join(sorted(_REGISTRY))}"
                                 f"{hints}; a behaviour of your own needs @register and, outside onboard/behaviours/, "
                                 "--import)") from None


def build_params(cls: Type[Behaviour], overrides: Optional[Mapping[str, Any]], where: str = "params") -> Any:
    """The behaviour's parameter record with ``overrides`` applied; unknown names and bad values rejected."""
    if not (isinstance(cls.Params, type) and dataclasses.is_dataclass(cls.Params)):
        raise ConfigError(where, f"{cls.__name__}.Params must be a dataclass (got {cls.Params!r})")
    named = [key for key in overrides if isinstance(key, str)] if isinstance(overrides, Mapping) else []
    if named and not any(f.init for f in dataclasses.fields(cls.Params)):
        # `unknown key (known: )` left the author to guess that the behaviour, not the scenario, was wrong
        how = "sets no Params (class attribute `Params = <a dataclass of its parameters>`)" \
            if cls.Params is NoParams else f"has no parameters ({cls.Params.__name__} has no fields)"
        key = named[0] if len(named[0]) <= SHOWN_CHARS else named[0][:SHOWN_CHARS] + "..."
        raise ConfigError(join(where, key), f"unknown key: behaviour {cls.__name__} {how}")
    try:
        return from_mapping(cls.Params, dict(overrides or {}), where)
    except (NameError, TypeError) as err:      # an annotation the config reader cannot resolve or build
        raise ConfigError(where, f"{cls.__name__}.Params cannot be read: {type(err).__name__}: {err}") from None


def takes_param(cls: Type[Behaviour], name: str) -> bool:
    """Whether the behaviour's Params has a field ``name`` (how a behaviour asks for the mission's path, say)."""
    return any(f.name == name for f in dataclasses.fields(cls.Params))


def _load_builtin() -> None:
    # Importing the package registers the shipped behaviours.
    from . import behaviours  # noqa: F401
