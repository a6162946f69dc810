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

import dataclasses
from typing import Any, Callable, Dict, Mapping, Optional, Type

from .config import ConfigError, from_mapping
from .hal import Robot


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
        """Called when the backend halts the behaviour (end of run, e-stop, watchdog). Stops the wheels."""
        self.robot.wheels.stop()

    @property
    def finished(self) -> bool:
        """True when this robot considers the job done; a run ends when every live robot is finished."""
        return False

    def telemetry(self) -> Dict[str, Any]:
        """Small JSON-compatible summary of this robot's internal state, for logs and result files."""
        return {"state": self.state}


def telemetry_of(behaviour: Behaviour) -> Dict[str, Any]:
    """The behaviour's telemetry plus ``finished``: what a robot reports each step (sim runner and agent)."""
    data = dict(behaviour.telemetry())
    data["finished"] = bool(behaviour.finished)
    return data


_REGISTRY: Dict[str, Type[Behaviour]] = {}


def register(name: str) -> Callable[[Type[Behaviour]], Type[Behaviour]]:
    """Class decorator: make a behaviour available by name to scenarios and agents."""

    def decorate(cls: Type[Behaviour]) -> Type[Behaviour]:
        _REGISTRY[name] = cls
        cls.name = name
        return cls

    return decorate


def behaviour_names() -> list:
    _load_builtin()
    return sorted(_REGISTRY)


def get_behaviour(name: str, where: str = "behaviour") -> Type[Behaviour]:
    _load_builtin()
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ConfigError(where, f"unknown behaviour {name!r} (known: {', '.join(sorted(_REGISTRY))})") from None


def build_params(cls: Type[Behaviour], overrides: Optional[Mapping[str, Any]], where: str = "params") -> Any:
    """The behaviour's parameter record with ``overrides`` applied; unknown names and bad values rejected."""
    return from_mapping(cls.Params, dict(overrides or {}), where)


def _load_builtin() -> None:
    # Importing the package registers the shipped behaviours.
    from . import behaviours  # noqa: F401
