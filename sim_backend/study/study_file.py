"""Reading a study: a YAML study file, or the paper's grid, checked into a StudySpec.

Every problem is a ConfigError naming the field (``seeds``, ``overrides.<key>``, ``scenarios[<i>]``), found before
anything runs: parse_study also expands the study (``grid.expand``), building every cell's scenario once.
"""
from __future__ import annotations

import math
import os
import re
from pathlib import Path
from typing import Any, Dict, List, Optional

from onboard.config import (
    MAX_NAME_LENGTH,
    MAX_SEED,
    ConfigError,
    as_integer,
    as_written,
    check_seed,
    has_control_character,
)
from onboard.filekinds import STUDY, wrong_kind
from onboard.yamlfile import read_yaml
from sim_backend.scenario import builtin_names, looks_like_path

from .grid import StudySpec, expand
from .paper_reference import paper_scenarios
from .text import counted

# Far more runs than any machine finishes (a 1-second lab-6 run each would take a day), and a bound before a
# typo such as `reps: 1000000000` makes a list that fills the memory.
MAX_SEEDS = 100_000
# Every cell is built and checked before anything runs (about 20 ms each on the development machine) and gets a
# folder of its own: a grid of more cells than this is a value list too many, not a study. Counted before the
# grid is expanded: eight keys of ten values made itertools.product fill the memory before the first cell.
MAX_CELLS = 10_000
MAX_RUNS = MAX_SEEDS       # cells x seeds: the bound one cell's seeds have, for the whole study
STUDY_KEYS = ("name", "scenarios", "seeds", "reps", "overrides", "time_limit_s")
SEED_RANGE = re.compile(r"^\s*(\d+)\s*\.\.\s*(\d+)\s*$")
SAFE_NAME = re.compile(r"^[A-Za-z0-9_.+-]+$")


def paper_study(reps: int) -> StudySpec:
    check_reps("--reps", reps)
    spec = StudySpec(name="paper", scenarios=paper_scenarios(), seeds=list(range(1, reps + 1)))
    check_grid_size(spec, "--reps")
    return spec


def check_reps(where: str, value: Any) -> int:
    reps = as_integer(value)        # 2.0 as 2, as scenario files take it
    if reps is None or reps < 1:
        raise ConfigError(where, f"must be an integer >= 1 (got {as_written(value)})")
    if reps > MAX_SEEDS:
        raise ConfigError(where, f"must be at most {MAX_SEEDS} (got {reps})")
    return reps


def load_study_file(path: Path, reps: Optional[int] = None) -> StudySpec:
    """A study file; ``reps`` (``--reps``) replaces its seeds, or gives them when the file has none."""
    data = read_yaml(path, "study")
    if data is None:
        raise ConfigError(str(path), "the file is empty (a study needs at least its scenarios)")
    if reps is not None:
        check_reps("--reps", reps)
    if reps is not None and isinstance(data, dict):
        data = {key: value for key, value in data.items() if key not in ("seeds", "reps")}
        data["reps"] = reps
    try:
        return parse_study(data, base_dir=path.parent, default_name=path.stem,
                           seeds_field="--reps" if reps is not None else None)
    except ConfigError as err:       # which file: a study names scenario files, and each can be wrong too
        if err.field.startswith("--"):      # an option's value, not the file's
            raise
        raise ConfigError(f"{path}: {err.field}" if err.field else str(path), err.problem) from None


def parse_study(data: Any, base_dir: Path = Path("."), default_name: str = "study",
                seeds_field: Optional[str] = None) -> StudySpec:
    """Validate a study mapping; every problem is a ConfigError naming the field. ``seeds_field`` names where the
    seeds came from when not the mapping (``--reps``)."""
    if not isinstance(data, dict):
        raise ConfigError("", f"a study file must be a mapping of keys (got {type(data).__name__})")
    unknown = [key for key in data if key not in STUDY_KEYS]
    other = wrong_kind(data, STUDY)          # a scenario or lab config given as the study
    if other:
        raise ConfigError("", other)
    if unknown:
        raise ConfigError(str(unknown[0]), f"unknown key (known: {', '.join(STUDY_KEYS)})")
    name = data.get("name", default_name)
    if not isinstance(name, str) or not SAFE_NAME.match(name):
        raise ConfigError("name", f"must be a name of letters, digits and _.+- (got {as_written(name)})")
    if len(name) > MAX_NAME_LENGTH:
        raise ConfigError("name", f"names the study's folders: at most {MAX_NAME_LENGTH} characters (got {len(name)})")
    listed = data.get("overrides")
    spec = StudySpec(name=name, scenarios=parse_scenario_list(data.get("scenarios"), base_dir),
                     seeds=parse_seeds(data), overrides={} if isinstance(listed, list) else parse_overrides(listed),
                     time_limit_s=parse_time_limit("time_limit_s", data.get("time_limit_s")),
                     override_sets=parse_override_sets(listed) if isinstance(listed, list) else None)
    check_grid_size(spec, seeds_field or ("seeds" if "seeds" in data else "reps"))
    if spec.time_limit_s is not None:
        check_limit_not_overridden(spec)
    expand(spec)   # builds and validates every cell's scenario now, before anything runs
    return spec


def check_limit_not_overridden(spec: StudySpec, flag: str = "") -> None:
    """Refuse a study time limit (the file's time_limit_s, or ``flag``: --time-limit) beside cells that override
    time_limit_s: it replaces every run's limit, so the cells would differ in name only (and summary.csv would
    name them by limits they never ran with)."""
    limited = [i for i, chosen in enumerate(spec.cells()) if "time_limit_s" in chosen]
    if not limited:
        return
    where = "overrides" if spec.override_sets is None else f"overrides[{limited[0]}]"
    if not flag:
        raise ConfigError(f"{where}.time_limit_s", "the study's time_limit_s replaces it in every run: give "
                                                   "one or the other")
    raise ConfigError(flag, f"replaces the time limit of every run, and the study's {where}.time_limit_s gives its "
                            "cells limits of their own: they would differ in name only; drop one or the other")


def check_grid_size(spec: StudySpec, seeds_field: str) -> None:
    """Refuse a grid of more than MAX_CELLS cells or MAX_RUNS runs, counted from the value lists, before anything
    expands it (``spec.cells()``); ``seeds_field`` is where the seeds came from."""
    listed = spec.override_sets is not None
    per_scenario = len(spec.override_sets or ()) if listed else math.prod(len(v) for v in spec.overrides.values())
    cells = per_scenario * len(spec.scenarios)
    if cells > MAX_CELLS:
        how = (f"{len(spec.override_sets or ())} listed" if listed else
               " x ".join(str(len(values)) for values in spec.overrides.values()) + " values")
        scenarios = counted(len(spec.scenarios), "scenario")
        raise ConfigError("overrides", f"makes {cells} cells ({scenarios} x {how}), more than a study may hold "
                                       f"({MAX_CELLS}; each is built and checked before anything runs): give fewer "
                                       f"values, or list the cells you want")
    runs = cells * len(spec.seeds)
    if runs > MAX_RUNS:
        raise ConfigError(seeds_field, f"{cells} cells x {len(spec.seeds)} seeds make {runs} runs, more than a "
                                       f"study may run ({MAX_RUNS}): give fewer seeds or fewer cells")


def parse_scenario_list(value: Any, base_dir: Path) -> List[str]:
    if not isinstance(value, list) or not value:
        raise ConfigError("scenarios", f"must be a non-empty list of scenario names or files (got {as_written(value)})")
    names = []
    for i, item in enumerate(value):
        if not isinstance(item, str) or not item.strip():
            raise ConfigError(f"scenarios[{i}]", f"must be a scenario name or file (got {as_written(item)})")
        if has_control_character(item):      # a NUL ended the dry run in a traceback ("embedded null byte")
            raise ConfigError(f"scenarios[{i}]", f"holds a control character (got {as_written(item)})")
        # Files are relative to the study file, so a study folder can be moved as a whole; so is a file named
        # without .yaml (it used to be looked up in the current folder, so the study meant something else
        # depending on where it was run from).
        beside, path_like = base_dir / item, looks_like_path(item)    # ./lab-6 is a file, or an error: not lab-6
        is_file = path_like or beside.is_file()
        if is_file and not path_like and item in builtin_names():
            raise ConfigError(f"scenarios[{i}]", f"{as_written(item)} is both a built-in scenario and a file beside "
                                                 f"the study: write ./{item} for the file, or rename the file")
        if is_file and not beside.exists():
            check_not_relative_to_cwd(f"scenarios[{i}]", item, base_dir)
        names.append(str(beside.resolve()) if is_file else item)
    if len(set(names)) != len(names):
        twice = next(item for item, name in zip(value, names) if names.count(name) > 1)
        raise ConfigError("scenarios", f"lists a scenario twice: {twice}")
    return names


def check_not_relative_to_cwd(where: str, item: str, base_dir: Path) -> None:
    """A scenario file missing beside the study but found from the current folder was written relative to the
    current folder: say so, as "no such file: <study folder>/<item>" alone read as if the file were gone."""
    here = Path(item)
    if here.is_absolute() or not here.is_file():
        return
    relative = Path(os.path.relpath(here.resolve(), base_dir.resolve())).as_posix()
    raise ConfigError(where, f"no such file: {base_dir / item} (a scenario file is relative to the study file: "
                             f"for {item} in the current folder, write {relative})")


def parse_seeds(data: Dict[str, Any]) -> List[int]:
    if "seeds" in data and "reps" in data:
        raise ConfigError("seeds", "give either seeds (a list, or 'first..last') or reps (seeds 1..reps), not both")
    if "seeds" not in data and "reps" not in data:
        raise ConfigError("seeds", "missing: give seeds (a list, or 'first..last') or reps (seeds 1..reps), here or "
                                   "as --reps")
    if "reps" in data:
        return list(range(1, check_reps("reps", data["reps"]) + 1))
    value = data["seeds"]
    if isinstance(value, str):
        match = SEED_RANGE.match(value)
        if match and max(len(match.group(1)), len(match.group(2))) > len(str(MAX_SEED)):   # int() refuses 4300
            raise ConfigError("seeds", f"a range's seeds must be at most {MAX_SEED} (got {as_written(value)})")
        if not match or int(match.group(2)) < int(match.group(1)):
            raise ConfigError("seeds", f"a range must read 'first..last' with first <= last (got {as_written(value)})")
        check_seed("seeds", int(match.group(2)))
        if int(match.group(2)) - int(match.group(1)) >= MAX_SEEDS:
            raise ConfigError("seeds", f"a range may hold at most {MAX_SEEDS} seeds (got {as_written(value)})")
        return list(range(int(match.group(1)), int(match.group(2)) + 1))
    if not isinstance(value, list) or not value:
        number = as_integer(value)
        hint = (f": [{number}] for seed {number} alone, or reps: {number} for seeds 1..{number}"
                if number is not None and number >= 0 else "")
        raise ConfigError("seeds",
                          f"must be a non-empty list of integers or 'first..last' (got {as_written(value)}){hint}")
    seeds = [as_integer(seed) for seed in value]
    for i, seed in enumerate(seeds):
        if seed is None or seed < 0:
            raise ConfigError(f"seeds[{i}]", f"must be an integer >= 0 (got {as_written(value[i])})")
        check_seed(f"seeds[{i}]", seed)
    if len(set(seeds)) != len(seeds):
        twice = sorted({seed for seed in seeds if seeds.count(seed) > 1})
        raise ConfigError("seeds", f"lists seed {', '.join(map(str, twice))} twice")
    return seeds


def parse_overrides(value: Any) -> Dict[str, List[Any]]:
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise ConfigError("overrides", "must be a mapping of scenario key -> list of values (a grid), or a list of "
                                       f"mappings of scenario key -> value (one cell each) (got {as_written(value)})")
    overrides = {}
    for key, values in value.items():
        where = f"overrides.{key}"
        check_override_key(where, key)
        values = values if isinstance(values, list) else [values]
        if not values:
            raise ConfigError(where, "must list at least one value")
        repeated = [v for k, v in enumerate(values) if v in values[:k]]    # 0 and 0.0 make the same cell
        if repeated:
            raise ConfigError(where, f"lists the value {as_written(repeated[0])} twice")
        overrides[key] = values
    check_nested_overrides(overrides)
    return overrides


def parse_override_sets(value: List[Any]) -> List[Dict[str, Any]]:
    """``overrides:`` as a list: each item is one cell, a mapping of dotted key -> its one value (a list value is
    one whole value, not a list of cells); ``{}`` is the scenario as it is."""
    if not value:
        raise ConfigError("overrides", "lists no cells: give at least one mapping (or {} for the scenario as it is)")
    sets = []
    for i, chosen in enumerate(value):
        where = f"overrides[{i}]"
        if chosen is None:
            chosen = {}
        if not isinstance(chosen, dict):
            raise ConfigError(where, f"must be a mapping of scenario key -> value, one cell (got {as_written(chosen)})")
        for key in chosen:
            check_override_key(f"{where}.{key}", key)
        check_nested_overrides(chosen, where)
        if chosen in sets:
            raise ConfigError(where, f"repeats overrides[{sets.index(chosen)}]: the two cells would be the same")
        sets.append(dict(chosen))
    return sets


def check_override_key(where: str, key: Any) -> None:
    if not isinstance(key, str) or not all(part.strip() for part in key.split(".")):
        raise ConfigError(where, "the key must be a dotted scenario key, e.g. params.inter_robot_distance_m")
    if key in ("name", "seed"):
        raise ConfigError(where, "cannot be overridden (the study sets names and seeds)")


def check_nested_overrides(overrides: Dict[str, Any], where: str = "overrides") -> None:
    """Refuse a key overridden inside another that is overridden whole (``object.mass`` and ``object``): the
    one applied last wins, so cells were labelled with masses that never ran."""
    for key in overrides:
        for outer in overrides:
            if key != outer and key.startswith(outer + "."):
                into = f"each value of {where}.{outer}" if where == "overrides" else f"{where}.{outer}"
                raise ConfigError(f"{where}.{key}", f"lies inside {where}.{outer}, which replaces all of {outer}: "
                                  f"one of them would be lost; put {key[len(outer) + 1:]} into {into} instead")


def parse_time_limit(where: str, value: Any) -> Optional[float]:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
        raise ConfigError(where, f"must be a number of seconds > 0 (got {as_written(value)})")
    return float(value)
