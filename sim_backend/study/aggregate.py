"""From a study folder's result.json files to per-cell statistics and ``summary.csv``.

Statistics are over the runs that did not fail (``failed: true`` runs are counted, never averaged). A
distribution is summarised by its median and its spread: quartiles (numpy's linear interpolation) and
min/max. Rates are fractions of the runs that did not fail.
"""
from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from onboard.config import is_whole_number
from onboard.sorting import natural_key

from . import paper_reference as paper
from .paper_reference import PaperCase
from .worker import RESULT_FILE, read_result

WAYPOINT_METRICS = ("centroid_estimation_error_m", "position_error_m", "orientation_error_rad",
                    "effective_pushers", "effective_rotators")
RUN_METRICS = ("time_to_cage_s", "time_to_complete_s", "cage_size", "cage_spacing_mean_m", "cage_spacing_std_m",
               "final_position_error_m", "final_orientation_error_rad", "wall_time_s")
# result.json keeps the cage spacing as {"mean": m, "std": s}; the summary flattens it to two run metrics.
NESTED_METRICS = {"cage_spacing_mean_m": ("cage_spacing_m", "mean"), "cage_spacing_std_m": ("cage_spacing_m", "std")}
CAGED_ONLY = ("cage_size",)
# Top-level numbers and true/false fields every result.json has, or the transport's evaluator gives and the
# summary already covers: any other is the behaviour's own (its evaluator's result()), summarised as it is.
FRAMEWORK_FIELDS = frozenset(("seed", "robots", "sim_time_s", "real_time_factor", "failed", "caged", "completed",
                              "cage_encloses_object", *RUN_METRICS))
CSV_COLUMNS = ("cell", "scenario", "robots", "overrides", "metric", "waypoint", "n", "value", "q1", "q3",
               "min", "max", "paper_value", "paper_n")


@dataclass
class Distribution:
    n: int
    median: float
    q1: float
    q3: float
    min: float
    max: float


def distribution(values: Sequence[float]) -> Optional[Distribution]:
    finite = [float(v) for v in values if v is not None and math.isfinite(v)]
    if not finite:
        return None
    q1, median, q3 = np.percentile(finite, [25, 50, 75])
    return Distribution(len(finite), float(median), float(q1), float(q3), min(finite), max(finite))


@dataclass
class Cell:
    """All runs of one (scenario, overrides) cell; ``results`` holds every run, failed ones included."""

    name: str
    scenario: str
    robots: Optional[int]
    overrides: Dict[str, Any]
    case: PaperCase
    results: Dict[int, Dict[str, Any]] = field(default_factory=dict)   # seed -> result

    @property
    def ok(self) -> List[Dict[str, Any]]:
        return [r for _, r in sorted(self.results.items()) if not r.get("failed")]

    @property
    def failed(self) -> List[Tuple[int, Dict[str, Any]]]:
        return [(seed, r) for seed, r in sorted(self.results.items()) if r.get("failed")]

    @property
    def has_path(self) -> bool:
        return any("completed" in r for r in self.ok)

    @property
    def cages(self) -> bool:
        """Its runs cage an object: a run says so, or it reproduces a paper case, or its runs (failed ones too,
        which say nothing of caging) ran the transport behaviour."""
        results = list(self.results.values())
        return (self.case != PaperCase() or any("caged" in r for r in results)
                or any(r.get("behaviour") == "transport" for r in results))

    def time_limits_s(self) -> List[float]:
        """The time limits its runs ran with, where the study replaced the scenario's own (``--time-limit``, a
        study's ``time_limit_s``, or an override of ``time_limit_s``)."""
        limits = [(r.get("study") or {}).get("time_limit_s") for r in self.results.values()]
        limits.append(self.overrides.get("time_limit_s"))
        return [float(v) for v in limits if isinstance(v, (int, float)) and not isinstance(v, bool)]

    @property
    def shortened(self) -> bool:
        """Some of its runs were stopped before the time limit of the paper's scenario it reproduces."""
        if self.case == PaperCase():
            return False
        own = paper.scenario_time_limit_s(self.scenario)
        return own is not None and any(limit < own for limit in self.time_limits_s())

    def values(self, key: str) -> List[float]:
        # A cage that never closed has no size (result.json says 0): count cage sizes of caged runs only.
        runs = [r for r in self.ok if r.get("caged")] if key in CAGED_ONLY else self.ok
        values = (run_value(r, key) for r in runs)
        return [v for v in values if isinstance(v, (int, float)) and not isinstance(v, bool)]

    def own_numbers(self) -> List[str]:
        """The behaviour's own numbers (its evaluator's top-level fields, not ``FRAMEWORK_FIELDS``), in the
        order its runs give them."""
        return self._own_fields(lambda v: isinstance(v, (int, float)) and not isinstance(v, bool))

    def own_flags(self) -> List[str]:
        """The behaviour's own true/false fields (an evaluator's ``"gathered": true``): a rate each."""
        return self._own_fields(lambda v: isinstance(v, bool))

    def _own_fields(self, kind) -> List[str]:
        names: Dict[str, None] = {}
        for result in self.ok:
            names.update((k, None) for k, v in result.items() if k not in FRAMEWORK_FIELDS and kind(v))
        return list(names)

    def waypoint_values(self, index: int, key: str) -> List[float]:
        out = []
        for result in self.ok:
            for waypoint in result.get("waypoints") or []:
                if waypoint.get("index") == index and isinstance(waypoint.get(key), (int, float)):
                    out.append(waypoint[key])
        return out

    def waypoint_indices(self) -> List[int]:
        return sorted({w["index"] for r in self.ok for w in r.get("waypoints") or [] if "index" in w})

    def compared_waypoints(self) -> List[int]:
        """The waypoints our runs reached or the paper gives errors for: a waypoint no run reached keeps the
        paper's numbers beside an empty ours (the rows of waypoints 5-9 went missing without a word)."""
        return sorted(set(self.waypoint_indices()) | set(paper.error_waypoints(self.case)))

    def rate(self, predicate) -> Optional[float]:
        ok = self.ok
        return sum(1 for r in ok if predicate(r)) / len(ok) if ok else None


def run_value(result: Dict[str, Any], key: str) -> Any:
    """``result[key]``, or for a flattened metric (``NESTED_METRICS``) the field inside its record."""
    if key not in NESTED_METRICS:
        return result.get(key)
    record, field_name = NESTED_METRICS[key]
    nested = result.get(record)
    return nested.get(field_name) if isinstance(nested, dict) else None


@dataclass
class StudyResults:
    root: Path
    cells: List[Cell]
    unreadable: List[str]   # result.json files that exist but cannot be read


def load_results(out_dir: Path) -> StudyResults:
    cells: Dict[str, Cell] = {}
    unreadable = []
    for path in sorted(out_dir.glob(f"*/seed-*/{RESULT_FILE}")):
        result = read_result(path.parent)
        seed_text = path.parent.name[len("seed-"):]
        # seed-² (int() refuses it) is not a run's folder; seed 1's result copied into seed-2 is not seed 2's run
        if not result or not is_whole_number(seed_text) or result.get("seed") != int(seed_text):
            unreadable.append(str(path.relative_to(out_dir)))
            continue
        name = path.parent.parent.name
        if name not in cells:
            study = result.get("study") or {}
            scenario = str(result.get("scenario", name.split("@")[0]))
            overrides = dict(study.get("overrides") or {})
            source = study.get("scenario")
            cells[name] = Cell(name, scenario, result.get("robots"), overrides,
                               paper_case_of(scenario, result.get("robots"), overrides,
                                             source if isinstance(source, str) else None))
        cells[name].results[int(seed_text)] = result
    return StudyResults(out_dir, sorted(cells.values(), key=cell_order), unreadable)


# Object fields that make another object (not where it starts, how heavy or how slippery it is).
OBJECT_IDENTITY = ("shape", "size", "radius", "vertices", "parts", "scale", "static")


def paper_case_of(scenario: str, robots: Any, overrides: Dict[str, Any], source: Optional[str] = None) -> PaperCase:
    """The paper's experiment a cell reproduces, by its scenario's name, unless the cell is not that experiment:
    a scenario file merely named like it (``source``, the scenario as the study named it, is a path rather than
    the built-in name; None for results from before it was recorded), or a cell that changed what identifies it:
    another robot count (``robots.count``), path or object. The paper's numbers for 25 robots are not those of 12
    robots pushing the 25-robot box, nor of 25 robots pushing another box."""
    case = paper.paper_case(scenario)
    if case == PaperCase():
        return case
    if source not in (None, scenario) or changes_object(overrides) or changes_path(overrides):
        return PaperCase()
    paper_robots = paper.IRREGULAR_ROBOTS if case.irregular else case.robots
    return case if robots == paper_robots else PaperCase()


def changes_object(overrides: Dict[str, Any]) -> bool:
    return any(key == "object" or key in {f"object.{name}" for name in OBJECT_IDENTITY} for key in overrides)


def changes_path(overrides: Dict[str, Any]) -> bool:
    return any(key == "path" or key.startswith("path.") for key in overrides)


PAPER_TIMES = {"time_to_cage_s": paper.time_to_cage_s, "time_to_complete_s": paper.time_to_push_s}


def paper_time_s(cell: Cell, metric: str) -> Optional[float]:
    """The paper's median of a time (``PAPER_TIMES``) for this cell; None when the paper has none, and when the
    cell's runs were stopped early: a run that would have caged or completed after its limit has no time, so
    our median is one of the fast runs only, and beside the paper's it would read as a speed-up."""
    return None if cell.shortened else PAPER_TIMES[metric](cell.case)


def cell_order(cell: Cell) -> tuple:
    """Paper cells in the paper's order (robots, then path), then irregular objects, then the rest; within
    one scenario, numbers in the cell name by value (``count=6`` before ``count=40``)."""
    case = cell.case
    if case.robots is not None:
        return (0, case.robots, paper.PAPER_PATHS.index(case.path), natural_key(cell.name))
    return (1 if case.irregular else 2, 0, 0, natural_key(cell.name))


@dataclass
class SummaryRow:
    metric: str
    n: int
    value: Optional[float]
    spread: Optional[Distribution] = None
    waypoint: Optional[int] = None
    paper_value: Optional[float] = None
    paper_n: Optional[int] = None


def success_rate(cell: Cell) -> Optional[float]:
    """Completed (every waypoint, within tolerance) for a transport; caged round the object for a caging-only
    run (a cage the ground truth finds closed on one side of it does not count; results from before that
    check count when caged); None for a behaviour whose results say neither (another behaviour's own metrics
    are in its result.json)."""
    if cell.has_path:
        return cell.rate(lambda r: bool(r.get("completed")))
    if any("caged" in r for r in cell.ok):
        return cell.rate(lambda r: bool(r.get("caged")) and r.get("cage_encloses_object") is not False)
    return None


def cell_rows(cell: Cell) -> List[SummaryRow]:
    ok = len(cell.ok)
    rows = [SummaryRow("runs", len(cell.results), len(cell.results)),
            SummaryRow("failed_runs", len(cell.results), len(cell.failed))]
    if any("caged" in r for r in cell.ok):
        rows.append(SummaryRow("caged_rate", ok, cell.rate(lambda r: bool(r.get("caged")))))
    if cell.has_path:
        rows.append(SummaryRow("all_waypoints_rate", ok, cell.rate(lambda r: r.get("time_to_complete_s") is not None)))
        rows.append(SummaryRow("completed_rate", ok, cell.rate(lambda r: bool(r.get("completed")))))
    rows.append(SummaryRow("success_rate", ok, success_rate(cell)))
    for metric in RUN_METRICS:
        paper_value = paper_time_s(cell, metric) if metric in PAPER_TIMES else None
        rows.append(distribution_row(metric, cell.values(metric), paper_value))
    for metric in cell.own_numbers():
        rows.append(distribution_row(metric, cell.values(metric), None))
    for metric in cell.own_flags():
        rows.append(SummaryRow(f"{metric}_rate", len(cell.ok), cell.rate(lambda r, key=metric: r.get(key) is True)))
    for index in cell.waypoint_indices():
        for metric in WAYPOINT_METRICS:
            reference = paper.error_values(cell.case, index, metric)
            reference_median = float(np.median(reference)) if reference else None
            rows.append(distribution_row(metric, cell.waypoint_values(index, metric), reference_median,
                                         index, len(reference) or None))
    always = {"runs", "failed_runs", *time_metrics(cell)}
    return [row for row in rows if row.n or (row.metric in always and row.waypoint is None)]


def time_metrics(cell: Cell) -> List[str]:
    """The times a cell's summary has a row for even without a value (every run failed, or none caged), so that
    the cell is not missing from a table of times: wall_time_s always; the time to cage for a cell that cages
    (said by a run, or known from its paper case or its transport behaviour when every run failed before
    saying); the time to complete when it has a path, or may have one (its runs all failed)."""
    caging = cell.cages
    without_path = cell.case.irregular or (bool(cell.ok) and not cell.has_path)
    times = ["wall_time_s"]
    if caging:
        times.append("time_to_cage_s")
    if cell.has_path or (caging and not without_path):
        times.append("time_to_complete_s")
    return times


def distribution_row(metric: str, values: List[float], paper_value: Optional[float], waypoint: Optional[int] = None,
                     paper_n: Optional[int] = None) -> SummaryRow:
    spread = distribution(values)
    return SummaryRow(metric, spread.n if spread else 0, spread.median if spread else None, spread, waypoint,
                      paper_value, paper_n)


def number_text(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def overrides_text(overrides: Dict[str, Any]) -> str:
    """``key=value`` pairs separated by spaces; a list or mapping value as compact JSON, so that it has no
    spaces (a dict's repr did) and reads back with ``json.loads``."""
    return " ".join(f"{key}={override_value_text(value)}" for key, value in overrides.items())


def override_value_text(value: Any) -> str:
    if isinstance(value, (dict, list, tuple)) or value is None:
        return json.dumps(value, separators=(",", ":"))      # None as null, as the study file and JSON say it
    return str(value)


def write_summary_csv(results: StudyResults, path: Path) -> Path:
    """One row per (cell, metric[, waypoint]); see docs/study.md for the columns."""
    with path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(CSV_COLUMNS)
        for cell in results.cells:
            for row in cell_rows(cell):
                s = row.spread
                writer.writerow([cell.name, cell.scenario, number_text(cell.robots), overrides_text(cell.overrides),
                                 row.metric, number_text(row.waypoint), row.n, number_text(row.value),
                                 *(number_text(getattr(s, k)) if s else "" for k in ("q1", "q3", "min", "max")),
                                 number_text(row.paper_value), number_text(row.paper_n)])
    return path
