"""The hub's ``start`` command, checked field by field before the agent acts on it.

The command is input from the network: each check here turns a value that used to crash the agent, or run it
in a way nobody asked for, into a ConfigError naming the field (``run.spec``, ``run.control_hz``, ...). The
agent says the error in its log and telemetry and refuses the run.
"""
from __future__ import annotations

import math
from typing import Any, Dict

from onboard.config import ConfigError, check_range
from onboard.hal import RobotSpec
from onboard.protocol import MAX_CONTROL_HZ


def run_spec(spec: Any) -> RobotSpec:
    """The ``start`` command's ``run.spec``: a mapping of positive numbers, unknown names ignored. Checked here
    because the hub's command is input: a list crashed the agent, and a speed limit of 0 or less turned the HAL's
    clamp off."""
    if spec is None:
        return RobotSpec()
    if not isinstance(spec, dict):
        raise ConfigError("run.spec", f"must be a mapping (got {spec!r:.40})")
    values = {}
    for name, value in spec.items():
        if name in RobotSpec.__dataclass_fields__:
            values[name] = positive_number(f"run.spec.{name}", value)
    return RobotSpec(**values)


def run_params(params: Any) -> Dict[str, Any]:
    if params is not None and not isinstance(params, dict):
        raise ConfigError("run.params", f"must be a mapping (got {params!r:.40})")
    return params or {}


def run_control_hz(value: Any) -> float:
    """``run.control_hz`` as the hub's config allows it, (0, MAX_CONTROL_HZ]: 0 or less, or a huge rate, made the
    loop step the behaviour as fast as it could, every step a deadline miss."""
    return check_range("run.control_hz", positive_number("run.control_hz", value), high=MAX_CONTROL_HZ)


def run_id_text(value: Any) -> None:
    """A run id the agent can echo: its telemetry names the run, and the hub drops telemetry whose run_id is not
    a string, so the robot would look silent."""
    if value is not None and not isinstance(value, str):
        raise ConfigError("run.run_id", f"must be a string (got {value!r:.40})")


def run_uses_hub_clock(value: Any) -> bool:
    """``run.clock``: ``hub`` (the frames' simulated time) or ``local``. Compared with "hub" alone, a "Hub" or a
    true ran a lockstep run on the robot's own clock, its behaviour's time apart from the simulation's."""
    if value not in ("local", "hub"):
        raise ConfigError("run.clock", f"must be local or hub (got {value!r:.40})")
    return value == "hub"


def positive_number(where: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 < value < math.inf:
        raise ConfigError(where, f"must be a number > 0 (got {value!r:.40})")
    return float(value)
