"""What ran in a study, for ``report.md``: its seeds, which code and scenario versions, and what the runs
were warned of (before them, and during some)."""
from __future__ import annotations

from collections import Counter
from typing import Any, Dict, List

from .aggregate import Cell
from .text import counted


def seeds_text(cells: List[Cell]) -> str:
    """'1-10 (9 cells), 1-3 (3 cells)': the repetitions each cell has, which the run counts alone hid."""
    by_seeds: Counter = Counter(tuple(sorted(cell.results)) for cell in cells)
    parts = [f"{span_text(list(seeds))} ({counted(count, 'cell')})" for seeds, count in by_seeds.most_common()]
    return ", ".join(parts) if parts else "none"


def span_text(seeds: List[int]) -> str:
    if seeds and seeds == list(range(seeds[0], seeds[-1] + 1)) and len(seeds) > 2:
        return f"{seeds[0]}-{seeds[-1]}"
    return ", ".join(map(str, seeds))


def code_text(cells: List[Cell]) -> str:
    """Which code ran: the behaviour's fingerprint each run recorded (the same fingerprint, the same code)."""
    versions = Counter(str((result.get("study") or {}).get("behaviour_sha1") or "?")
                       for cell in cells for result in cell.results.values())
    if len(versions) == 1:
        return (f"Behaviour code: `{next(iter(versions))}` in every run (`study.behaviour_sha1` in result.json: "
                "the same fingerprint, the same behaviour code).")
    return f"Behaviour code: {len(versions)} versions (see Mixed versions below)."


def version_section(cells: List[Cell]) -> List[str]:
    """Runs that ran different versions of their behaviour's code (``study.behaviour_sha1``: workers with other
    checkouts, or the code edited between two commands) or of their cell's scenario (``study.scenario_sha1``):
    their statistics mix what no single version would give."""
    lines = []
    by_behaviour: Dict[str, Counter] = {}
    for cell in cells:
        for result in cell.results.values():
            version = (result.get("study") or {}).get("behaviour_sha1")
            if version:
                by_behaviour.setdefault(str(result.get("behaviour")), Counter())[version] += 1
        scenarios = scenario_versions([r.get("study") or {} for r in cell.results.values()])
        if len(scenarios) > 1:
            lines.append(f"- `{cell.name}`: {len(scenarios)} versions of its scenario ({versions_text(scenarios)})")
    for behaviour, versions in sorted(by_behaviour.items()):
        if len(versions) > 1:
            lines.insert(0, f"- behaviour `{behaviour}`: {len(versions)} versions of its code "
                            f"({versions_text(versions)})")
    if not lines:
        return []
    return ["## Mixed versions", "",
            "**These results come from different versions of the code or scenarios** (`behaviour_sha1`, "
            "`scenario_sha1` in each result.json): a statistic over them describes none of the versions. Delete "
            "the runs of the versions you do not want and run the same command again.", "", *lines, ""]


def scenario_versions(studies: List[Dict[str, Any]]) -> Counter:
    """How many runs ran each version of a cell's scenario, when they ran more than one. Runs recorded before
    2026-11-29 have only the full fingerprint (description included) as scenario_sha1; later ones record it as
    scenario_sha1_full too, so a cell holding both is compared by that one. scenario_sha1 leaves out the
    scenario's time_limit_s when the study set the limit: runs with and without a study limit differ by that
    alone (said apart, as the time limits), so each is compared only with runs fingerprinted the same way."""
    recorded = [study for study in studies if study.get("scenario_sha1")]
    if not all(study.get("scenario_sha1_full") for study in recorded):
        return Counter(str(study.get("scenario_sha1_full") or study["scenario_sha1"]) for study in recorded)
    by_limit: Dict[bool, Counter] = {}
    for study in recorded:
        by_limit.setdefault(study.get("time_limit_s") is not None, Counter())[str(study["scenario_sha1"])] += 1
    return sum((versions for versions in by_limit.values() if len(versions) > 1), Counter())


def versions_text(versions: Counter) -> str:
    return ", ".join(f"`{version}` {counted(count, 'run')}" for version, count in versions.most_common())


def warning_section(cells: List[Cell]) -> List[str]:
    """The runs' result.json ``warnings``, once per cell: the simulator's word before the runs (it goes by the
    scenario), and apart from them, with their seeds, what the runner said during some runs (a step() slow in
    wall time, which depends on the machine's load). All were listed as said before the runs."""
    before, during = [], []
    for cell in cells:
        seeds_of: Dict[str, List[int]] = {}
        for seed, result in sorted(cell.results.items()):
            for warning in result.get("warnings") or []:
                if isinstance(warning, str) and seed not in seeds_of.setdefault(warning, []):
                    seeds_of[warning].append(seed)
        for warning, seeds in seeds_of.items():
            if said_during_the_run(warning):
                which = f"seed{'s' if len(seeds) > 1 else ''} {', '.join(map(str, seeds))}"
                during.append(f"- `{cell.name}` ({which}): {warning}")
            else:
                before.append(f"- `{cell.name}`: {warning}")
    lines = []
    if before:
        lines += ["Said before the runs started: what the simulator knew would doom, or often spoil, these cells' "
                  "runs.", "", *before, ""]
    if during:
        lines += ["Said during some runs (about the behaviour's code and the machine, not the run's outcome):", "",
                  *during, ""]
    return ["## Warnings", "", *lines] if lines else []


def said_during_the_run(warning: str) -> bool:
    """The runner's notes during a run (sim_backend/runner.py ``_note``): a slow step(), a step() that returned
    a value. Every other warning is said before the run."""
    return "of wall time at t =" in warning or "step() returned" in warning
