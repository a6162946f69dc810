"""``report.md``: a study's outcome per cell and its errors per waypoint, next to the paper's numbers."""
from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from . import paper_reference as paper
from .aggregate import (
    Cell,
    PaperCase,
    StudyResults,
    distribution,
    load_results,
    paper_time_s,
    success_rate,
    write_summary_csv,
)
from .driver import UNWRITABLE_KEY, outcome_text, read_study
from .provenance import code_text, seeds_text, version_section, warning_section
from .text import counted

# Every file ``write_figures`` may draw. One this aggregation does not draw is removed: it would show an earlier
# aggregation's runs beside a summary of the current ones (and report.md would not link it).
FIGURE_FILES = ("times.png", "errors.png", "effective.png", "trajectories.png")

ERROR_COLUMNS = (("centroid_estimation_error_m", "centroid est. err (m)"),
                 ("position_error_m", "position err (m)"),
                 ("orientation_error_rad", "orientation err (rad)"))


def number(value: Optional[float], digits: int = 3) -> str:
    if value is None:
        return "–"
    if abs(value) < 10:
        return f"{value:.{digits}g}"
    return f"{value:.0f}" if float(value).is_integer() else f"{value:.1f}"


def median_and_spread(values: List[float], digits: int = 3) -> str:
    """``median [q1–q3]``, or the single value, or ``–`` when there is none."""
    spread = distribution(values)
    if spread is None:
        return "–"
    if spread.n == 1:
        return number(spread.median, digits)
    return f"{number(spread.median, digits)} [{number(spread.q1, digits)}–{number(spread.q3, digits)}]"


def percent(value: Optional[float]) -> str:
    return "–" if value is None else f"{100 * value:.0f}%"


def count_of(cell: Cell, key: str) -> str:
    ok = cell.ok
    if not any(key in r for r in ok):
        return "–"
    return f"{sum(1 for r in ok if r.get(key))}/{len(ok)}"


def write_study_outputs(out_dir: Path, figures: bool = True) -> Dict[str, Path]:
    """(Re)build summary.csv, the figures and report.md from the run folders under ``out_dir``."""
    results = load_results(out_dir)
    files = {"summary": write_summary_csv(results, out_dir / "summary.csv")}
    drawn: Dict[str, Path] = {}
    if figures:
        from .figures import write_figures  # matplotlib only when drawing

        drawn = write_figures(results, out_dir / "figures")
    remove_stale_figures(out_dir / "figures", drawn)
    files["report"] = write_report(results, read_study(out_dir), out_dir / "report.md", drawn)
    files.update({f"figure {name}": path for name, path in drawn.items()})
    return files


def remove_stale_figures(folder: Path, drawn: Dict[str, Path]) -> None:
    """Remove the figures of an earlier aggregation that this one did not redraw (``--no-figures``, or a
    figure whose data is gone); ``khepri study report DIR`` draws them again from the runs."""
    kept = {path.name for path in drawn.values()}
    for name in FIGURE_FILES:
        if name not in kept:
            (folder / name).unlink(missing_ok=True)


def write_report(results: StudyResults, study: Dict[str, Any], path: Path, figures: Dict[str, Path]) -> Path:
    lines = header(results, study)
    lines += version_section(results.cells)
    lines += warning_section(results.cells)
    lines += outcome_table(results.cells)
    lines += own_metrics_table(results.cells)
    lines += error_tables(results.cells)
    lines += effective_tables(results.cells)
    lines += figure_section(figures, path.parent)
    lines += failure_section(results, unwritable_runs(results, study))
    if compares_with_the_paper(results.cells):
        lines += source_section()
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def header(results: StudyResults, study: Dict[str, Any]) -> List[str]:
    runs = sum(len(c.results) for c in results.cells)
    failed = sum(len(c.failed) for c in results.cells)
    lines = [f"# Study `{study.get('name', results.root.name)}`", ""]
    commands = study.get("commands") or []
    if commands:
        lines += ["Commands that wrote this folder:", "", "```sh", *commands, "```", ""]
    unreadable = f", {len(results.unreadable)} unreadable (listed below)" if results.unreadable else ""
    lines += [f"{counted(runs, 'run')} in {counted(len(results.cells), 'cell')}, {failed} failed (crashed or stopped; "
              f"excluded from the statistics){unreadable}. Time limit: {time_limit_text(results.cells)}.", ""]
    planned, missing = missing_runs(results, study)
    if missing:
        shown = ", ".join(f"`{d}`" for d in missing[:8]) + (" ..." if len(missing) > 8 else "")
        lines += [f"**{len(missing)} of the {len(planned)} runs the commands above asked for have no "
                  f"result yet** (not run, or interrupted): {shown}. Running the same command again runs them.",
                  ""]
    lines += [f"Seeds: {seeds_text(results.cells)}. {code_text(results.cells)}", ""]
    paper_note = (" Paper: medians from the paper (times quoted in its text; errors from its per-run data)."
                  if compares_with_the_paper(results.cells) else "")
    lines += ["Values are medians over the runs that did not fail, with the interquartile range in brackets."
              + paper_note, ""]
    return lines


def compares_with_the_paper(cells: List[Cell]) -> bool:
    """Some cell is one of the paper's experiments (``aggregate.paper_case_of``): the report cites its data."""
    return any(cell.case != PaperCase() for cell in cells)


def time_limit_text(cells: List[Cell]) -> str:
    """The limits the runs here ran with (each result.json records its own), not the latest command's."""
    counts: Dict[Any, int] = {}
    for cell in cells:
        for result in cell.results.values():
            limit = (result.get("study") or {}).get("time_limit_s")
            counts[limit] = counts.get(limit, 0) + 1
    if not counts:
        return "–"

    def text(limit: Any) -> str:
        return f"{limit:g} s" if isinstance(limit, (int, float)) else "each scenario’s own"

    if len(counts) == 1:
        limit = next(iter(counts))
        return f"{text(limit)} for every run" if isinstance(limit, (int, float)) else text(limit)
    return "mixed: " + ", ".join(f"{text(limit)} ({counted(n, 'run')})" for limit, n in counts.items())


def unwritable_runs(results: StudyResults, study: Dict[str, Any]) -> Dict[str, str]:
    """The runs whose result.json could not be written (study.json ``unwritable``), and why; a run that has a
    result by now (the folder was fixed and the study resumed) is no longer one of them."""
    recorded = study.get(UNWRITABLE_KEY)
    if not isinstance(recorded, dict):
        return {}
    present = {f"{cell.name}/seed-{seed}" for cell in results.cells for seed in cell.results}
    return {str(run_dir): str(why) for run_dir, why in recorded.items() if run_dir not in present}


def missing_runs(results: StudyResults, study: Dict[str, Any]) -> Tuple[List[str], List[str]]:
    """The run folders the study's commands asked for (study.json ``planned``), and those that hold no
    result."""
    present = {f"{cell.name}/seed-{seed}" for cell in results.cells for seed in cell.results}
    planned = study.get("planned")
    planned = [d for d in planned if isinstance(d, str)] if isinstance(planned, list) else []
    return planned, [d for d in planned if d not in present]


def is_transport(cell: Cell) -> bool:
    """A cell whose runs report caging (the transport's evaluator), or would have, had they not all failed: the
    transport tables apply to it (a lab-6 cell whose runs all failed was listed among "other behaviours")."""
    return cell.has_path or cell.cages


def outcome_table(cells: List[Cell]) -> List[str]:
    others = [c for c in cells if not is_transport(c)]
    cells = [c for c in cells if is_transport(c)]
    lines = generic_outcome_table(others)
    if not cells:
        return lines
    lines += ["## Outcome per cell", "",
             "Success = completed (every waypoint reached within the tolerances) for a transport, caged for a "
             "caging-only run.", "",
             "| cell | robots | runs | failed | caged | all waypoints | success | time to cage (s) | paper | "
             "time to complete (s) | paper | cage size | cage spacing (m) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for cell in cells:
        all_waypoints = (f"{sum(1 for r in cell.ok if r.get('time_to_complete_s') is not None)}/{len(cell.ok)}"
                         if cell.has_path else "–")
        lines.append(
            f"| {cell.name} | {cell.robots if cell.robots is not None else '–'} | {len(cell.results)} | "
            f"{len(cell.failed)} | {count_of(cell, 'caged')} | {all_waypoints} | {percent(success_rate(cell))} | "
            f"{median_and_spread(cell.values('time_to_cage_s'), 4)} | "
            f"{number(paper_time_s(cell, 'time_to_cage_s'), 4)} | "
            f"{median_and_spread(cell.values('time_to_complete_s'), 4)} | "
            f"{number(paper_time_s(cell, 'time_to_complete_s'), 4)} | {median_and_spread(cell.values('cage_size'))} | "
            f"{spacing_text(cell)} |")
    return lines + [""] + shortened_note(cells)


def shortened_note(cells: List[Cell]) -> List[str]:
    """Why a paper cell has no paper times: its runs were stopped before its scenario's own time limit."""
    shortened = [cell for cell in cells if cell.shortened]
    if not shortened:
        return []
    listed = ", ".join(f"`{cell.name}` ({'/'.join(f'{v:g}' for v in sorted(set(cell.time_limits_s())))} s, "
                       f"not {paper.scenario_time_limit_s(cell.scenario):g} s)" for cell in shortened)
    return [f"Paper times left out: these cells' runs were stopped before their scenario's own time limit "
            f"(`--time-limit`), so runs that would have caged or completed later have no time and our medians "
            f"are of the fast runs only: {listed}.", ""]


def generic_outcome_table(cells: List[Cell]) -> List[str]:
    """Cells of another behaviour (no caging, no path): how their runs ended, and when."""
    if not cells:
        return []
    lines = ["## Outcome per cell (other behaviours)", "",
             "How the runs ended, and the simulated time of those whose robots all reported `finished`.", "",
             "| cell | robots | runs | failed | ended by | time to finish (s) | simulated (s) |",
             "|---|---|---|---|---|---|---|"]
    for cell in cells:
        reasons = Counter(str(r.get("stop_reason")) for r in cell.ok)
        ended = ", ".join(f"{reason} {count}" for reason, count in reasons.most_common()) or "–"
        finished = [float(r["sim_time_s"]) for r in cell.ok
                    if r.get("stop_reason") == "behaviour finished" and isinstance(r.get("sim_time_s"), (int, float))]
        lines.append(f"| {cell.name} | {cell.robots if cell.robots is not None else '–'} | {len(cell.results)} | "
                     f"{len(cell.failed)} | {ended} | {median_and_spread(finished, 4)} | "
                     f"{median_and_spread(cell.values('sim_time_s'), 4)} |")
    return lines + [""]


def own_metrics_table(cells: List[Cell]) -> List[str]:
    """The numbers and true/false fields a behaviour's evaluator adds to result.json (``Cell.own_numbers``,
    ``own_flags``), per cell: what a study of one's own behaviour is run for."""
    rows = []
    for cell in cells:
        for metric in cell.own_numbers():
            spread = distribution(cell.values(metric))
            extremes = f"{number(spread.min)} – {number(spread.max)}" if spread and spread.n > 1 else "–"
            rows.append(f"| {cell.name} | `{metric}` | {spread.n if spread else 0} | "
                        f"{median_and_spread(cell.values(metric))} | {extremes} |")
        for metric in cell.own_flags():
            rate = cell.rate(lambda r, key=metric: r.get(key) is True)
            rows.append(f"| {cell.name} | `{metric}` | {len(cell.ok)} | true in {percent(rate)} | – |")
    if not rows:
        return []
    return ["## The behaviour's own results", "",
            "Every other number or true/false field of the runs' result.json (what the behaviour's evaluator "
            "returns): median [interquartile range] and extremes, or how often it was true.", "",
            "| cell | field | n | value | min – max |", "|---|---|---|---|---|", *rows, ""]


def spacing_text(cell: Cell) -> str:
    """The median over runs of each run's mean distance between neighbouring members while transporting, and
    the median of their standard deviations (``±``): a cage that opens up shows as a large ``±``."""
    means, stds = cell.values("cage_spacing_mean_m"), cell.values("cage_spacing_std_m")
    if not means:
        return "–"
    spread = distribution(stds)
    return f"{number(distribution(means).median)}" + (f" ± {number(spread.median, 2)}" if spread else "")


def error_tables(cells: List[Cell]) -> List[str]:
    if not any(cell.compared_waypoints() for cell in cells):
        return []                  # no cell follows a path: no waypoint, no table, no heading
    lines = ["## Errors per waypoint, ours vs the paper", "",
             "`n` = our runs that reached the waypoint. Paper: median over its runs (MISTLab/SwarmHaul "
             "`Errors.csv`).", ""]
    for cell in cells:
        indices = cell.compared_waypoints()
        if not indices:
            continue
        lines += [f"### {cell.name}", "",
                  "| WP | n | " + " | ".join(f"{label} ours | paper" for _, label in ERROR_COLUMNS) + " |",
                  "|---|---|" + "---|---|" * len(ERROR_COLUMNS)]
        for index in indices:
            cells_text = []
            for metric, _ in ERROR_COLUMNS:
                reference = paper.error_values(cell.case, index, metric)
                cells_text.append(f"{median_and_spread(cell.waypoint_values(index, metric))} | "
                                  f"{number(float(np.median(reference))) if reference else '–'}")
            reached = len(cell.waypoint_values(index, "position_error_m"))
            lines.append(f"| {index} | {reached} | " + " | ".join(cells_text) + " |")
        lines.append("")
    return lines


def effective_tables(cells: List[Cell]) -> List[str]:
    path_cells = [c for c in cells if c.waypoint_indices()]
    if not path_cells:
        return []
    lines = ["## Effective pushers and rotators per waypoint (ours; the paper gives no numbers)", "",
             "Each entry: pushers / rotators, medians over the runs that reached the waypoint.", ""]
    width = max(max(c.waypoint_indices()) for c in path_cells) + 1
    lines += ["| cell | " + " | ".join(f"WP{i}" for i in range(width)) + " |", "|---|" + "---|" * width]
    for cell in path_cells:
        entries = []
        for index in range(width):
            pushers = distribution(cell.waypoint_values(index, "effective_pushers"))
            rotators = distribution(cell.waypoint_values(index, "effective_rotators"))
            entries.append(f"{number(pushers.median if pushers else None)} / "
                           f"{number(rotators.median if rotators else None)}")
        lines.append(f"| {cell.name} | " + " | ".join(entries) + " |")
    return lines + [""]


def figure_section(figures: Dict[str, Path], folder: Path) -> List[str]:
    if not figures:
        return []
    lines = ["## Figures", ""]
    for title, path in figures.items():
        lines += [f"### {title}", "", f"![{title}]({path.relative_to(folder).as_posix()})", ""]
    return lines


def failure_section(results: StudyResults, unwritable: Dict[str, str]) -> List[str]:
    failed = [(cell.name, seed, result) for cell in results.cells for seed, result in cell.failed]
    if not failed and not results.unreadable and not unwritable:
        return []
    lines = ["## Failed runs", ""]
    if failed:
        lines += ["Re-run them with `--retry-failed`.", ""]
        lines += [f"- `{name}` seed {seed}: {outcome_text(result)[len('FAILED: '):]}" for name, seed, result in failed]
        lines.append("")
    if unwritable:
        lines += ["Their folder could not be written, so they have no result.json (make the folder writable and run "
                  "the same command again):", ""]
        lines += [f"- `{run_dir}`: {why}" for run_dir, why in unwritable.items()]
        lines.append("")
    if results.unreadable:
        lines += ["Unreadable, or not a run's result.json (left out; a run of the study's grid is run again when "
                  "the study resumes, other folders are ignored):", ""]
        lines += [f"- `{path}`" for path in results.unreadable]
        lines.append("")
    return lines


def source_section() -> List[str]:
    return ["## Paper data", "",
            "Varadharajan, Soma, Beltrame, \"Collective transport via sequential caging\". Errors per waypoint: "
            "the authors' per-run data (MISTLab/SwarmHaul `plotting/Data/Errors.csv`); times: medians quoted in "
            "the paper's text. Copies and notes: `sim_backend/study/data/`.", ""]
