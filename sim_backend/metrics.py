"""Ground-truth evaluation of a run, outside the behaviour: one evaluator per behaviour name.

Evaluators see the world (true poses) and each robot's telemetry (what the robots *believe*, the same dict a
real robot sends its hub, so the software-in-the-loop run evaluates identically); the behaviours never see
the evaluators. Each returns the behaviour-specific part of result.json.
"""
from __future__ import annotations

import json
import math
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple, Type

import numpy as np

from onboard.behaviour import USER_CODE_ERRORS, plain_json
from onboard.config import ConfigError, as_written
from onboard.geometry import wrap
from onboard.hal.payload import a_kind
from onboard.plugins import OTHER_REGISTRIES

from .evaluator_error import EvaluatorError


class Evaluator:
    """Watches a run. ``on_step`` is called once per control step after the behaviours stepped."""

    def __init__(self, scenario, world):
        self.scenario = scenario
        self.world = world

    def on_step(self, time_s: float, telemetry: List[Optional[Dict[str, Any]]]) -> None:
        """``telemetry[i]`` is robot i's latest telemetry (``onboard.behaviour.telemetry_of``), None if dead."""

    def warnings(self, params: Any) -> List[str]:
        """What the simulator knows about this scenario (the true object, the walls) that will make the
        behaviour fail, said before the run starts; ``params`` are the behaviour's."""
        return []

    def centroid_estimate(self, telemetry: List[Optional[Dict[str, Any]]]) -> np.ndarray:
        """The swarm's mean belief of the object centroid (NaN when nobody has one); for the trajectory file."""
        return np.array([np.nan, np.nan])

    def result(self) -> Dict[str, Any]:
        return {}

    def waypoints_reached(self) -> Optional[int]:
        """How many of the scenario's waypoints the run has reached so far, by this evaluator's rule (the hub's
        `ctl status` shows it); None when it does not judge waypoints."""
        return None


def waypoint_error(truth: Sequence[float], target: Sequence[float]) -> Tuple[float, float]:
    """The object's distance (m) and absolute yaw difference (rad) from a waypoint ``[x, y, yaw_deg]``, given its
    true pose ``[x, y, yaw_rad]``: result.json's ``position_error_m`` and ``orientation_error_rad``."""
    return (float(math.hypot(truth[0] - target[0], truth[1] - target[1])),
            float(abs(wrap(truth[2] - math.radians(target[2])))))


def evaluator_call(evaluator: Evaluator, method: str, *args: Any) -> Any:
    """``evaluator.<method>(*args)``, with an exception in it raised as EvaluatorError (a user's evaluator is
    user code: without this a ZeroDivisionError in it read as a crash of the run with no file or line)."""
    try:
        return getattr(evaluator, method)(*args)
    except USER_CODE_ERRORS as exc:
        raise EvaluatorError(evaluator, f"{method}()", exc) from exc


def make_evaluator(name: str, scenario: Any, world: Any) -> Evaluator:
    """The evaluator registered for behaviour ``name``, made for this run; an exception in a user's
    ``__init__`` is an EvaluatorError, as in any other call."""
    cls = evaluator_for(name)
    try:
        return cls(scenario, world)
    except USER_CODE_ERRORS as exc:
        raise EvaluatorError(cls, "__init__()", exc) from exc


def merge_result(evaluator: Evaluator, result: Dict[str, Any],
                 earlier_error: Optional[str] = None) -> Optional[EvaluatorError]:
    """Add the evaluator's ``result()`` to ``result``. If it raised after the run had already failed
    (``earlier_error``), both are kept: its failure goes to ``result["evaluation_error"]``. Returns the failure
    when it is the run's error (no earlier one), else None."""
    try:
        result.update(checked_result(evaluator, evaluator_call(evaluator, "result"), result))
    except EvaluatorError as failure:
        if not earlier_error:
            return failure
        result["evaluation_error"] = str(failure)
    return None


# result.json's fields that the simulator and a study write besides those already in the result when the
# evaluator's are added (scenario, seed, robots, stop_reason, ...): an evaluator's field must not replace one.
LATER_FIELDS = frozenset(("telemetry", "error", "traceback", "evaluation_error", "warnings", "failed", "study"))


def checked_result(evaluator: Evaluator, fields: Any, result: Dict[str, Any]) -> Dict[str, Any]:
    """The evaluator's ``result()`` if result.json can hold it; else EvaluatorError naming the field. A
    ``seed`` or ``stop_reason`` of its own used to replace the run's (a study then lost the run), and a set
    in it ended ``sim run`` in a traceback with no result.json."""
    def refuse(problem: str) -> EvaluatorError:
        error = EvaluatorError(evaluator, "result()", TypeError(problem))
        error.lines = []        # no traceback: it would only repeat the line, with no frame of the user's
        return error

    if not isinstance(fields, dict):
        raise refuse(f"returned {a_kind(fields)}, not a dict of result.json fields")
    taken = sorted(str(key) for key in fields if key in result or key in LATER_FIELDS)
    if taken:
        raise refuse(f"{taken[0]!r} is a result.json field the simulator writes: give the evaluator's "
                     f"own another name")
    try:
        json.dumps(fields, default=json_default)
    except (TypeError, ValueError, RecursionError):
        try:
            plain_json(fields, "result()")     # names the first value JSON cannot hold
        except TypeError as exc:
            raise refuse(str(exc)) from None
        except RecursionError:
            pass
        raise refuse("nests lists or mappings too deep for JSON") from None
    return fields


def result_text(result: Dict[str, Any]) -> str:
    """result.json's text, as ``sim run``, ``sil`` and a study write it: numpy values as Python's, and NaN or
    infinity as null. JSON has neither, and Python's json writes a bare NaN that strict readers (jq, a
    browser, pandas in some modes) refuse; a physics blow-up or an evaluator's NaN must not make the file
    unreadable."""
    return json.dumps(finite(result), indent=2, default=json_default, allow_nan=False) + "\n"


def finite(value: Any) -> Any:
    """``value`` with every non-finite float (also inside numpy arrays, lists and dicts) made None."""
    if isinstance(value, dict):
        return {key: finite(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite(item) for item in value]
    if isinstance(value, (np.generic, np.ndarray)):
        return finite(value.tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def json_default(value: Any) -> Any:
    """``json.dumps``'s ``default`` for result.json (sim_backend/outputs.py writes it so): numpy numbers, booleans
    and arrays as Python's."""
    if isinstance(value, (np.generic, np.ndarray)):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


_EVALUATORS: Dict[str, Type[Evaluator]] = {}


def evaluator_for(name: str) -> Callable[..., Evaluator]:
    from . import transport_metrics  # noqa: F401  (registers the transport evaluator)

    return _EVALUATORS.get(name, Evaluator)


OTHER_REGISTRIES.append(lambda: list(_EVALUATORS.values()))    # a user's module of evaluators registers something


def evaluators_of_no_behaviour() -> List[str]:
    """``module.Class is registered to judge 'name', ...`` for each evaluator registered under a name that no
    registered behaviour has: a typo of the behaviour's name, which judged nothing without a word."""
    from onboard.behaviour import behaviour_names

    known = behaviour_names()
    return [f"{_qualified(cls)} is registered to judge {name!r}, which is no behaviour's name (known: "
            f"{', '.join(known)}): no run is judged by it" for name, cls in sorted(_EVALUATORS.items())
            if name not in known]


def register_evaluator(name: str):
    """Class decorator: judge the runs of the behaviour ``name`` with this Evaluator subclass. As @register does
    for behaviours, it refuses a name that is not a non-empty string (no scenario could name it), a class that is
    not an Evaluator, and a name another class took (the later import silently replaced the earlier)."""
    def decorate(cls):
        from . import transport_metrics  # noqa: F401  (the built-in names are taken first, whatever the order)

        where = f"@register_evaluator({as_written(name)}) above {_qualified(cls)}"
        if not isinstance(name, str) or not name.strip():
            raise ConfigError("register_evaluator", f"{where}: the name must be the behaviour's, a non-empty string")
        if not (isinstance(cls, type) and issubclass(cls, Evaluator)):
            raise ConfigError("register_evaluator", f"{where}: the class must subclass sim_backend.metrics.Evaluator")
        taken = _EVALUATORS.get(name)
        if taken is not None and _qualified(taken) != _qualified(cls):     # the same class imported again is fine
            raise ConfigError("register_evaluator", f"the behaviour {name!r} is judged by {_qualified(taken)} "
                                                    f"already; {_qualified(cls)} cannot judge it too")
        _EVALUATORS[name] = cls
        return cls
    return decorate


def _qualified(cls: Any) -> str:
    return f"{getattr(cls, '__module__', '?')}.{getattr(cls, '__qualname__', repr(cls))}"


def spread(xy: np.ndarray) -> float:
    """Mean distance of the robots from their centroid (m)."""
    return float(np.mean(np.hypot(*(xy - xy.mean(axis=0)).T))) if len(xy) else 0.0


@register_evaluator("aggregate")
class AggregateEvaluator(Evaluator):
    def __init__(self, scenario, world):
        super().__init__(scenario, world)
        self.initial_spread = spread(world.robot_poses()[:, :2])

    def result(self) -> Dict[str, Any]:
        final = spread(self.world.robot_poses()[:, :2])
        return {"initial_spread_m": self.initial_spread, "final_spread_m": final,
                "spread_ratio": final / self.initial_spread if self.initial_spread > 0 else 1.0}
