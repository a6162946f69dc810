"""The paper's numbers (data/README.md names the source), keyed the way our results are.

Our paper scenarios are named ``paper-<robots>-<path>``; the paper's per-run error data (CSV) spells the
zigzag path ``zigzac``. Everything here is read from files in ``data/`` so the numbers are never retyped.
"""
from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from functools import cache, lru_cache
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import yaml

DATA_DIR = Path(__file__).parent / "data"
ERRORS_CSV = DATA_DIR / "swarmhaul-errors.csv"
TIMES_YAML = DATA_DIR / "paper-times.yaml"

PAPER_ROBOTS = (25, 50, 100)
PAPER_PATHS = ("straight", "zigzag", "straight_rot")
IRREGULAR_SCENARIOS = ("irregular-cloud", "irregular-box_rotation", "irregular-clover")
IRREGULAR_ROBOTS = 30      # "The 3 irregular shapes took around 300 s to cage when using 30 robots"
# The CSV's metric codes in column c/p/r, named as in our result.json waypoints.
ERROR_METRICS = {0: "centroid_estimation_error_m", 1: "position_error_m", 2: "orientation_error_rad"}
CSV_PATH_NAMES = {"zigzac": "zigzag"}
PAPER_SCENARIO = re.compile(r"^paper-(\d+)-(straight_rot|straight|zigzag)$")

ErrorKey = Tuple[int, str, int, str]   # (robots, path, waypoint, metric)


@dataclass(frozen=True)
class PaperCase:
    """Which of the paper's experiments a scenario reproduces (None fields: not a paper case)."""

    robots: Optional[int] = None
    path: Optional[str] = None
    irregular: bool = False


def paper_case(scenario_name: str) -> PaperCase:
    match = PAPER_SCENARIO.match(scenario_name)
    if match and int(match.group(1)) in PAPER_ROBOTS:
        return PaperCase(robots=int(match.group(1)), path=match.group(2))
    if scenario_name in IRREGULAR_SCENARIOS:
        return PaperCase(irregular=True)
    return PaperCase()


def paper_scenarios() -> List[str]:
    """The paper's grid: 3 robot counts x 3 paths, then the three irregular caging-only objects."""
    return [f"paper-{n}-{path}" for n in PAPER_ROBOTS for path in PAPER_PATHS] + list(IRREGULAR_SCENARIOS)


@lru_cache(maxsize=1)
def error_samples() -> Dict[ErrorKey, Tuple[float, ...]]:
    """Per-run values of the paper's error figure: (robots, path, waypoint, metric) -> values."""
    samples: Dict[ErrorKey, Tuple[float, ...]] = {}
    with ERRORS_CSV.open(newline="", encoding="utf-8") as handle:
        for row in csv.DictReader(handle):
            path = CSV_PATH_NAMES.get(row["path"], row["path"])
            metric = ERROR_METRICS[int(float(row["c/p/r"]))]
            key = (int(float(row["robots"])), path, int(float(row["WP"])), metric)
            # Empty cells are repetitions the authors did not publish; skip them rather than read as 0.
            samples[key] = tuple(float(row[str(rep)]) for rep in range(1, 31) if row[str(rep)].strip())
    return samples


def error_values(case: PaperCase, waypoint: int, metric: str) -> Tuple[float, ...]:
    """The paper's per-run values for this case, waypoint and metric; empty when the paper has none."""
    if case.robots is None:
        return ()
    return error_samples().get((case.robots, case.path, waypoint, metric), ())


def error_waypoints(case: PaperCase) -> List[int]:
    """The waypoints the paper gives errors for in this case (none for a case that is not the paper's)."""
    if case.robots is None:
        return []
    return sorted({key[2] for key in error_samples() if key[:2] == (case.robots, case.path)})


@lru_cache(maxsize=1)
def quoted_numbers() -> dict:
    """data/paper-times.yaml: medians quoted in the paper's text."""
    return yaml.safe_load(TIMES_YAML.read_text(encoding="utf-8"))


def time_to_cage_s(case: PaperCase) -> Optional[float]:
    numbers = quoted_numbers()
    if case.irregular:
        return float(numbers["irregular_time_to_cage_s"])
    value = numbers["time_to_cage_s"].get(case.robots) if case.robots else None
    return None if value is None else float(value)


def time_to_push_s(case: PaperCase) -> Optional[float]:
    if case.robots is None:
        return None
    value = quoted_numbers()["time_to_push_s"].get(case.robots, {}).get(case.path)
    return None if value is None else float(value)


@cache
def scenario_time_limit_s(scenario_name: str) -> Optional[float]:
    """The time limit of the built-in scenario that reproduces a paper case (what the paper's runs had room for,
    as far as we know); None when there is no such scenario."""
    from onboard.config import ConfigError
    from sim_backend.scenario import load_builtin  # here: the scenarios need not load to read the paper's data

    try:
        return float(load_builtin(scenario_name).time_limit_s)
    except ConfigError:        # no such built-in scenario: nothing to compare with
        return None
