"""``--set KEY=VALUE``: a field of a scenario changed from the command line (`sim run`, `sim show`, `sil`), as a
study's ``overrides`` change it (``sim_backend/study``): a dotted key into the scenario, every default filled in,
and a value read as YAML (``0.2``, ``true``, ``[1.0, 2.0]``). Trying one parameter no longer needs a copy of the
scenario file or a one-cell study."""
from __future__ import annotations

import copy
from typing import Any, Callable, Dict, Sequence, Tuple

import yaml

from onboard.config import ConfigError, as_written, to_mapping

from .scenario import Scenario, load_scenario, parse_scenario

SETTING = "--set"


def apply_overrides(base: Dict[str, Any], chosen: Dict[str, Any],
                    field_of: Callable[[str], str] = lambda key: f"overrides.{key}") -> Dict[str, Any]:
    """A copy of ``base`` with each dotted key of ``chosen`` set to its value (missing mappings made on the way);
    ConfigError, on ``field_of(key)``, for a key that goes through a value that is no mapping."""
    data = copy.deepcopy(base)
    for key, value in chosen.items():
        target = data
        parts = key.split(".")
        for depth, part in enumerate(parts[:-1]):
            child = target.get(part)
            if child is None:
                child = target[part] = {}
            if not isinstance(child, dict):
                raise ConfigError(field_of(key), f"{'.'.join(parts[:depth + 1])} is not a mapping")
            target = child
        target[parts[-1]] = copy.deepcopy(value)
    return data


def parse_settings(texts: Sequence[str]) -> Dict[str, Any]:
    """``["params.travel_speed_m_s=0.2", ...]`` as ``{"params.travel_speed_m_s": 0.2, ...}``; a key given twice
    keeps its last value, as later options do."""
    chosen: Dict[str, Any] = {}
    for text in texts:
        key, sep, value = text.partition("=")
        key = key.strip()
        if not sep or not key or any(not part for part in key.split(".")):
            raise ConfigError(SETTING, f"must be KEY=VALUE with a dotted KEY into the scenario, e.g. "
                                       f"params.cruise_speed_m_s=0.15 (got {as_written(text)})")
        try:
            chosen[key] = yaml.safe_load(value) if value.strip() else None
        except yaml.YAMLError as err:
            problem = str(getattr(err, "problem", None) or err).splitlines()[0]
            raise ConfigError(f"{SETTING} {key}", f"the value {as_written(value)} is not YAML: {problem}") from None
    return chosen


def load_with_settings(ref: str, texts: Sequence[str]) -> Tuple[Scenario, Dict[str, Any]]:
    """The scenario ``ref`` (a built-in name or a file) with the ``--set`` values applied, and those values."""
    scenario = load_scenario(ref)
    chosen = parse_settings(texts)
    if not chosen:
        return scenario, chosen
    data = apply_overrides(to_mapping(scenario), chosen, field_of=lambda key: f"{SETTING} {key}")
    try:
        return parse_scenario(data, default_name=scenario.name), chosen
    except ConfigError as err:
        raise ConfigError(SETTING, str(err)) from None
