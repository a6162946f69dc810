"""``khepri study``: the grid, real runs through a process pool and a Dask LocalCluster, resume, failures,
and the aggregation (summary.csv, report.md, figures) of known results."""
import csv
import io
import json
import logging
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from khepri_cli.main import main
from onboard.config import ConfigError
from sim_backend.scenario import load_scenario
from sim_backend.study import paper_reference as paper
from sim_backend.study.aggregate import load_results
from sim_backend.study.driver import StudyProgress, longest_first, run_study
from sim_backend.study.executors import WORKER_DIED, LocalExecutor
from sim_backend.study.grid import behaviour_code_sha1, expand
from sim_backend.study.report import FIGURE_FILES, write_study_outputs
from sim_backend.study.study_file import load_study_file, paper_study, parse_study
from sim_backend.study.worker import execute_run

# Small and fast: lab-6 (6 robots) and a failing cell, a few simulated seconds each.
TINY_STUDY = """
name: tiny
scenarios: [lab-6]
seeds: 1..2
time_limit_s: 4
"""
# A behaviour with a bug (it raises 1 s into the run): the failing cell of the tiny study.
CRASHING_MODULE = """
from dataclasses import dataclass, field

from onboard.behaviour import Behaviour, register


@dataclass
class CrashingParams:
    path: list = field(default_factory=list)


@register("crashing")
class Crashing(Behaviour):
    Params = CrashingParams

    def step(self):
        if self.robot.clock.now() >= 1.0:
            raise RuntimeError("a deliberate bug, 1 s in")
"""
GOOD, CRASHING = "lab-6@behaviour=transport", "lab-6@behaviour=crashing"
HUNDRED_DROPS = ", ".join(f"0.{i:03d}" for i in range(100))
DEEP_JSON = "[" * 100_000 + "]" * 100_000      # valid JSON, but past Python's recursion limit: RecursionError


def write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def results_in(out: Path) -> dict:
    return {str(p.relative_to(out).parent): json.loads(p.read_text()) for p in sorted(out.glob("*/seed-*/result.json"))}


def comparable(result: dict) -> dict:
    """A result without what depends on the machine's speed."""
    return {k: v for k, v in result.items() if k not in ("wall_time_s", "real_time_factor")}


# --- the grid ------------------------------------------------------------------------------------------

def test_the_paper_grid_is_nine_transport_cases_and_three_irregular_objects():
    runs = expand(paper_study(2))
    cells = list(dict.fromkeys(r.cell for r in runs))
    assert cells == [f"paper-{n}-{p}" for n in (25, 50, 100) for p in ("straight", "zigzag", "straight_rot")] + [
        "irregular-cloud", "irregular-box_rotation", "irregular-clover"]
    assert [r.seed for r in runs if r.cell == "irregular-clover"] == [1, 2]
    assert len(runs) == 24


def test_the_runs_that_may_take_longest_go_to_the_workers_first():
    """Three 100-robot runs queued behind 24 short ones would each finish alone on a worker at the end; first
    in the queue, they run beside the short ones. Equals keep the grid's order."""
    runs = longest_first(expand(paper_study(2)))
    robots = [r.scenario_data["robots"]["count"] for r in runs]
    assert robots == sorted(robots, reverse=True) and robots[:6] == [100] * 6
    assert [(r.cell, r.seed) for r in runs[:3]] == [("paper-100-straight", 1), ("paper-100-straight", 2),
                                                  ("paper-100-zigzag", 1)]


@pytest.mark.parametrize("path", sorted((Path(__file__).parent.parent / "sim_backend" / "studies").glob("*.yaml")),
                         ids=lambda p: p.stem)
def test_every_shipped_study_file_expands_to_valid_cells(path):
    """The study files docs/behaviour.md points to: each scenario and override is built and checked."""
    runs = expand(load_study_file(path))
    assert runs and len({r.cell for r in runs}) >= 2
    assert all(r.seed >= 1 for r in runs)


def test_overrides_make_a_cartesian_product_of_cells(tmp_path):
    spec = parse_study({"name": "spacing", "scenarios": ["lab-6"], "reps": 2,
                        "overrides": {"params.inter_robot_distance_m": [0.45, 0.65], "comm.drop": [0.0, 0.1]}})
    runs = expand(spec)
    assert len(runs) == 8
    first = runs[0]
    assert first.cell == "lab-6@params.inter_robot_distance_m=0.45@comm.drop=0"
    assert first.scenario_data["params"]["inter_robot_distance_m"] == 0.45
    assert runs[-1].scenario_data["comm"]["drop"] == 0.1
    assert runs[-1].run_dir == "lab-6@params.inter_robot_distance_m=0.65@comm.drop=0.1/seed-2"


def test_overrides_listed_one_cell_each_change_keys_together(tmp_path):
    """`overrides:` as a list of cells: robots.count and object.size paired, not crossed (a grid gave 4 cells, two
    of them 3 robots round a big box); a list value in a cell is one whole value, and {} is the scenario."""
    spec = parse_study({"name": "pairs", "scenarios": ["lab-6"], "seeds": [1], "overrides": [
        {}, {"robots.count": 4, "object.size": [0.2, 0.2]},
        {"robots.count": 8, "object.size": [0.5, 0.5], "robots.spawn.x": [-1.6, -0.6]}]})
    runs = expand(spec)
    assert [run.cell for run in runs] == ["lab-6", "lab-6@robots.count=4@object.size=0.2,0.2",
                                          "lab-6@robots.count=8@object.size=0.5,0.5@robots.spawn.x=-1.6,-0.6"]
    assert [(r.scenario_data["robots"]["count"], r.scenario_data["object"]["size"]) for r in runs] == \
        [(6, [0.285, 0.435]), (4, [0.2, 0.2]), (8, [0.5, 0.5])]
    assert runs[2].scenario_data["robots"]["spawn"]["x"] == [-1.6, -0.6]


@pytest.mark.parametrize("overrides, said", [
    ("[]", "overrides: lists no cells: give at least one mapping (or {} for the scenario as it is)"),
    ("[{}, {}]", "overrides[1]: repeats overrides[0]: the two cells would be the same"),
    ("[{robots.count: 4}, 3]", "overrides[1]: must be a mapping of scenario key -> value, one cell (got 3)"),
    ("[{seed: 3}]", "overrides[0].seed: cannot be overridden (the study sets names and seeds)"),
    ("[{object: {shape: circle, radius: 0.2}, object.mass: 2}]", "overrides[0].object.mass: lies inside "
     "overrides[0].object, which replaces all of object: one of them would be lost; put mass into "
     "overrides[0].object instead"),
    ("[{}, {time_limit_s: 9}]", "overrides[1].time_limit_s: the study's time_limit_s replaces it in every run"),
    ("[{robots.count: 0}]", "overrides (lab-6@robots.count=0): robots.count: must be >= 1 (got 0)"),
    ("3", "overrides: must be a mapping of scenario key -> list of values (a grid), or a list of mappings"),
])
def test_a_bad_list_of_override_cells_names_the_cell(tmp_path, capsys, overrides, said):
    study = write(tmp_path / "s.yaml", TINY_STUDY + f"overrides: {overrides}\n")
    assert main(["study", str(study), "--dry-run"]) == 2
    assert f"khepri: error: {study}: {said}" in capsys.readouterr().err


def test_a_whole_mapping_override_names_its_cell_with_its_keys():
    """An override of a whole mapping (an object shape) used to name its folder after the dict's repr:
    lab-6@object=__shape___box____size___0.3__0.4___mass___2.0_."""
    box = {"shape": "box", "size": [0.3, 0.4], "mass": 2.0, "position": [0.0, 0.0]}
    spec = parse_study({"name": "objects", "scenarios": ["lab-6"], "reps": 1, "overrides": {"object": [box]}})
    run = expand(spec)[0]
    assert run.cell == "lab-6@object=shape=box,size=0.3,0.4,mass=2,position=0,0"
    assert run.scenario_data["object"]["mass"] == 2.0


def test_a_cell_name_too_long_for_a_folder_is_shortened_with_a_fingerprint(tmp_path):
    """A whole polygon of 24 vertices named a folder of over 255 bytes: every run of the cell was "not run: its
    folder cannot be written (File name too long)", which no fixing of folders could cure."""
    ring = [[round(0.2 * np.cos(k * np.pi / 12), 4), round(0.2 * np.sin(k * np.pi / 12), 4)] for k in range(24)]
    shapes = [{"shape": "polygon", "vertices": ring, "mass": mass} for mass in (0.3, 0.4)]
    text = TINY_STUDY.replace("seeds: 1..2", "seeds: [1]").replace("time_limit_s: 4", "time_limit_s: 1")
    study = write(tmp_path / "s.yaml", text + f"overrides: {{object: {json.dumps(shapes)}}}\n")
    cells = sorted({run.cell for run in expand(load_study_file(study))})
    assert len(cells) == 2 and all(len(cell) <= 255 for cell in cells)
    assert cells[0].startswith("lab-6@object=shape=polygon,vertices=0.2,0,") and "~" in cells[0]
    assert main(["study", str(study), "--out", str(tmp_path / "out"), "--workers", "1", "--no-figures"]) == 0
    assert sorted(results_in(tmp_path / "out")) == [f"{cell}/seed-1" for cell in cells]


def test_the_summarys_overrides_column_writes_lists_and_mappings_as_json_without_spaces():
    """A whole-mapping override used to appear as a dict's repr, whose spaces broke the column's
    space-separated key=value pairs."""
    from sim_backend.study.aggregate import overrides_text

    text = overrides_text({"object": {"shape": "circle", "size": 0.2}, "robots.spawn.x": [-1, 0], "comm.drop": 0.1})
    pairs = dict(pair.split("=", 1) for pair in text.split(" "))
    assert pairs == {"object": '{"shape":"circle","size":0.2}', "robots.spawn.x": "[-1,0]", "comm.drop": "0.1"}
    assert json.loads(pairs["object"]) == {"shape": "circle", "size": 0.2}


@pytest.mark.parametrize("text, message", [
    ("scenarios: lab-6\nreps: 2", "scenarios: must be a non-empty list"),
    ("scenarios: [no-such-scenario]\nreps: 2", "scenarios[0]: scenario: unknown scenario 'no-such-scenario'"),
    ("scenarios: [lab-6]\nreps: 0", "reps: must be an integer >= 1 (got 0)"),
    ("scenarios: [lab-6]", "seeds: missing: give seeds (a list, or 'first..last') or reps"),
    ("scenarios: [lab-6]\nseeds: [1]\nreps: 2", "seeds: give either seeds (a list, or 'first..last') or reps (seeds "
     "1..reps), not both"),
    ("scenarios: [lab-6]\nseeds: 5..2", "seeds: a range must read 'first..last'"),
    ("scenarios: [lab-6]\nseeds: [1, -3]", "seeds[1]: must be an integer >= 0"),
    # A bare number is ambiguous (seed 3, or three seeds): both spellings are offered.
    ("scenarios: [lab-6]\nseeds: 3", "seeds: must be a non-empty list of integers or 'first..last' (got 3): [3] for "
     "seed 3 alone, or reps: 3 for seeds 1..3"),
    ("scenarios: [lab-6]\nreps: 1\noverrides: {params.no_such_param: [1]}", "params.no_such_param: unknown key"),
    ("scenarios: [lab-6]\nreps: 1\noverrides: {robots.count: [0]}", "robots.count: must be >= 1"),
    # An override of one field that leaves a sibling unfit says how to change both together.
    ("scenarios: [lab-6]\nreps: 1\noverrides: {object.shape: [circle]}",
     "object.size is the scenario's own, kept beside the override of object.shape: to change them together, "
     "override object as a whole, e.g. object: [{shape: ..., size: ...}]"),
    ("scenarios: [lab-6]\nreps: 1\noverrides: {object.shape: [circle], object.size: [[0.3, 0.3]]}",
     "object.size is overridden too, and every value of one is paired with every value of the other"),
    ("scenarios: [lab-6]\nreps: 1\ntime_limit_s: -5", "time_limit_s: must be a number of seconds > 0"),
    ("scenarios: [lab-6]\nreps: 1\ntime_limit_s: .inf", "time_limit_s: must be a number of seconds > 0"),
    ("scenarios: [lab-6]\nseeds: 1..100000000000", "seeds: a range may hold at most 100000 seeds"),
    # Counted before the grid is expanded: eight keys of ten values filled the memory (itertools.product). The
    # first cell here is refused too, so that a grid built before it is counted fails fast, with another error.
    ("scenarios: [lab-6]\nreps: 1\noverrides: {robots.count: [0, 6], comm.drop: [" + HUNDRED_DROPS + "], "
     "comm.range_m: [" + ", ".join(str(i + 1) for i in range(100)) + "]}",
     "overrides: makes 20000 cells (1 scenario x 2 x 100 x 100 values), more than a study may hold (10000"),
    ("scenarios: [lab-6]\nreps: 60000\noverrides: {robots.count: [0, 6]}",
     "bad.yaml: reps: 2 cells x 60000 seeds make 120000 runs, more than a study may run (100000)"),
    ("scenarios: [lab-6]\nreps: 1\noverrides: {comm.drop: [0.1, 0.2, 0.1]}",
     "overrides.comm.drop: lists the value 0.1 twice"),
    ("scenarios: [lab-6]\nreps: 1\nreps: 2", "bad.yaml:3: not valid YAML (the key 'reps' is given twice"),
    ("scenarios: [lab-6]\nreps: 1\nrepeats: 3", "repeats: unknown key"),
    ("scenarios: [lab-6\nreps: 1", "bad.yaml:2: not valid YAML"),
    ("# nothing but a comment\n", "bad.yaml: the file is empty (a study needs at least its scenarios)"),
    ("scenarios: [lab-6]\nseeds: [true]", "seeds[0]: must be an integer >= 0 (got true)"),     # not Python's True
    (f"scenarios: [lab-6]\nseeds: [{2 ** 63}]", "seeds[0]: must be <= 9223372036854775807 (got 9223372036854775808)"),
    ("scenarios: [lab-6]\nseeds: 1..1" + "0" * 30, "seeds: a range's seeds must be at most 9223372036854775807"),
    # A list-valued key lists its values: [-1, 0] is two cells, x = -1 and x = 0; say how to give one list.
    ("scenarios: [lab-6]\nreps: 1\noverrides: {robots.spawn.x: [-1, 0]}",
     "robots.spawn.x: must be a list (got -1); each value listed under overrides.robots.spawn.x is one whole "
     "robots.spawn.x (a cell each), which is a list: to give it [-1, 0] as one value, write robots.spawn.x: [[-1, 0]]"),
    ("scenarios: [lab-6]\nreps: 1\noverrides: {path: [[1, 0, 0]]}",
     "path[0]: must be a list (got 1); each value listed under overrides.path is one whole path (a cell each), which "
     "is a list: to give it [[1, 0, 0]] as one value, write path: [[[1, 0, 0]]]"),
])
def test_a_bad_study_file_is_refused_with_the_field_named(tmp_path, capsys, text, message):
    study = write(tmp_path / "bad.yaml", text)
    assert main(["study", str(study), "--out", str(tmp_path / "out")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_an_empty_file_is_named_by_its_path_once(tmp_path, capsys):
    """`empty.yaml: empty.yaml: the file is empty`, its folder dropped; every other error names the path."""
    (tmp_path / "bad").mkdir()
    write(tmp_path / "bad" / "empty.yaml", "")
    study = write(tmp_path / "bad" / "se.yaml", "scenarios: [empty.yaml]\nseeds: [1]\n")
    assert main(["study", str(study), "--dry-run"]) == 2
    said = capsys.readouterr().err.strip()
    assert said == f"khepri: error: {study}: scenarios[0]: {tmp_path / 'bad' / 'empty.yaml'}: the file is empty (a " \
                   "scenario is a mapping of keys such as behaviour: and robots:; {} takes every default)", said


def test_too_many_runs_names_reps_when_the_option_gave_them(tmp_path, capsys):
    study = write(tmp_path / "two.yaml", "scenarios: [lab-6]\nreps: 1\noverrides: {robots.count: [0, 6]}\n")
    assert main(["study", str(study), "--reps", "60000", "--dry-run"]) == 2
    assert capsys.readouterr().err == ("khepri: error: --reps: 2 cells x 60000 seeds make 120000 runs, more than a "
                                       "study may run (100000): give fewer seeds or fewer cells\n")


@pytest.mark.parametrize("options, message", [
    (["--executor", "spark"], "--executor: must be local, dask or dask:ADDRESS"),
    (["--scenarios", "paper-25-straight"], "--scenarios: not in the study: paper-25-straight"),
    (["--time-limit", "0"], "--time-limit: must be a finite number of seconds > 0 (got 0)"),
    (["--time-limit", "inf"], "--time-limit: must be a finite number of seconds > 0 (got inf)"),
    (["--time-limit", "nan", "--dry-run"], "--time-limit: must be a finite number of seconds > 0 (got nan)"),
    (["--reps", "1000000000", "--dry-run"], "--reps: must be at most 100000 (got 1000000000)"),
    (["--executor", "dask:notaurl"], "--executor: not a Dask scheduler address: 'notaurl' (missing port number"),
    (["--executor", "dask:http://localhost:80"], "--executor: not a Dask scheduler address: 'http://localhost:80'"),
    (["--executor", "dask:tcp://127.0.0.1:99999", "--dry-run"],
     "--executor: the scheduler's port must be 1..65535 (got 99999 in 'tcp://127.0.0.1:99999')"),
    (["--executor", "dask:tcp://127.0.0.1:0"], "--executor: the scheduler's port must be 1..65535 (got 0 in"),
    (["--reps", "0"], "--reps: must be an integer >= 1"),
    (["--workers", "0"], "--workers: must be >= 1 (got 0)"),
    (["--workers", "-2", "--dry-run"], "--workers: must be >= 1 (got -2)"),
    (["--executor", "spark", "--dry-run"], "--executor: must be local, dask or dask:ADDRESS"),
])
def test_bad_options_are_refused(tmp_path, capsys, options, message):
    study = write(tmp_path / "tiny.yaml", TINY_STUDY)
    assert main(["study", str(study), "--out", str(tmp_path / "out"), *options]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_dry_run_prints_the_grid_and_runs_nothing(tmp_path, capsys):
    assert main(["study", "paper", "--reps", "3", "--scenarios", "paper-25-straight,irregular-clover",
                 "--dry-run", "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert out.startswith("6 runs, 6 to run, 0 finished")
    assert "paper-25-straight" in out and "irregular-clover" in out and "paper-50-straight" not in out
    assert not (tmp_path / "out").exists()


# --- real runs -----------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def local_study(tmp_path_factory):
    """The tiny study plus a cell whose behaviour crashes, run for real on a 2-process pool (the workers
    import the behaviour's module, as `khepri --import` asks)."""
    from onboard import behaviour

    folder = tmp_path_factory.mktemp("local")
    module = write(folder / "crashing.py", CRASHING_MODULE)
    study = write(folder / "tiny.yaml", TINY_STUDY + "overrides: {behaviour: [transport, crashing]}\n")
    out = folder / "out"
    code = main(["--import", str(module), "study", str(study), "--out", str(out), "--workers", "2"])
    yield study, out, code, module
    behaviour._REGISTRY.pop("crashing", None)     # other test modules list the known behaviours


def test_the_local_pool_runs_every_run_and_writes_its_files(local_study):
    _, out, code, _ = local_study
    results = results_in(out)
    assert sorted(results) == [f"{CRASHING}/seed-1", f"{CRASHING}/seed-2", f"{GOOD}/seed-1", f"{GOOD}/seed-2"]
    for seed in (1, 2):
        result = results[f"{GOOD}/seed-{seed}"]
        assert result["seed"] == seed and result["failed"] is False and result["sim_time_s"] == 4.0
        fingerprint = result["study"].pop("scenario_sha1")
        assert len(result["study"].pop("scenario_sha1_full")) == 16
        code_fingerprint = result["study"].pop("behaviour_sha1")
        assert result["study"] == {"cell": GOOD, "scenario": "lab-6", "overrides": {"behaviour": "transport"},
                                   "time_limit_s": 4.0}
        assert len(fingerprint) == 16 and int(fingerprint, 16) >= 0
        assert code_fingerprint == behaviour_code_sha1("transport") and len(code_fingerprint) == 16
        assert (out / GOOD / f"seed-{seed}" / "trajectory.npz").stat().st_size > 0
    assert code == 1   # some runs failed: the command says so
    assert (out / "summary.csv").is_file() and (out / "report.md").is_file()


def test_a_run_whose_behaviour_crashes_is_recorded_with_its_reason(local_study):
    _, out, _, _ = local_study
    result = json.loads((out / CRASHING / "seed-1" / "result.json").read_text())
    assert result["failed"] is True and result["stop_reason"] == "crashed"
    assert result["error"].startswith("robot 0, step(): RuntimeError: a deliberate bug, 1 s in")
    assert result["study"]["overrides"] == {"behaviour": "crashing"}
    report = (out / "report.md").read_text()
    assert f"- `{CRASHING}` seed 1: robot 0, step(): RuntimeError: a deliberate bug, 1 s in" in report


def test_a_cell_whose_robots_cannot_be_placed_is_refused_before_anything_runs(tmp_path, capsys):
    """Only the world finds it (the scenario itself is valid): the study builds each cell's world first."""
    study = write(tmp_path / "tiny.yaml", TINY_STUDY + "overrides: {robots.spawn.x: [[-1.2, -0.6], [0.0, 0.0]]}\n")
    assert main(["study", str(study), "--out", str(tmp_path / "out")]) == 2
    assert f"khepri: error: {study}: overrides (lab-6@robots.spawn.x=0,0): robots.spawn: 6 robots need about" in \
        capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_resume_skips_finished_runs_and_retries_failed_ones_only_when_asked(local_study, capsys):
    study, out, _, module = local_study
    finished = out / GOOD / "seed-1" / "result.json"
    failed = out / CRASHING / "seed-1" / "result.json"
    marks = {path: path.read_text() + " " for path in (finished, failed)}
    for path, text in marks.items():   # a trailing space marks the files: a re-run would rewrite them
        path.write_text(text)
    capsys.readouterr()
    main(["--import", str(module), "study", str(study), "--out", str(out), "--workers", "2"])
    assert "ran 0 runs (0 failed), skipped 2 finished and 2 failed" in capsys.readouterr().out
    assert all(path.read_text() == text for path, text in marks.items())
    main(["--import", str(module), "study", str(study), "--out", str(out), "--workers", "2", "--retry-failed"])
    assert "ran 2 runs (2 failed), skipped 2 finished" in capsys.readouterr().out
    assert finished.read_text() == marks[finished] and failed.read_text() != marks[failed]
    main(["--import", str(module), "study", str(study), "--out", str(out), "--time-limit", "3", "--no-figures"])
    assert "warning: 4 runs already in" in capsys.readouterr().err   # kept, though their time limit differs


def die_on_seed_2(spec, out_root):
    """A run function whose worker process dies (no exception, no result) on seed 2."""
    if spec.seed == 2:
        os._exit(3)
    return execute_run(spec, out_root)


def run_elsewhere(spec, out_root):
    """A worker that cannot see the driver's folder (as on another machine without a shared disk)."""
    return execute_run(spec, out_root + "-elsewhere")


def test_a_worker_process_that_dies_is_recorded_and_the_other_runs_complete(tmp_path):
    spec = parse_study({"name": "deaths", "scenarios": ["lab-6"], "seeds": [1, 2, 3], "time_limit_s": 1})
    outcome = run_study(spec, expand(spec), tmp_path, LocalExecutor(2, die_on_seed_2))
    results = results_in(tmp_path)
    assert outcome.ran == 3 and outcome.failed == 1
    assert results["lab-6/seed-2"]["failed"] is True and results["lab-6/seed-2"]["error"] == WORKER_DIED
    assert results["lab-6/seed-1"]["failed"] is False and results["lab-6/seed-3"]["failed"] is False


def quick_or_dying_later(spec, out_root):
    """Seed 2's worker dies a moment after the others returned (no simulation: only the pool matters)."""
    if spec.seed == 2:
        time.sleep(0.3)
        os._exit(3)
    return {"seed": spec.seed, "failed": False}


def test_a_worker_dying_while_the_driver_is_busy_does_not_break_the_study(tmp_path):
    """The pool can break between two completions; the next submit must not raise BrokenProcessPool."""
    spec = parse_study({"name": "late", "scenarios": ["lab-6"], "seeds": [1, 2, 3, 4], "time_limit_s": 1})
    seen = {}
    for result in LocalExecutor(2, quick_or_dying_later).results(expand(spec), str(tmp_path)):
        seen[result["seed"]] = result
        time.sleep(1.0)   # the driver writing files and printing, while seed 2's worker dies
    assert sorted(seen) == [1, 2, 3, 4]
    assert seen[2]["failed"] is True and seen[2]["error"] == WORKER_DIED
    assert not any(seen[seed]["failed"] for seed in (1, 3, 4))


def test_the_driver_writes_the_result_a_remote_worker_could_not(tmp_path):
    spec = parse_study({"name": "remote", "scenarios": ["lab-6"], "seeds": [1], "time_limit_s": 1})
    run_study(spec, expand(spec), tmp_path / "out", LocalExecutor(1, run_elsewhere))
    here = json.loads((tmp_path / "out" / "lab-6" / "seed-1" / "result.json").read_text())
    there = json.loads((tmp_path / "out-elsewhere" / "lab-6" / "seed-1" / "result.json").read_text())
    assert here == there and here["failed"] is False


def test_a_cell_folder_that_cannot_be_written_fails_its_runs_not_the_study(tmp_path, capsys):
    """A file where a cell's folder goes (as root, the way to make a folder unwritable): the whole study stopped
    with exit 2 ("Not a directory") after running every run."""
    study = write(tmp_path / "tiny.yaml", TINY_STUDY + "overrides: {comm.drop: [0.0, 0.1]}\n")
    out = tmp_path / "out"
    out.mkdir()
    write(out / "study.json", '{"name": "tiny"}')       # a study's folder: one of other files is refused
    blocker = write(out / "lab-6@comm.drop=0.1", "not a folder")
    assert main(["study", str(study), "--out", str(out), "--workers", "1", "--no-figures"]) == 1
    said = capsys.readouterr()
    assert "ran 2 runs (0 failed), skipped 0 finished; 2 could not write their result" in said.out
    assert f"FAILED: not run: its folder cannot be written (Not a directory: {out}/lab-6@comm.drop=0.1/seed-1)" \
        in said.err
    assert sorted(results_in(out)) == ["lab-6@comm.drop=0/seed-1", "lab-6@comm.drop=0/seed-2"]
    report = (out / "report.md").read_text()
    assert f"- `lab-6@comm.drop=0.1/seed-2`: not run: its folder cannot be written (Not a directory: {out}/" in report
    blocker.unlink()                       # fixed: the same command runs them, and they are failures no more
    assert main(["study", str(study), "--out", str(out), "--workers", "1", "--no-figures"]) == 0
    assert "ran 2 runs (0 failed), skipped 2 finished\n" in capsys.readouterr().out
    assert "cannot be written" not in (out / "report.md").read_text()


def block_own_folder(spec, out_root):
    """A run whose folder turns into a file while it runs (a full disk, a folder made read-only meanwhile):
    neither the worker nor the driver can write its result."""
    result = execute_run(spec, out_root + "-elsewhere")
    run_dir = Path(out_root) / spec.run_dir
    run_dir.rmdir()
    run_dir.write_text("in the way")
    return result


def test_a_result_that_cannot_be_written_after_its_run_is_recorded_as_lost(tmp_path):
    spec = parse_study({"name": "lost", "scenarios": ["lab-6"], "seeds": [1], "time_limit_s": 1})
    outcome = run_study(spec, expand(spec), tmp_path, LocalExecutor(1, block_own_folder), stream=io.StringIO())
    assert outcome.ran == 1 and list(outcome.unwritable) == ["lab-6/seed-1"]
    assert outcome.unwritable["lab-6/seed-1"].startswith("ran, but its result could not be written and is lost (")
    assert json.loads((tmp_path / "study.json").read_text())["unwritable"] == outcome.unwritable


def run_other_code(spec, out_root):
    """A worker whose checkout holds another version of the behaviour (a Dask worker on another machine)."""
    result = execute_run(spec, out_root)
    result["study"]["behaviour_sha1"] = "0123456789abcdef"
    return result


def test_a_worker_that_ran_another_version_of_the_code_is_said_during_the_run(tmp_path):
    spec = parse_study({"name": "versions", "scenarios": ["lab-6"], "seeds": [1, 2], "time_limit_s": 1})
    said = io.StringIO()
    run_study(spec, expand(spec), tmp_path, LocalExecutor(1, run_other_code), stream=said)
    warnings = [line for line in said.getvalue().splitlines() if line.startswith("warning:")]
    assert warnings == ["warning: lab-6/seed-1 ran another version of the code of behaviour 'transport' "
                        f"(behaviour_sha1 0123456789abcdef) than this machine has ({behaviour_code_sha1('transport')}"
                        "): the study mixes code versions; give every worker the same commit, and restart "
                        "long-lived dask workers after changing the code (they keep what they imported)"]  # once


# What a running study does to its folder, written out (not through khepri's code, which this test checks).
HOLD_THE_LOCK = """
import fcntl, os, sys, time
with open(os.path.join(sys.argv[1], "study.lock"), "w") as lock:
    fcntl.flock(lock, fcntl.LOCK_EX)
    lock.write(f"{os.getpid()}\\n")
    lock.flush()
    print("locked", flush=True)
    time.sleep(60)
"""


def test_a_second_study_into_the_same_folder_is_refused_while_the_first_runs(tmp_path, capsys):
    """Both ran every unfinished run. The lock is the kernel's (flock): one killed outright leaves none behind."""
    import subprocess
    import sys

    study = write(tmp_path / "tiny.yaml", "name: tiny\nscenarios: [lab-6]\nseeds: [1]\ntime_limit_s: 1\n")
    out = tmp_path / "out"
    out.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", HOLD_THE_LOCK, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline() == "locked\n"
        assert main(["study", str(study), "--out", str(out), "--workers", "1", "--no-figures"]) == 2
        assert capsys.readouterr().err == (
            f"khepri: error: --out: {out} is in use by another study (pid {holder.pid}, holding {out / 'study.lock'}): "
            f"wait for it to end, or give another --out\n")
        assert not (out / "lab-6").exists() and not (out / "study.json").exists()
    finally:
        holder.kill()        # as a crash would: no chance to clean anything up
        holder.wait()
        holder.stdout.close()
    assert main(["study", str(study), "--out", str(out), "--workers", "1", "--no-figures"]) == 0
    assert "ran 1 run (0 failed)" in capsys.readouterr().out
    assert (out / "study.lock").read_text() == f"{os.getpid()}\n"     # the pid a second study would name
    assert main(["study", str(study), "--out", str(out), "--workers", "1", "--no-figures"]) == 0   # resumes
    assert "ran 0 runs (0 failed), skipped 1 finished" in capsys.readouterr().out


def test_a_folder_whose_file_system_has_no_locks_runs_its_study_unlocked_and_says_so(tmp_path, monkeypatch, capsys):
    """flock's ENOLCK (NFS without its lock service) had no file name: the command ended in a traceback."""
    import errno
    import fcntl

    from sim_backend.study.driver import study_lock

    def no_locks(*args):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", no_locks)
    with study_lock(tmp_path):
        pass
    assert capsys.readouterr().err == (f"khepri: warning: --out: cannot lock {tmp_path / 'study.lock'} (No locks "
                                       f"available): a second study started into {tmp_path} meanwhile would not be "
                                       "refused\n")


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o027, 0o640)])
def test_a_result_the_driver_writes_has_the_umasks_permissions(tmp_path, umask, mode):
    """write_result's temporary file came from mkstemp, so its result.json was 0600: the rest of the lab could
    not read the runs of a remote worker, nor those that could not start."""
    spec = parse_study({"name": "remote", "scenarios": ["lab-6"], "seeds": [1], "time_limit_s": 1})
    before = os.umask(umask)
    try:
        run_study(spec, expand(spec), tmp_path / "out", LocalExecutor(1, run_elsewhere), stream=io.StringIO())
    finally:
        os.umask(before)
    run_dir = tmp_path / "out" / "lab-6" / "seed-1"
    assert (run_dir / "result.json").stat().st_mode & 0o777 == mode
    assert [p.name for p in run_dir.iterdir()] == ["result.json"]      # no temporary file left behind


def test_a_dask_local_cluster_gives_the_same_results_as_the_local_pool(local_study, tmp_path, capsys):
    study, local_out, _, module = local_study
    code = main(["--import", str(module), "study", str(study), "--executor", "dask", "--workers", "1",
                 "--out", str(tmp_path)])
    assert code == 1   # the failing cell fails on Dask too
    assert "on Dask LocalCluster, 1 worker," in capsys.readouterr().out
    dask_results, local_results = results_in(tmp_path), results_in(local_out)
    assert sorted(dask_results) == sorted(local_results)
    for key, result in dask_results.items():
        if result["failed"]:
            assert result["error"] == local_results[key]["error"]
        else:
            assert comparable(result) == comparable(local_results[key])
    assert "--executor dask" in json.loads((tmp_path / "study.json").read_text())["commands"][0]


def test_a_dask_local_cluster_beside_another_on_port_8787_says_nothing_of_it(tmp_path, recwarn):
    """Without a dashboard the LocalCluster's scheduler still served HTTP on port 8787; beside a Dask scheduler (or
    another study) Dask warned "Port 8787 is already in use. Perhaps you already have a cluster running?"."""
    import socket

    study = write(tmp_path / "tiny.yaml", TINY_STUDY.replace("seeds: 1..2", "seeds: [1]"))
    with socket.socket() as taken:
        try:
            taken.bind(("", 8787))
            taken.listen()
        except OSError:
            pass                             # something else holds it already: as good
        assert main(["study", str(study), "--executor", "dask", "--workers", "1", "--out", str(tmp_path / "o"),
                     "--no-figures"]) == 0
    assert not [w for w in recwarn if "8787" in str(w.message)]


def die_on_seed_1(spec, out_root):
    """The first run's worker process dies (no exception, no result); the others are ordinary runs."""
    if spec.seed == 1:
        os._exit(3)
    return execute_run(spec, out_root)


def test_runs_that_shared_a_dying_dask_worker_are_run_again_alone(tmp_path):
    """Dask counts every task a dying worker held as suspect, and loses the results it held: the runs queued
    behind a run that kills its worker were recorded as failed ("KilledWorker", "ended as 'lost'") with it.
    Dask here gives up on a task at once, and sends every run to the one worker, so they all share its death."""
    import dask

    from sim_backend.study.executors import DaskExecutor

    spec = parse_study({"name": "deaths", "scenarios": ["lab-6"], "seeds": [1, 2, 3], "time_limit_s": 1})
    with dask.config.set({"distributed.scheduler.allowed-failures": 0,
                          "distributed.scheduler.worker-saturation": float("inf")}):
        outcome = run_study(spec, expand(spec), tmp_path, DaskExecutor(None, 1, die_on_seed_1), stream=io.StringIO())
    results = results_in(tmp_path)
    assert outcome.ran == 3 and outcome.failed == 1
    assert results["lab-6/seed-1"]["failed"] is True and results["lab-6/seed-1"]["error"].startswith(WORKER_DIED)
    assert results["lab-6/seed-2"]["failed"] is False and results["lab-6/seed-3"]["failed"] is False


def free_port() -> int:
    import socket

    with socket.socket() as probe:       # a free port, closed again
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class RecordingHandler(logging.Handler):
    def __init__(self):
        super().__init__(logging.DEBUG)
        self.records: list = []

    def emit(self, record):
        self.records.append(record)


class SchedulerDiesAfterTheFirstResult:
    """An executor that passes the results on, and ends the Dask scheduler once the first one is in."""

    def __init__(self, executor, stop_scheduler):
        self.executor, self.stop_scheduler = executor, stop_scheduler

    def results(self, runs, out_root):
        for count, result in enumerate(self.executor.results(runs, out_root)):
            yield result
            if count == 0:
                self.stop_scheduler()


def test_a_lost_dask_scheduler_leaves_the_unfinished_runs_to_the_resume(tmp_path):
    """Every unfinished run was recorded as failed ("the Dask task ended as 'cancelled'"), so a resume skipped
    them for good, and a worker still running one could overwrite that record with its result afterwards."""
    import subprocess
    import sys

    from sim_backend.study.executors import DaskExecutor

    address = f"tcp://127.0.0.1:{free_port()}"
    client_log, client_records = logging.getLogger("distributed.client"), RecordingHandler()
    client_log.addHandler(client_records)
    scheduler = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                                  "--port", address.rsplit(":", 1)[1], "--no-dashboard"], stderr=subprocess.DEVNULL)
    worker = None
    try:
        executor = DaskExecutor(address, 1)
        executor.prepare()         # waits (up to 30 s) for the scheduler to start
        worker = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1",
                                   "--no-dashboard"], stderr=subprocess.DEVNULL)
        spec = parse_study({"name": "lost", "scenarios": ["lab-6"], "seeds": [1, 2, 3, 4, 5, 6], "time_limit_s": 30})
        with pytest.raises(ConfigError, match=f"--executor: lost the connection to the Dask scheduler at {address}: "
                                              "the runs not finished have no result; run the same command again"):
            run_study(spec, expand(spec), tmp_path, SchedulerDiesAfterTheFirstResult(executor, scheduler.kill),
                      stream=io.StringIO())
        # The client's own lines ("Failed to reconnect to scheduler", two CancelledError tracebacks) were printed
        # above that one line; the records that pass the executor's filter reach this handler.
        assert not [r for r in client_records.records if "reconnect" in r.getMessage() or r.exc_info], \
            [r.getMessage() for r in client_records.records]
    finally:
        client_log.removeHandler(client_records)
        for process in (scheduler, worker):
            if process is not None:
                process.kill()
                process.wait()
    results = results_in(tmp_path)
    assert results and not any(result["failed"] for result in results.values())
    assert len(results) < 6          # the others are left to the resume


# --- aggregation of known results ----------------------------------------------------------------------

def waypoint(index, position, centroid, orientation, pushers, rotators=0.0):
    return {"index": index, "reached_s": 100.0 + index, "position_error_m": position,
            "orientation_error_rad": orientation, "centroid_estimation_error_m": centroid,
            "effective_pushers": pushers, "effective_rotators": rotators}


def transport_result(seed, cage, complete, waypoints, completed=True):
    return {"scenario": "paper-25-straight", "seed": seed, "robots": 25, "behaviour": "transport",
            "sim_time_s": 500.0, "wall_time_s": 10.0 * seed, "stop_reason": "behaviour finished", "failed": False,
            "caged": True,
            "time_to_cage_s": cage, "cage_size": 18 + seed, "completed": completed, "time_to_complete_s": complete,
            "waypoints": waypoints, "final_position_error_m": 0.05, "final_orientation_error_rad": 0.01,
            "cage_spacing_m": {"mean": 0.42 + 0.02 * seed, "std": 0.01 * seed ** 2},
            "study": {"cell": "paper-25-straight", "overrides": {}}}


@pytest.fixture
def known_study(tmp_path):
    """Four paper-25-straight runs (one crashed) and two irregular-clover runs, written by hand."""
    runs = {
        "paper-25-straight/seed-1": transport_result(1, 100.0, 90.0, [waypoint(0, 0.1, 0.2, 0.01, 10),
                                                                      waypoint(1, 0.2, 0.3, 0.02, 12)]),
        "paper-25-straight/seed-2": transport_result(2, 200.0, 110.0, [waypoint(0, 0.2, 0.4, 0.03, 11),
                                                                       waypoint(1, 0.4, 0.5, 0.04, 13)]),
        "paper-25-straight/seed-3": transport_result(3, 400.0, None, [waypoint(0, 0.3, 0.6, 0.05, 12)],
                                                     completed=False),
        "paper-25-straight/seed-4": {"scenario": "paper-25-straight", "seed": 4, "robots": 25, "failed": True,
                                     "error": "RuntimeError: boom", "study": {"cell": "paper-25-straight"}},
        "irregular-clover/seed-1": {"scenario": "irregular-clover", "seed": 1, "robots": 30, "failed": False,
                                    "stop_reason": "behaviour finished",
                                    "caged": True, "time_to_cage_s": 280.0, "cage_size": 22},
        "irregular-clover/seed-2": {"scenario": "irregular-clover", "seed": 2, "robots": 30, "failed": False,
                                    "stop_reason": "time limit",
                                    "caged": False, "time_to_cage_s": None, "cage_size": 0},
    }
    for run_dir, result in runs.items():
        (tmp_path / run_dir).mkdir(parents=True)
        write(tmp_path / run_dir / "result.json", json.dumps(result))
    track = np.column_stack([np.linspace(0, -2, 50), np.zeros(50), np.zeros(50)])
    np.savez_compressed(tmp_path / "paper-25-straight/seed-1/trajectory.npz", object_pose=track,
                        path=np.array([[-1.0, 0.0, 0.0], [-2.0, 0.0, 0.0]]))
    return tmp_path


def summary_rows(folder):
    with (folder / "summary.csv").open() as handle:
        return {(r["cell"], r["metric"], r["waypoint"]): r for r in csv.DictReader(handle)}


def test_summary_csv_has_the_medians_spreads_rates_and_paper_values(known_study):
    write_study_outputs(known_study, figures=False)
    rows = summary_rows(known_study)
    cage = rows[("paper-25-straight", "time_to_cage_s", "")]
    assert (cage["n"], cage["value"], cage["q1"], cage["q3"], cage["min"], cage["max"], cage["paper_value"]) == (
        "3", "200", "150", "300", "100", "400", "247")
    complete = rows[("paper-25-straight", "time_to_complete_s", "")]
    assert (complete["n"], complete["value"], complete["paper_value"]) == ("2", "100", "100")
    assert rows[("paper-25-straight", "runs", "")]["value"] == "4"
    assert rows[("paper-25-straight", "failed_runs", "")]["value"] == "1"
    assert rows[("paper-25-straight", "success_rate", "")]["value"] == "0.666667"
    assert rows[("paper-25-straight", "all_waypoints_rate", "")]["value"] == "0.666667"
    position = rows[("paper-25-straight", "position_error_m", "0")]
    assert (position["n"], position["value"], position["q1"], position["q3"]) == ("3", "0.2", "0.15", "0.25")
    reference = paper.error_values(paper.paper_case("paper-25-straight"), 0, "position_error_m")
    assert position["paper_value"] == f"{np.median(reference):.6g}" and position["paper_n"] == "30"
    assert rows[("paper-25-straight", "effective_pushers", "1")]["value"] == "12.5"
    spacing = rows[("paper-25-straight", "cage_spacing_mean_m", "")]
    assert (spacing["n"], spacing["value"], spacing["min"], spacing["max"]) == ("3", "0.46", "0.44", "0.48")
    assert rows[("paper-25-straight", "cage_spacing_std_m", "")]["value"] == "0.04"
    assert ("irregular-clover", "cage_spacing_mean_m", "") not in rows     # no spacing recorded: no row
    clover = rows[("irregular-clover", "success_rate", "")]
    assert (clover["n"], clover["value"]) == ("2", "0.5")
    assert rows[("irregular-clover", "time_to_cage_s", "")]["paper_value"] == "300"
    assert ("irregular-clover", "completed_rate", "") not in rows


def test_a_cell_without_times_still_has_its_time_rows_with_empty_values(known_study):
    """A cell whose runs all failed, or none of which caged, had no time rows at all in summary.csv."""
    dead = {"scenario": "paper-25-zigzag", "seed": 1, "robots": 25, "behaviour": "transport", "failed": True,
            "error": WORKER_DIED, "study": {"cell": "paper-25-zigzag", "scenario": "paper-25-zigzag", "overrides": {}}}
    uncaged = {"scenario": "irregular-cloud", "seed": 1, "robots": 30, "behaviour": "transport", "failed": False,
               "stop_reason": "time limit", "caged": False, "time_to_cage_s": None, "cage_size": 0,
               "study": {"cell": "irregular-cloud", "scenario": "irregular-cloud", "overrides": {}}}
    for result in (dead, uncaged):
        (known_study / result["scenario"] / "seed-1").mkdir(parents=True)
        write(known_study / result["scenario"] / "seed-1" / "result.json", json.dumps(result))
    write_study_outputs(known_study, figures=False)
    rows = summary_rows(known_study)
    push = f"{paper.time_to_push_s(paper.paper_case('paper-25-zigzag')):.6g}"
    for cell, metric, paper_value in (("paper-25-zigzag", "time_to_cage_s", "247"),
                                      ("paper-25-zigzag", "time_to_complete_s", push),
                                      ("paper-25-zigzag", "wall_time_s", ""),
                                      ("irregular-cloud", "time_to_cage_s", "300")):
        row = rows[(cell, metric, "")]
        assert (row["n"], row["value"], row["q1"], row["max"], row["paper_value"]) == ("0", "", "", "", paper_value)
    assert ("irregular-cloud", "time_to_complete_s", "") not in rows       # caging only: no path, no such time
    assert ("paper-25-zigzag", "position_error_m", "0") not in rows        # per waypoint: only where reached


def test_a_cell_with_another_robot_count_or_path_gets_no_paper_numbers(tmp_path):
    """paper-25-straight@robots.count=12 showed the paper's 25-robot times and errors as if they were its own."""
    cells = {"paper-25-straight@robots.count=12": ({"robots.count": 12}, 12),
             "paper-25-straight@path=0,1,0": ({"path": [[0, 1, 0]]}, 25),
             "paper-25-straight@comm.drop=0.1": ({"comm.drop": 0.1}, 25)}
    for cell, (overrides, robots) in cells.items():
        result = dict(transport_result(1, 100.0, 90.0, [waypoint(0, 0.1, 0.2, 0.01, 10)]), robots=robots,
                      study={"cell": cell, "overrides": overrides})
        (tmp_path / cell / "seed-1").mkdir(parents=True)
        write(tmp_path / cell / "seed-1" / "result.json", json.dumps(result))
    write_study_outputs(tmp_path, figures=False)
    rows = summary_rows(tmp_path)
    for cell in cells:
        cage, position = rows[(cell, "time_to_cage_s", "")], rows[(cell, "position_error_m", "0")]
        same_case = cell.endswith("comm.drop=0.1")      # the paper's experiment, with more radio loss
        assert (cage["paper_value"] == "247", position["paper_n"] == "30") == (same_case, same_case), cell
    report = (tmp_path / "report.md").read_text()
    assert "| paper-25-straight@robots.count=12 | 12 | 1 | 0 | 1/1 | 1/1 | 100% | 100 | – | 90 | – |" in report


def test_a_paper_cell_with_another_object_or_a_look_alike_file_gets_no_paper_numbers(tmp_path):
    """Only the robot count was checked: a paper transport whose box an override replaced, or a user's scenario
    file that is merely named paper-25-straight, showed the paper's numbers beside its own."""
    cells = {"paper-25-straight@object.size=0.2,0.2": {"object.size": [0.2, 0.2]},
             "paper-25-straight@object=shape=circle,radius=0.3": {"object": {"shape": "circle", "radius": 0.3}},
             "paper-25-straight@object.mass=3": {"object.mass": 3}}
    look_alike = tmp_path / "mine" / "paper-25-straight"        # a file `name: paper-25-straight`, 25 robots
    folders = {tmp_path / cell: {"cell": cell, "scenario": "paper-25-straight", "overrides": overrides}
               for cell, overrides in cells.items()}
    folders[look_alike] = {"cell": "paper-25-straight", "scenario": str(tmp_path / "mine.yaml"), "overrides": {}}
    for folder, study in folders.items():
        (folder / "seed-1").mkdir(parents=True)
        result = dict(transport_result(1, 100.0, 90.0, [waypoint(0, 0.1, 0.2, 0.01, 10)]), study=study)
        write(folder / "seed-1" / "result.json", json.dumps(result))
    for root in (tmp_path, tmp_path / "mine"):
        write_study_outputs(root, figures=False)
    rows = summary_rows(tmp_path)
    rows.update({("mine",) + key[1:]: row for key, row in summary_rows(tmp_path / "mine").items()})
    for cell in [*cells, "mine"]:
        same_case = cell.endswith("object.mass=3")       # the paper's box, heavier: the paper's baseline still
        cage, position = rows[(cell, "time_to_cage_s", "")], rows[(cell, "position_error_m", "0")]
        assert (cage["paper_value"] == "247", position["paper_n"] == "30") == (same_case, same_case), cell


def test_an_irregular_cell_with_another_robot_count_or_object_gets_no_paper_numbers(tmp_path):
    """irregular-clover@robots.count=12 showed the paper's 30-robot caging time (300 s) as its reference."""
    cells = {"irregular-clover@robots.count=12": ({"robots.count": 12}, 12),
             "irregular-clover@object.shape=cloud": ({"object.shape": "cloud"}, 30),
             "irregular-clover@object.scale=2": ({"object.scale": 2}, 30),
             "irregular-clover@object.position=1,0": ({"object.position": [1, 0]}, 30),
             "irregular-clover@comm.drop=0.1": ({"comm.drop": 0.1}, 30)}
    for cell, (overrides, robots) in cells.items():
        result = {"scenario": "irregular-clover", "seed": 1, "robots": robots, "failed": False,
                  "stop_reason": "behaviour finished", "caged": True, "time_to_cage_s": 280.0, "cage_size": 22,
                  "study": {"cell": cell, "overrides": overrides}}
        (tmp_path / cell / "seed-1").mkdir(parents=True)
        write(tmp_path / cell / "seed-1" / "result.json", json.dumps(result))
    write_study_outputs(tmp_path, figures=False)
    rows = summary_rows(tmp_path)
    for cell in cells:
        same_case = cell.endswith(("comm.drop=0.1", "object.position=1,0"))    # the paper's object and 30 robots
        assert (rows[(cell, "time_to_cage_s", "")]["paper_value"] == "300") == same_case, cell
    from sim_backend.scenario import load_scenario
    from sim_backend.study.paper_reference import IRREGULAR_ROBOTS, IRREGULAR_SCENARIOS

    assert {load_scenario(name).robots.count for name in IRREGULAR_SCENARIOS} == {IRREGULAR_ROBOTS}


def test_runs_stopped_before_their_scenarios_time_limit_get_no_paper_times(known_study):
    """--time-limit 200 on paper-25-straight (own limit 1500 s): the runs that would have caged after 200 s have
    no time, and our median of the fast ones stood beside the paper's as if the swarm were faster."""
    limits = {"paper-25-straight": 200.0, "irregular-clover": 5000.0}     # the clover's is longer: kept
    for path in known_study.glob("*/seed-*/result.json"):
        data = json.loads(path.read_text())
        data["study"] = dict(data.get("study") or {}, time_limit_s=limits[path.parent.parent.name])
        write(path, json.dumps(data))
    write_study_outputs(known_study)
    rows = summary_rows(known_study)
    assert rows[("paper-25-straight", "time_to_cage_s", "")]["paper_value"] == ""
    assert rows[("paper-25-straight", "time_to_complete_s", "")]["paper_value"] == ""
    assert rows[("paper-25-straight", "position_error_m", "0")]["paper_n"] == "30"   # errors where reached: kept
    assert rows[("irregular-clover", "time_to_cage_s", "")]["paper_value"] == "300"
    report = (known_study / "report.md").read_text()
    assert "| paper-25-straight | 25 | 4 | 1 | 3/3 | 2/3 | 67% | 200 [150–300] | – | 100 [95–105] | – |" in report
    own = load_scenario("paper-25-straight").time_limit_s
    assert (f"Paper times left out: these cells' runs were stopped before their scenario's own time limit "
            f"(`--time-limit`), so runs that would have caged or completed later have no time and our medians are "
            f"of the fast runs only: `paper-25-straight` (200 s, not {own:g} s).") in report


def test_report_md_puts_ours_next_to_the_paper(known_study):
    write_study_outputs(known_study, figures=False)
    report = (known_study / "report.md").read_text()
    assert ("| paper-25-straight | 25 | 4 | 1 | 3/3 | 2/3 | 67% | 200 [150–300] | 247 | 100 [95–105] | 100 | "
            "20 [19.5–20.5] | 0.46 ± 0.04 |") in report
    assert "| irregular-clover | 30 | 2 | 0 | 1/2 | – | 50% | 280 | 300 | – | – | 22 | – |" in report
    assert "| 0 | 3 | 0.4 [0.3–0.5] | 0.102 | 0.2 [0.15–0.25] | 0.0747 | 0.03 [0.02–0.04] | 0.0218 |" in report
    assert "- `paper-25-straight` seed 4: RuntimeError: boom" in report


def test_the_report_counts_what_is_missing_and_says_what_actually_ran(known_study):
    """Planned runs without a result are counted; the time limits are the runs' own; a result.json that is
    valid JSON but no run's result is left out and listed; warnings the runs carried are shown."""
    write(known_study / "study.json", json.dumps({
        "name": "known", "time_limit_s": 100.0, "commands": ["khepri study known.yaml --time-limit 100"],
        "planned": ["paper-25-straight/seed-1", "paper-25-straight/seed-5", "irregular-clover/seed-3"]}))
    clover = known_study / "irregular-clover" / "seed-1" / "result.json"
    data = json.loads(clover.read_text())
    data["study"] = {"cell": "irregular-clover", "overrides": {}, "time_limit_s": 1500.0}
    data["warnings"] = ["comm.range_m: 0.3 m is shorter than the cage spacing I_d"]
    write(clover, json.dumps(data))
    (known_study / "junk" / "seed-1").mkdir(parents=True)
    write(known_study / "junk" / "seed-1" / "result.json", json.dumps({"scenario": "x"}))
    write_study_outputs(known_study, figures=False)
    report = (known_study / "report.md").read_text()
    assert "**2 of the 3 runs the commands above asked for have no result yet**" in report
    assert "`paper-25-straight/seed-5`, `irregular-clover/seed-3`" in report
    assert "Time limit: mixed: each scenario’s own (5 runs), 1500 s (1 run)." in report   # not study.json's 100
    assert "- `irregular-clover`: comm.range_m: 0.3 m is shorter than the cage spacing I_d" in report
    assert "- `junk/seed-1/result.json`" in report and len(load_results(known_study).cells) == 2


def test_the_report_flags_results_of_mixed_code_and_scenario_versions(known_study):
    """Results carry behaviour_sha1 and scenario_sha1, but a folder mixing two versions of the code (workers with
    other checkouts, a fix between two commands) was reported as if it were one."""
    write_study_outputs(known_study, figures=False)
    assert "## Mixed versions" not in (known_study / "report.md").read_text()    # nothing recorded: nothing said
    versions = {1: ("aaaa", "s1"), 2: ("aaaa", "s1"), 3: ("bbbb", "s2")}
    for seed, (code, scenario) in versions.items():
        path = known_study / "paper-25-straight" / f"seed-{seed}" / "result.json"
        data = json.loads(path.read_text())
        data["study"].update(behaviour_sha1=code, scenario_sha1=scenario)
        write(path, json.dumps(data))
    write_study_outputs(known_study, figures=False)
    report = (known_study / "report.md").read_text()
    assert "## Mixed versions" in report and "**These results come from different versions" in report
    assert "- behaviour `transport`: 2 versions of its code (`aaaa` 2 runs, `bbbb` 1 run)" in report
    assert "- `paper-25-straight`: 2 versions of its scenario (`s1` 2 runs, `s2` 1 run)" in report


def test_runs_of_one_cell_with_and_without_a_study_limit_are_not_mixed_scenario_versions(known_study):
    """A run under the study's limit fingerprints its scenario without time_limit_s: a cell whose seeds ran with
    --time-limit and later ones without was reported as running two versions of its scenario."""
    limits = {1: (1.0, "limited"), 2: (1.0, "limited"), 3: (None, "own")}
    for seed, (limit, scenario) in limits.items():
        path = known_study / "paper-25-straight" / f"seed-{seed}" / "result.json"
        data = json.loads(path.read_text())
        data["study"].update(time_limit_s=limit, scenario_sha1=scenario, scenario_sha1_full=f"full-{seed}")
        write(path, json.dumps(data))
    write_study_outputs(known_study, figures=False)
    assert "## Mixed versions" not in (known_study / "report.md").read_text()
    path = known_study / "paper-25-straight" / "seed-2" / "result.json"      # a real change is still said
    write(path, path.read_text().replace('"limited"', '"edited"'))
    write_study_outputs(known_study, figures=False)
    assert "- `paper-25-straight`: 2 versions of its scenario (`limited` 1 run, `edited` 1 run)" in \
        (known_study / "report.md").read_text()


def test_a_behaviour_without_caging_gets_no_success_rate(tmp_path):
    result = {"scenario": "aggregate-20", "seed": 1, "robots": 20, "behaviour": "aggregate", "failed": False,
              "stop_reason": "time limit", "spread_ratio": 0.2, "study": {"cell": "aggregate-20", "overrides": {}}}
    (tmp_path / "aggregate-20" / "seed-1").mkdir(parents=True)
    write(tmp_path / "aggregate-20" / "seed-1" / "result.json", json.dumps(result))
    write_study_outputs(tmp_path, figures=False)
    report = (tmp_path / "report.md").read_text()
    assert "| aggregate-20 | 20 | 1 | 0 | time limit 1 | – | – |" in report    # how it ended; no success column
    assert "success" not in report.split("## Outcome per cell (other behaviours)")[1]


def test_a_behaviours_own_numbers_and_flags_are_summarised_and_the_paper_is_left_out(tmp_path):
    """A study of one's own behaviour is run for its evaluator's numbers: the summary and the report had none of
    them (only how the runs ended), and they cited the paper's data that no cell was compared with."""
    for seed, (ratio, gathered) in enumerate(((0.2, True), (0.4, False), (0.3, True)), start=1):
        result = {"scenario": "aggregate-20", "seed": seed, "robots": 20, "behaviour": "aggregate", "failed": False,
                  "stop_reason": "time limit", "sim_time_s": 20.0, "real_time_factor": 100.0, "wall_time_s": 0.2,
                  "spread_ratio": ratio, "gathered": gathered, "note": "text is not summarised",
                  "study": {"cell": "aggregate-20", "overrides": {}}}
        (tmp_path / "aggregate-20" / f"seed-{seed}").mkdir(parents=True)
        write(tmp_path / "aggregate-20" / f"seed-{seed}" / "result.json", json.dumps(result))
    write_study_outputs(tmp_path, figures=False)
    rows = {row["metric"]: row for row in csv.DictReader((tmp_path / "summary.csv").open())}
    assert rows["spread_ratio"]["value"] == "0.3" and rows["spread_ratio"]["min"] == "0.2"
    assert rows["spread_ratio"]["max"] == "0.4" and rows["spread_ratio"]["n"] == "3"
    assert float(rows["gathered_rate"]["value"]) == pytest.approx(2 / 3)
    assert not {"seed", "robots", "sim_time_s", "real_time_factor", "note", "note_rate"} & set(rows)
    report = (tmp_path / "report.md").read_text()
    assert "| aggregate-20 | `spread_ratio` | 3 | 0.3 [0.25–0.35] | 0.2 – 0.4 |" in report
    assert "| aggregate-20 | `gathered` | 3 | true in 67% | – |" in report
    assert "Paper" not in report and "paper" not in report


def test_a_transport_study_gets_no_table_of_its_own_numbers(tmp_path):
    """The transport's numbers are in its own tables already: a whole lab-6 run's result.json, aggregated, adds
    nothing as 'own results' (a field the transport's evaluator gains must join FRAMEWORK_FIELDS or its table)."""
    assert main(["sim", "run", "lab-6", "--out", str(tmp_path / "run"), "--no-plot"]) == 0
    result = json.loads((tmp_path / "run" / "result.json").read_text())
    assert result["completed"] is True
    (tmp_path / "study" / "lab-6" / "seed-1").mkdir(parents=True)
    write(tmp_path / "study" / "lab-6" / "seed-1" / "result.json", json.dumps(dict(result, failed=False)))
    write_study_outputs(tmp_path / "study", figures=False)
    assert "## The behaviour's own results" not in (tmp_path / "study" / "report.md").read_text()


def test_override_values_that_would_share_a_folder_are_refused(tmp_path, capsys):
    study = write(tmp_path / "s.yaml", TINY_STUDY + "overrides: {comm.drop: [0.1234561, 0.1234564]}\n")
    assert main(["study", str(study), "--dry-run"]) == 2
    assert (f"khepri: error: {study}: overrides: comm.drop=0.1234561 and comm.drop=0.1234564 give the same folder name "
            "'lab-6@comm.drop=0.123456'") in capsys.readouterr().err


def test_the_simulators_warnings_are_said_once_per_cell_before_the_study_runs(tmp_path, capsys):
    study = write(tmp_path / "s.yaml", TINY_STUDY + "overrides: {comm.range_m: [3.0, 0.3]}\n")
    assert main(["study", str(study), "--dry-run"]) == 0
    err = capsys.readouterr().err
    assert err.count("khepri: warning: lab-6@comm.range_m=0.3: comm.range_m: 0.3 m is shorter than") == 1
    assert "lab-6@comm.range_m=3:" not in err


def test_figures_are_written_as_non_empty_images(known_study):
    files = write_study_outputs(known_study)
    figures = sorted(p.name for name, p in files.items() if name.startswith("figure"))
    assert figures == ["effective.png", "errors.png", "times.png", "trajectories.png"]
    assert set(figures) <= set(FIGURE_FILES)     # what a later aggregation removes if it does not redraw it
    for name in figures:
        with Image.open(known_study / "figures" / name) as image:
            pixels = np.asarray(image.convert("L"))
        assert pixels.shape[0] > 300 and pixels.std() > 5   # something is drawn, not a blank canvas
    assert "![Errors per waypoint](figures/errors.png)" in (known_study / "report.md").read_text()


def test_an_aggregation_without_figures_removes_the_earlier_ones(known_study):
    """Figures left from an earlier aggregation would show other runs than summary.csv and report.md."""
    write_study_outputs(known_study)
    assert (known_study / "figures" / "errors.png").exists()
    (known_study / "figures" / "mine.png").write_bytes(b"a user's own file")
    write_study_outputs(known_study, figures=False)
    assert sorted(p.name for p in (known_study / "figures").iterdir()) == ["mine.png"]
    assert "## Figures" not in (known_study / "report.md").read_text()


def test_study_report_reaggregates_a_folder_without_running(known_study, capsys):
    assert main(["study", "report", str(known_study), "--no-figures"]) == 1   # the folder has a failed run
    assert "report: " in capsys.readouterr().out
    assert len(load_results(known_study).cells) == 2
    assert main(["study", "report", str(known_study / "missing")]) == 2
    assert "study report: no such folder" in capsys.readouterr().err
    # The folder after an option: argparse alone left it over as an unrecognised argument.
    assert main(["study", "report", "--no-figures", str(known_study / "missing")]) == 2
    assert "study report: no such folder" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["study", "report", "--no-figures", str(known_study), "surplus"])
    assert "unrecognized arguments: surplus" in capsys.readouterr().err
    for option in (["--reps", "5"], ["--executor", "spark"], ["--retry-failed"], ["--executor", "local"]):
        assert main(["study", "report", str(known_study), *option]) == 2      # ignored without a word, before
        assert capsys.readouterr().err == (f"khepri: error: {option[0]}: is for running a study; `khepri study "
                                           "report DIR` runs nothing and takes only --no-figures\n")
    (known_study / "notes.txt").write_text("a file, not a study")
    assert main(["study", "report", str(known_study / "notes.txt")]) == 2
    assert "notes.txt is a file: give the study's folder" in capsys.readouterr().err
    (known_study / "empty").mkdir()
    assert main(["study", "report", str(known_study / "empty")]) == 2
    assert "holds no study" in capsys.readouterr().err


@pytest.mark.parametrize("edit", [{"study": [1]}, {"study": {"overrides": [1]}},
                                  {"study": {"time_limit_s": [60]}}, {"study": {"behaviour_sha1": [1]}},
                                  {"waypoints": [1, 2]}, {"waypoints": [{"index": "a"}]}, {"warnings": 5},
                                  {"completed": "maybe"}, {"final_position_error_m": "far"}, {"caged": 1},
                                  {"waypoints": [{"index": 0, "position_error_m": "0.1"}]}])
def test_a_hand_edited_result_of_another_shape_is_listed_not_a_traceback(known_study, capsys, edit):
    """These crashed `study report` (and a resumed study's report) with a TypeError or AttributeError; the last
    four were taken: "maybe" counted as completed, and "far" was left out of the statistics unsaid."""
    path = known_study / "paper-25-straight/seed-1/result.json"
    write(path, json.dumps({**json.loads(path.read_text()), **edit}))
    assert main(["study", "report", str(known_study), "--no-figures"]) == 1   # the folder has a failed run
    assert "paper-25-straight/seed-1/result.json" in load_results(known_study).unreadable


def test_a_seed_folder_named_with_a_superscript_is_listed_not_a_traceback(known_study):
    """`seed-²` passed str.isdigit, and int() of it ended `study report` in a ValueError."""
    odd = known_study / "paper-25-straight/seed-\u00b2"
    shutil.copytree(known_study / "paper-25-straight/seed-1", odd)
    assert "paper-25-straight/seed-\u00b2/result.json" in load_results(known_study).unreadable


def test_a_result_nested_past_pythons_recursion_limit_is_listed_not_a_traceback(known_study, capsys):
    """json.loads raises RecursionError, not ValueError, for it: `study report` ended in a traceback."""
    write(known_study / "paper-25-straight/seed-1/result.json", DEEP_JSON)
    assert main(["study", "report", str(known_study), "--no-figures"]) == 1   # the folder has a failed run
    assert "paper-25-straight/seed-1/result.json" in load_results(known_study).unreadable


# --- the paper's data and the progress line ------------------------------------------------------------

def test_the_papers_csv_gives_the_medians_its_readme_quotes():
    for row in paper.quoted_numbers()["error_medians"]:
        case = paper.PaperCase(robots=row["robots"], path=row["path"])
        median = {(m, wp): float(np.median(paper.error_values(case, wp, m)))
                  for m in paper.ERROR_METRICS.values() for wp in range(10)}
        assert median[("centroid_estimation_error_m", 0)] == pytest.approx(row["centroid_wp0"], abs=0.006)
        assert median[("centroid_estimation_error_m", 9)] == pytest.approx(row["centroid_wp9"], abs=0.006)
        assert median[("position_error_m", 0)] == pytest.approx(row["position_wp0"], abs=0.0006)
        assert median[("position_error_m", 9)] == pytest.approx(row["position_wp9"], abs=0.0006)
        worst = max(median[("orientation_error_rad", wp)] for wp in range(10))
        assert worst == pytest.approx(row["orientation_max"], abs=0.0006)
    assert len(paper.error_values(paper.PaperCase(100, "straight_rot"), 0, "position_error_m")) == 14


class FakeClock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def test_progress_lines_show_each_run_and_an_eta_from_the_pace_so_far(tmp_path):
    clock = FakeClock()
    with (tmp_path / "log.txt").open("w+") as stream:
        progress = StudyProgress(4, stream, clock)
        clock.now = 10.0
        progress.update({"seed": 1, "failed": False, "caged": True, "time_to_cage_s": 71.0, "completed": False,
                         "wall_time_s": 2.5, "study": {"cell": "lab-6"}})
        clock.now = 20.0
        progress.update({"seed": 2, "failed": True, "error": "RuntimeError: boom", "study": {"cell": "lab-6"}})
        stream.seek(0)
        lines = stream.read().splitlines()
    assert lines == ["[1/4] lab-6 seed 1: caged at 71 s, not completed (2.5 s wall) | ETA 0:00:30",
                     "[2/4] lab-6 seed 2: FAILED: RuntimeError: boom, 1 failed | ETA 0:00:20"]


def test_the_eta_weighs_runs_by_their_expected_cost(tmp_path):
    """Longest first: one 100-robot run done in 20 minutes, with another as long and two short ones left,
    is about 20 minutes more, not three times the pace of the first run."""
    clock = FakeClock()
    costs = {("paper-100-straight", 1): 600_000.0, ("paper-100-zigzag", 1): 600_000.0,
             ("lab-6", 1): 3_600.0, ("lab-6", 2): 3_600.0}
    with (tmp_path / "log.txt").open("w+") as stream:
        progress = StudyProgress(4, stream, clock, costs)
        clock.now = 1200.0
        progress.update({"seed": 1, "failed": False, "caged": True, "time_to_cage_s": 3718.0, "completed": True,
                         "time_to_complete_s": 150.0, "study": {"cell": "paper-100-straight"}})
        assert progress.eta_text() == "ETA 0:20:14"


USER_BEHAVIOUR = '''
from dataclasses import dataclass

from onboard.behaviour import Behaviour, register


@dataclass
class StandStillParams:
    speed_m_s: float = 0.0


@register("study-stand-still")
class StandStill(Behaviour):
    Params = StandStillParams

    def step(self) -> None:
        self.robot.wheels.set_speeds(self.params.speed_m_s, self.params.speed_m_s)
'''


def test_workers_import_the_users_behaviour_module_too(tmp_path, monkeypatch, capsys):
    write(tmp_path / "study_user_behaviour.py", USER_BEHAVIOUR)
    write(tmp_path / "still.yaml", "name: still-4\nbehaviour: study-stand-still\ntime_limit_s: 1\n"
                                   "robots: {count: 4, spawn: {x: [-1, 1], y: [-1, 1]}}\n")
    write(tmp_path / "still-study.yaml", "scenarios: [still.yaml]\nreps: 1\n")
    monkeypatch.chdir(tmp_path)
    code = main(["--import", "study_user_behaviour", "study", "still-study.yaml", "--out", "out", "--workers", "1"])
    result = json.loads((tmp_path / "out" / "still-4" / "seed-1" / "result.json").read_text())
    assert (code, result["failed"], result["behaviour"]) == (0, False, "study-stand-still"), result.get("error")


def test_sigterm_stops_the_study_and_its_workers_and_keeps_it_resumable(tmp_path):
    import signal
    import subprocess
    import sys

    out = tmp_path / "out"
    study = tmp_path / "long.yaml"
    study.write_text("name: long\nscenarios: [lab-6]\nseeds: [1, 2, 3, 4]\n")
    driver = subprocess.Popen([sys.executable, "-m", "khepri_cli.main", "study", str(study), "--out", str(out),
                               "--workers", "2", "--no-figures"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    workers = []
    deadline = time.monotonic() + 60
    while len(workers) < 2 and time.monotonic() < deadline:   # the pool's two workers have started
        time.sleep(0.2)
        children = Path(f"/proc/{driver.pid}/task/{driver.pid}/children").read_text().split()
        workers = [int(pid) for pid in children if "spawn_main" in Path(f"/proc/{pid}/cmdline").read_text()]
    assert len(workers) == 2
    driver.send_signal(signal.SIGTERM)
    assert driver.wait(timeout=30) == 130
    time.sleep(0.5)
    alive = [pid for pid in workers if Path(f"/proc/{pid}").exists()
             and "Z" not in Path(f"/proc/{pid}/stat").read_text().split()[2]]
    assert alive == []
    assert not list(out.glob("*/seed-*/result.json"))        # interrupted runs left no result: a resume reruns them


def test_ctrl_c_on_a_dask_local_cluster_says_one_line_and_keeps_the_runs_so_far(tmp_path):
    """Ctrl-C in a terminal reaches the whole foreground group: each LocalCluster worker printed a traceback of
    its event loop's KeyboardInterrupt beside the driver's "khepri: interrupted"."""
    import signal
    import subprocess
    import sys

    out = tmp_path / "out"
    study = write(tmp_path / "many.yaml", "name: many\nscenarios: [lab-6]\nreps: 500\ntime_limit_s: 10\n")
    driver = subprocess.Popen([sys.executable, "-m", "khepri_cli.main", "study", str(study), "--out", str(out),
                               "--executor", "dask", "--workers", "1", "--no-figures"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True,
                              preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))   # as in a terminal
    try:
        deadline = time.monotonic() + 60
        while not list(out.glob("*/seed-*/result.json")) and time.monotonic() < deadline:
            time.sleep(0.2)
        time.sleep(0.5)                                   # the next run in flight
        os.killpg(driver.pid, signal.SIGINT)              # what the terminal does on Ctrl-C
        _, err = driver.communicate(timeout=30)
    finally:
        if driver.poll() is None:
            os.killpg(driver.pid, signal.SIGKILL)
    lines = [line for line in err.decode().splitlines() if not line.startswith("[")]   # not the progress lines
    assert (driver.returncode, lines) == (130, ["khepri: interrupted"])
    assert 0 < len(results_in(out)) < 500


def test_a_local_cluster_worker_does_not_log_a_heartbeat_to_the_scheduler_that_closed(caplog):
    """The Ctrl-C test above failed once in a full suite run: a worker's heartbeat fell between the scheduler
    closing and its own close, and it logged an ERROR with two tracebacks under "khepri: interrupted". The
    worker's other errors still show."""
    import logging
    import signal

    from sim_backend.study.executors import dask_setup

    before = signal.getsignal(signal.SIGINT)
    worker_log = logging.getLogger("distributed.worker")
    try:
        dask_setup(None)
        with caplog.at_level(logging.ERROR, logger="distributed.worker"):
            try:
                raise OSError("Timed out trying to connect to tcp://127.0.0.1:40000")
            except OSError:
                worker_log.exception("Failed to communicate with scheduler during heartbeat.")
                worker_log.exception("Compute Failed")
    finally:
        signal.signal(signal.SIGINT, before)
        worker_log.filters.clear()
    assert [record.getMessage() for record in caplog.records] == ["Compute Failed"]


def test_the_workers_of_a_killed_driver_do_not_stay_behind(tmp_path):
    """SIGKILL of the driver (the out-of-memory killer, `kill -9`) left its pool's worker waiting for ever."""
    import signal
    import subprocess
    import sys

    study = tmp_path / "long.yaml"
    study.write_text("name: long\nscenarios: [lab-6]\nseeds: [1, 2, 3, 4]\n")
    driver = subprocess.Popen([sys.executable, "-m", "khepri_cli.main", "study", str(study), "--out",
                               str(tmp_path / "out"), "--workers", "1", "--no-figures"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    workers = []
    try:
        deadline = time.monotonic() + 60
        while not workers and time.monotonic() < deadline:
            time.sleep(0.2)
            children = Path(f"/proc/{driver.pid}/task/{driver.pid}/children").read_text().split()
            workers = [int(pid) for pid in children if "spawn_main" in Path(f"/proc/{pid}/cmdline").read_text()]
        assert workers
        driver.send_signal(signal.SIGKILL)
        driver.wait(timeout=10)

        def alive():
            return [pid for pid in workers if Path(f"/proc/{pid}").exists()
                    and "Z" not in Path(f"/proc/{pid}/stat").read_text().split()[2]]
        deadline = time.monotonic() + 10      # a run in flight is a second of lab-6; then 0.5 s to notice
        while alive() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert alive() == []
    finally:
        for pid in workers:
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass


def test_a_dask_address_that_never_answers_as_dask_is_an_error_not_a_hang(tmp_path):
    """Something listens there (a web server, say), accepts the connection, and never speaks Dask."""
    import socket

    from onboard.config import ConfigError
    from sim_backend.study.dask_address import connect_to_scheduler

    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    address = f"tcp://127.0.0.1:{listener.getsockname()[1]}"
    try:
        with pytest.raises(ConfigError, match=f"cannot use the Dask scheduler {address}"):
            connect_to_scheduler(address, timeout_s=1.0)
    finally:
        listener.close()


def test_a_dask_address_where_nothing_listens_is_refused_at_once_and_says_so():
    """Dask retried a refused connection for its whole 30 s timeout, then said only "Timed out trying to connect".
    (A scheduler started just before the study still has 10 s to listen: see the lost-scheduler test.)"""
    import socket

    from onboard.config import ConfigError
    from sim_backend.study.dask_address import connect_to_scheduler

    with socket.socket() as probe:       # a free port, closed again: nothing listens there
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    started = time.monotonic()
    refused = f"nothing listens on port {port} of 127.0.0.1 \\(connection refused for 10 s\\)"
    with pytest.raises(ConfigError, match=refused):
        connect_to_scheduler(f"tcp://127.0.0.1:{port}")
    assert time.monotonic() - started < 20


def test_a_dask_scheduler_that_cannot_be_reached_is_said_before_the_folder_is_made(tmp_path, capsys, monkeypatch):
    import socket

    from sim_backend.study import executors

    real = executors.connect_to_scheduler
    monkeypatch.setattr(executors, "connect_to_scheduler", lambda address: real(address, timeout_s=1.0))
    with socket.socket() as probe:       # a free port, closed again: nothing listens there
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    study = write(tmp_path / "tiny.yaml", TINY_STUDY)
    assert main(["study", str(study), "--executor", f"dask:tcp://127.0.0.1:{port}", "--out", str(tmp_path / "o")]) == 2
    assert f"cannot use the Dask scheduler tcp://127.0.0.1:{port}" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_a_dask_host_that_does_not_exist_is_said_by_a_dry_run_too(tmp_path, capsys):
    """--dry-run checked the address's form and port but not its host, so a typo there passed the rehearsal."""
    study = write(tmp_path / "tiny.yaml", TINY_STUDY)
    command = ["study", str(study), "--dry-run", "--out", str(tmp_path / "o"), "--executor"]
    assert main(command + ["dask:tcp://nosuchhost.invalid:8786"]) == 2
    assert ("khepri: error: --executor: cannot use the Dask scheduler tcp://nosuchhost.invalid:8786: unknown host "
            "'nosuchhost.invalid'") in capsys.readouterr().err
    assert main(command + ["dask:tcp://127.0.0.1:8786"]) == 0        # nothing is reached: nobody need listen


@pytest.mark.parametrize("damaged, why", [
    ("[1, 2]", "not a JSON object: [1, 2]"), ('{"name": "tiny", "commands": "khepri study x"}',
                                              "commands is not a list of text"),
    ('{"name": "tiny", "commands": [', "not JSON: Expecting value: line 1 column 31 (char 30)"), ("", "empty"),
    ("[]", "not a JSON object: []"), (DEEP_JSON, "not JSON: lists or mappings nested too deeply"),
    ('{"commands": []}', "no study name"),
], ids=["list", "commands", "cut", "empty", "empty-list", "deep", "nameless"])
def test_a_damaged_study_json_is_said_and_kept_as_it_is(tmp_path, capsys, damaged, why):
    """Taken as missing, a damaged study.json let another study in without --merge, and a run replaced it, the
    commands it listed lost."""
    from sim_backend.study.driver import record_study

    study = write(tmp_path / "tiny.yaml", "name: other\nscenarios: [lab-6]\nseeds: [1]\ntime_limit_s: 1\n")
    out = tmp_path / "out"
    out.mkdir()
    (out / "study.json").write_text(damaged)
    for options in (["--dry-run"], [], ["--merge"]):
        assert main(["study", str(study), "--out", str(out), "--workers", "1", "--no-figures", *options]) == 2
        said = capsys.readouterr().err
        assert said.startswith(f"khepri: error: {out / 'study.json'}: damaged ({why}") and said.count("\n") == 1
        assert said.endswith("): fix or remove it\n"), said
    with pytest.raises(ConfigError, match="damaged"):
        record_study(parse_study({"scenarios": ["lab-6"], "reps": 1}), out, "khepri study again")
    assert (out / "study.json").read_text() == damaged and sorted(p.name for p in out.iterdir()) == ["study.json"]


def test_a_folder_of_other_files_is_refused_rather_than_written_over(tmp_path, capsys):
    """--out naming a folder of one's own (paper notes in report.md, a figure) wrote the study's report.md and
    figures/ over them without a word."""
    study = write(tmp_path / "tiny.yaml", "name: tiny\nscenarios: [lab-6]\nseeds: [1]\ntime_limit_s: 1\n")
    out = tmp_path / "notes"
    (out / "figures").mkdir(parents=True)
    write(out / "report.md", "my paper notes")
    write(out / "figures" / "times.png", "my figure")
    for options in (["--dry-run"], [], ["--merge"]):
        assert main(["study", str(study), "--out", str(out), "--workers", "1", *options]) == 2
        assert capsys.readouterr().err == (
            f"khepri: error: --out: {out} is not empty (figures, report.md) and holds no study (no study.json): a "
            "study writes report.md, summary.csv and figures/ into its folder, over what is there; give a new or "
            "empty folder\n")
    assert (out / "report.md").read_text() == "my paper notes"
    assert sorted(p.name for p in out.rglob("*")) == ["figures", "report.md", "times.png"]


def test_a_first_run_stopped_before_its_study_json_resumes_and_so_do_runs_without_one(tmp_path, capsys):
    """A study writes study.json before any run, after taking the folder's lock: stopped in between, the folder
    holds the lock (and perhaps study.json's temporary file) alone, and is the study's. A folder whose study.json
    was removed (as the error above says to) still holds the runs: a study folder too."""
    study = write(tmp_path / "tiny.yaml", "name: tiny\nscenarios: [lab-6]\nseeds: [1]\ntime_limit_s: 1\n")
    out = tmp_path / "out"
    out.mkdir()
    write(out / "study.lock", "4242\n")
    write(out / "study.tmp", '{"name": "ti')
    assert main(["study", str(study), "--out", str(out), "--workers", "1", "--no-figures"]) == 0
    assert "ran 1 run (0 failed)" in capsys.readouterr().out
    (out / "study.json").unlink()
    assert main(["study", str(study), "--out", str(out), "--workers", "1", "--no-figures"]) == 0
    assert "ran 0 runs (0 failed), skipped 1 finished" in capsys.readouterr().out


def test_runs_kept_from_another_time_limit_are_not_said_to_have_run_a_changed_scenario(tmp_path, capsys):
    """A run under the study's limit fingerprints its scenario without time_limit_s, one under the scenario's own
    with it: the same scenario passed for a changed one after --time-limit came or went."""
    scenario = write(tmp_path / "arena.yaml", "robots: {count: 4}\nobject: {shape: circle, radius: 0.2}\n"
                                              "time_limit_s: 2\n")
    study = write(tmp_path / "s.yaml", "name: s\nscenarios: [arena.yaml]\nseeds: [1]\n")
    for first, then in ((["--time-limit", "1"], []), ([], ["--time-limit", "1"])):
        out = tmp_path / f"out{len(first)}"
        assert main(["study", str(study), "--out", str(out), "--workers", "1", "--no-figures", *first]) == 0
        capsys.readouterr()
        assert main(["study", str(study), "--out", str(out), "--dry-run", *then]) == 0
        said = capsys.readouterr().err
        assert "1 run already in" in said and "ran with another time limit" in said and "changed since" not in said
    write(scenario, scenario.read_text() + "comm: {drop: 0.1}\n")       # a real change is still said
    assert main(["study", str(study), "--out", str(tmp_path / "out2"), "--dry-run"]) == 0
    assert "ran a scenario that has changed since (cells arena)" in capsys.readouterr().err


def test_a_folder_of_another_study_is_refused_unless_merge_asks_for_it(tmp_path, capsys):
    """--out naming another study's folder took its finished runs of lab-6 as this study's, and renamed its
    report, without a word."""
    first = write(tmp_path / "first.yaml", TINY_STUDY.replace("seeds: 1..2", "seeds: [1]"))
    second = write(tmp_path / "second.yaml", TINY_STUDY.replace("name: tiny", "name: second"))
    out = tmp_path / "out"
    assert main(["study", str(first), "--out", str(out), "--workers", "1", "--no-figures"]) == 0
    capsys.readouterr()
    for dry_run in (["--dry-run"], []):
        assert main(["study", str(second), "--out", str(out), "--workers", "1", "--no-figures", *dry_run]) == 2
        assert (f"khepri: error: --out: {out} holds the study 'tiny' ({out}/study.json), not 'second': give another "
                "--out, or add --merge to add this study's runs to that folder") in capsys.readouterr().err
    assert json.loads((out / "study.json").read_text())["name"] == "tiny"
    assert main(["study", str(first), "--out", str(out), "--workers", "1", "--no-figures"]) == 0   # its own: resumes
    assert main(["study", str(second), "--out", str(out), "--workers", "1", "--no-figures", "--merge"]) == 0
    assert "ran 1 run (0 failed), skipped 1 finished" in capsys.readouterr().out
    assert json.loads((out / "study.json").read_text())["commands"][-1].endswith("--merge")


def test_a_hand_edited_study_name_in_the_out_folder_is_shown_by_its_start(tmp_path):
    """The name recorded in study.json went into the error line whole."""
    from sim_backend.study.folder import check_out_folder

    write(tmp_path / "study.json", json.dumps({"name": "n" * 100_000}))
    with pytest.raises(ConfigError) as caught:
        check_out_folder(tmp_path, "mine", merge=False)
    assert f"holds the study '{'n' * 59}... ({tmp_path}/study.json), not 'mine'" in str(caught.value)


def write_gathering(path: Path, name: str, time_limit_s: float) -> Path:
    """A scenario file of six robots running `aggregate` where lab-6 places them, named ``name``."""
    scenario = load_scenario("lab-6")
    return write(path, f"name: {name}\nbehaviour: aggregate\ntime_limit_s: {time_limit_s:g}\n"
                       f"robots: {{count: 6, spawn: {{x: {list(scenario.robots.spawn.x)}, "
                       f"y: {list(scenario.robots.spawn.y)}}}}}\n")


def test_resume_warns_about_finished_runs_of_a_scenario_file_edited_since(tmp_path, capsys):
    write_gathering(tmp_path / "mine.yaml", "mine", time_limit_s=2)
    study = write(tmp_path / "edits.yaml", "scenarios: [mine.yaml]\nreps: 1\n")
    out = tmp_path / "out"
    assert main(["study", str(study), "--out", str(out), "--workers", "1", "--no-figures"]) == 0
    main(["study", str(study), "--out", str(out), "--workers", "1", "--no-figures"])
    assert "changed since" not in capsys.readouterr().err
    write(tmp_path / "mine.yaml", (tmp_path / "mine.yaml").read_text().replace("count: 6", "count: 4"))
    for dry_run in (["--dry-run"], []):     # --dry-run says so too, before anything would run
        main(["study", str(study), "--out", str(out), "--workers", "1", "--no-figures", *dry_run])
        err = capsys.readouterr().err
        assert "warning: 1 run already in" in err and "ran a scenario that has changed since (cells mine)" in err
        assert "(cells mine) and is kept; use another --out, or delete those cells' folders, to run it again" in err


def test_resume_does_not_warn_of_an_edit_that_changes_no_run(tmp_path, capsys):
    """A new description, or the scenario's own time limit where the study sets the limit, warned that the
    scenario had changed and told the user to throw the runs away. Runs recorded before (their scenario_sha1
    the fingerprint of every field) are still taken as the scenario they ran."""
    write_gathering(tmp_path / "mine.yaml", "mine", time_limit_s=20)
    study = write(tmp_path / "edits.yaml", "scenarios: [mine.yaml]\nreps: 1\ntime_limit_s: 2\n")
    out = tmp_path / "out"
    assert main(["study", str(study), "--out", str(out), "--workers", "1", "--no-figures"]) == 0
    original = (tmp_path / "mine.yaml").read_text()
    edited = original.replace("time_limit_s: 20", "time_limit_s: 21")
    write(tmp_path / "mine.yaml", edited + "description: six robots gather\n")
    assert main(["study", str(study), "--out", str(out), "--workers", "1", "--no-figures", "--dry-run"]) == 0
    assert "changed since" not in capsys.readouterr().err
    result_path = out / "mine" / "seed-1" / "result.json"
    result = json.loads(result_path.read_text())
    assert result["study"]["scenario_sha1"] != result["study"]["scenario_sha1_full"]
    old_style = dict(result["study"], scenario_sha1=result["study"].pop("scenario_sha1_full"))
    write(result_path, json.dumps(dict(result, study=old_style)))         # as a run recorded before
    write(tmp_path / "mine.yaml", original)           # the very scenario file that run ran
    assert main(["study", str(study), "--out", str(out), "--workers", "1", "--no-figures", "--dry-run"]) == 0
    assert "changed since" not in capsys.readouterr().err
    write(tmp_path / "mine.yaml", original.replace("count: 6", "count: 4"))   # a change that changes the run
    main(["study", str(study), "--out", str(out), "--workers", "1", "--no-figures", "--dry-run"])
    assert "ran a scenario that has changed since (cells mine)" in capsys.readouterr().err


def test_the_report_takes_runs_from_before_and_after_the_fingerprint_change_as_one_version(known_study):
    for seed in (1, 2, 3):
        path = known_study / "paper-25-straight" / f"seed-{seed}" / "result.json"
        data = json.loads(path.read_text())
        # seed 1 as recorded before 2026-11-29 (every field), the others after (both fingerprints)
        data["study"].update({"scenario_sha1": "full"} if seed == 1 else
                             {"scenario_sha1": "runs", "scenario_sha1_full": "full"})
        write(path, json.dumps(data))
    write_study_outputs(known_study, figures=False)
    assert "## Mixed versions" not in (known_study / "report.md").read_text()


def test_resume_warns_about_finished_runs_of_a_behaviour_edited_since(tmp_path, capsys, monkeypatch):
    """Only the scenario was fingerprinted: after a fix to the behaviour, a re-run kept the old results
    without a word."""
    module = write(tmp_path / "edited_walk.py", "from onboard.behaviour import Behaviour, register\n\n\n"
                                                "@register('edited-walk')\nclass Walk(Behaviour):\n"
                                                "    def step(self):\n        self.robot.wheels.set_speeds(0.1, 0.1)\n")
    write(tmp_path / "walk.yaml", "name: walk\nbehaviour: edited-walk\ntime_limit_s: 1\n"
                                  "robots: {count: 2, spawn: {x: [-0.5, 0.5], y: [-0.5, 0.5]}}\n")
    study = write(tmp_path / "s.yaml", "scenarios: [walk.yaml]\nreps: 1\n")
    monkeypatch.chdir(tmp_path)
    command = ["--import", "edited_walk", "study", str(study), "--out", "out", "--workers", "1", "--no-figures"]
    assert main(command) == 0
    main(command)
    assert "behaviour's code" not in capsys.readouterr().err
    module.write_text(module.read_text().replace("0.1, 0.1", "0.2, 0.2"))
    behaviour_code_sha1.cache_clear()           # a new `khepri study` process would read the file afresh
    main(command + ["--dry-run"])
    err = capsys.readouterr().err
    assert "warning: 1 run already in out ran another version of its behaviour's code" in err
    assert ") and is kept; use another --out" in err


def test_scenarios_picks_a_scenario_file_by_its_name_too(tmp_path, capsys):
    """--scenarios took only the file's stem, not the name inside it, which is what its cells are called."""
    write_gathering(tmp_path / "my-file.yaml", "friday-demo", time_limit_s=1)
    study = write(tmp_path / "s.yaml", "scenarios: [my-file.yaml, lab-6]\nreps: 1\n")
    for name in ("friday-demo", "my-file"):
        assert main(["study", str(study), "--scenarios", name, "--dry-run", "--out", str(tmp_path / "o")]) == 0
        out = capsys.readouterr().out
        assert "friday-demo" in out and "lab-6" not in out.replace(str(tmp_path), "")


def test_scenarios_picks_a_scenario_file_by_its_path_as_typed(tmp_path, capsys, monkeypatch):
    """docs/study.md: a scenario file by "its path"; only the absolute path the study resolved it to worked."""
    (tmp_path / "sub").mkdir()
    write_gathering(tmp_path / "sub" / "my-file.yaml", "friday-demo", time_limit_s=1)
    study = write(tmp_path / "sub" / "s.yaml", "scenarios: [my-file.yaml, lab-6]\nreps: 1\n")
    monkeypatch.chdir(tmp_path)
    # The file name as the study file lists it was refused from another folder (it resolved against this one).
    for path in ("sub/my-file.yaml", "./sub/my-file.yaml", str(tmp_path / "sub" / "my-file.yaml"), "my-file.yaml"):
        assert main(["study", str(study), "--scenarios", path, "--dry-run", "--out", str(tmp_path / "o")]) == 0, path
        out = capsys.readouterr().out
        assert "friday-demo" in out and "lab-6" not in out.replace(str(tmp_path), "")
    assert main(["study", str(study), "--scenarios", "other/my-file.yaml", "--dry-run"]) == 2
    said = capsys.readouterr().err
    assert "not in the study: other/my-file.yaml (the study has: my-file, lab-6, friday-demo, my-file.yaml)" in said


def test_the_report_of_another_behaviour_says_how_its_runs_ended(tmp_path):
    """A study of a behaviour without caging got empty transport tables and nothing about its runs."""
    write_gathering(tmp_path / "gather.yaml", "gather", time_limit_s=2)
    study = write(tmp_path / "s.yaml", "scenarios: [gather.yaml]\nreps: 2\n")
    assert main(["study", str(study), "--out", str(tmp_path / "out"), "--workers", "1", "--no-figures"]) == 0
    report = (tmp_path / "out" / "report.md").read_text()
    assert "## Outcome per cell (other behaviours)" in report
    assert "| gather | 6 | 2 | 0 | time limit 2 | – | 2 [2–2] |" in report
    assert "caged" not in report and "## Errors per waypoint" not in report


def test_reps_on_the_command_line_gives_a_study_file_its_seeds(tmp_path, capsys):
    study = write(tmp_path / "no-seeds.yaml", "scenarios: [lab-6]\ntime_limit_s: 1\n")
    assert main(["study", str(study), "--reps", "2", "--dry-run", "--out", str(tmp_path / "out")]) == 0
    assert "2 runs, 2 to run" in capsys.readouterr().out
    assert main(["study", str(study), "--dry-run", "--out", str(tmp_path / "out")]) == 2   # neither: say so
    assert "seeds: missing: give seeds" in capsys.readouterr().err


def test_the_study_time_limit_is_what_fault_warnings_and_overrides_go_by(tmp_path):
    """A fault at 70 s of a scenario limited to 60 s, in a study that gives every run 200 s: it fires, and the
    warning that it "never fails" was wrong. A time_limit_s override beside the study's own made cells that
    differed in name only (every run got the study's limit)."""
    scenario = tmp_path / "late-fault.yaml"
    scenario.write_text("robots: {count: 4}\nobject: {shape: box, size: [0.4, 0.4]}\npath: [[1.0, 0, 0]]\n"
                        "time_limit_s: 60\nfaults: [{robot: 1, at_s: 70}]\n")
    runs = expand(parse_study({"scenarios": [str(scenario)], "reps": 1, "time_limit_s": 200}))
    assert not any("never fails" in warning for warning in runs[0].warnings)
    runs = expand(parse_study({"scenarios": [str(scenario)], "reps": 1, "time_limit_s": 65}))
    assert any("70 s is not before the time limit (65 s)" in warning for warning in runs[0].warnings)
    with pytest.raises(ConfigError, match="overrides.time_limit_s: the study's time_limit_s replaces it"):
        parse_study({"scenarios": ["lab-6"], "reps": 1, "time_limit_s": 30, "overrides": {"time_limit_s": [50]}})


def test_a_scenario_file_named_without_yaml_is_found_beside_the_study_wherever_it_runs_from(tmp_path, monkeypatch):
    """`scenarios: [mydisc]` with the file mydisc beside the study: found from the study's folder, but from
    its parent "unknown scenario 'mydisc'"; and a file `lab-6` beside it was an ambiguity error from one
    folder and silently the built-in lab-6 from another."""
    folder = tmp_path / "study"
    folder.mkdir()
    (folder / "mydisc").write_text("robots: {count: 4}\nobject: {shape: circle, radius: 0.2}\npath: [[1, 0, 0]]\n")
    (folder / "s.yaml").write_text("scenarios: [mydisc]\nreps: 1\n")
    monkeypatch.chdir(tmp_path)
    assert [run.scenario for run in expand(load_study_file(folder / "s.yaml"))] == [str((folder / "mydisc").resolve())]
    (folder / "lab-6").write_text((folder / "mydisc").read_text())
    (folder / "t.yaml").write_text("scenarios: [lab-6]\nreps: 1\n")
    with pytest.raises(ConfigError, match=r"scenarios\[0\]: 'lab-6' is both a built-in scenario and a file"):
        load_study_file(folder / "t.yaml")


def test_a_scenario_written_as_a_path_to_no_file_is_no_such_file_as_in_sim_run(tmp_path, monkeypatch):
    """`scenarios: [./lab-6]` was "unknown scenario './lab-6': not a file and not built in", where `sim run ./lab-6`
    says "no such file"; the same words everywhere."""
    monkeypatch.chdir(tmp_path)
    write(tmp_path / "s.yaml", "scenarios: [./lab-6]\nreps: 1\n")
    with pytest.raises(ConfigError) as info:
        load_study_file(tmp_path / "s.yaml")
    assert str(info.value) == (f"{tmp_path / 's.yaml'}: scenarios[0]: scenario: no such file: {tmp_path / 'lab-6'} "
                               "(the built-in scenario is lab-6, without a folder)")


def test_a_scenario_file_written_relative_to_the_current_folder_is_said_to_be_relative_to_the_study(tmp_path,
                                                                                                  monkeypatch, capsys):
    """`scenarios: [study/scen/a.yaml]` run from the study's parent said only "no such file: study/study/scen/a.yaml",
    as if the file were gone."""
    (tmp_path / "study/scen").mkdir(parents=True)
    (tmp_path / "study/scen/a.yaml").write_text("robots: {count: 4}\nobject: {shape: circle, radius: 0.2}\n")
    (tmp_path / "study/s.yaml").write_text("scenarios: [study/scen/a.yaml]\nreps: 1\n")
    monkeypatch.chdir(tmp_path)
    assert main(["study", "study/s.yaml", "--dry-run"]) == 2
    assert capsys.readouterr().err == ("khepri: error: study/s.yaml: scenarios[0]: no such file: "
                                       "study/study/scen/a.yaml (a scenario file is relative to the study file: for "
                                       "study/scen/a.yaml in the current folder, write scen/a.yaml)\n")


def test_a_study_takes_whole_numbers_written_as_floats_as_scenario_files_do():
    spec = parse_study({"scenarios": ["lab-6"], "reps": 2.0})
    assert spec.seeds == [1, 2] and all(type(seed) is int for seed in spec.seeds)
    assert parse_study({"scenarios": ["lab-6"], "seeds": [1.0, 3]}).seeds == [1, 3]
    with pytest.raises(ConfigError, match=r"seeds\[0\]: must be an integer >= 0 \(got 1.5\)"):
        parse_study({"scenarios": ["lab-6"], "seeds": [1.5]})


def test_a_caging_only_run_whose_cage_missed_the_object_is_not_a_success(tmp_path):
    """A cage the ground truth finds closed on one side of the object counts as caged, not as a success."""
    from sim_backend.study.aggregate import success_rate

    for seed, encloses in ((1, True), (2, False), (3, None)):          # None: a result from before the check
        result = {"scenario": "irregular-clover", "seed": seed, "robots": 30, "behaviour": "transport",
                  "failed": False, "stop_reason": "behaviour finished", "caged": True, "time_to_cage_s": 300.0,
                  "cage_size": 18, "study": {"cell": "irregular-clover", "overrides": {}}}
        if encloses is not None:
            result["cage_encloses_object"] = encloses
        (tmp_path / "irregular-clover" / f"seed-{seed}").mkdir(parents=True)
        write(tmp_path / "irregular-clover" / f"seed-{seed}" / "result.json", json.dumps(result))
    (cell,) = load_results(tmp_path).cells
    assert cell.rate(lambda r: bool(r.get("caged"))) == 1.0 and success_rate(cell) == 2 / 3


@pytest.mark.parametrize("overrides", ["{object.mass: [2.0, 3.0], object: [{shape: circle, radius: 0.2}]}",
                                       "{object: [{shape: circle, radius: 0.2}], object.mass: [2.0, 3.0]}"])
def test_a_key_overridden_inside_a_whole_mapping_override_is_refused(tmp_path, capsys, overrides):
    """The whole mapping silently replaced the sub-key: two cells labelled mass 2 and 3 both ran the default."""
    study = write(tmp_path / "s.yaml", TINY_STUDY + f"overrides: {overrides}\n")
    assert main(["study", str(study), "--dry-run"]) == 2
    assert f"khepri: error: {study}: overrides.object.mass: lies inside overrides.object, which replaces all of " \
           "object: one of them would be lost; put mass into each value of overrides.object instead" \
           in capsys.readouterr().err


def test_a_built_in_name_in_a_study_is_the_built_in_whatever_the_current_folder_holds(tmp_path, monkeypatch, capsys):
    """`khepri sim show lab-6 > lab-6` in the current folder made a study elsewhere that lists lab-6 fail with
    "'lab-6' is both a built-in scenario and a file in this folder"; the study's files are beside the study."""
    (tmp_path / "st").mkdir()
    study = write(tmp_path / "st/s.yaml", TINY_STUDY)
    write(tmp_path / "lab-6", "robots: {count: 3}\n")
    monkeypatch.chdir(tmp_path)
    assert main(["study", "st/s.yaml", "--dry-run", "--out", str(tmp_path / "o")]) == 0
    assert [run.scenario_data["robots"]["count"] for run in expand(load_study_file(study))] == [6, 6]


@pytest.mark.parametrize("target, said", [
    ("nothere.yaml", "study: no such file: nothere.yaml"),
    ("sub/nothere", "study: no such file: sub/nothere"),
    ("sub", "study: sub is a folder: give `paper`, a study YAML file, or `report sub` to re-aggregate"),
    ("papr", "study: 'papr' is not `paper`, `report` or a study file (no such file)"),
    ("scen.yaml", "scen.yaml: this is a scenario, not a study: run it with `khepri sim run FILE`"),
    ("list.yaml", "list.yaml: a study file must be a mapping of keys (got list)"),
    ("bad.yaml", "bad.yaml: scenarios[0]: mass.yaml: object.mass: must be > 0 (got -2)"),
])
def test_a_study_target_that_is_not_a_study_file_says_what_it_is(tmp_path, monkeypatch, capsys, target, said):
    (tmp_path / "sub").mkdir()
    write(tmp_path / "scen.yaml", "robots: {count: 4}\nobject: {shape: circle, radius: 0.2}\n")
    write(tmp_path / "list.yaml", "- a\n- b\n")
    write(tmp_path / "mass.yaml", "object: {shape: circle, radius: 0.2, mass: -2}\n")
    write(tmp_path / "bad.yaml", "scenarios: [mass.yaml]\nreps: 1\n")
    monkeypatch.chdir(tmp_path)
    assert main(["study", target, "--dry-run"]) == 2
    assert capsys.readouterr().err.startswith(f"khepri: error: {said}")


def test_a_transport_cell_whose_runs_all_failed_keeps_the_transport_tables(tmp_path):
    """lab-6 runs all stopped by a wall-clock limit were listed under "other behaviours", with `ended by` and
    `time to finish` columns, while summary.csv counted them as transport cells (time to cage, n = 0)."""
    study = write(tmp_path / "s.yaml", "scenarios: [lab-6]\nreps: 1\ntime_limit_s: 30\n")
    main(["study", str(study), "--out", str(tmp_path / "out"), "--workers", "1", "--no-figures",
          "--wall-limit", "0.01"])
    report = (tmp_path / "out" / "report.md").read_text()
    assert "(other behaviours)" not in report and "## Outcome per cell" in report
    assert "| lab-6 |" in report.split("## Outcome per cell")[1]


def test_a_repeated_scenario_or_seed_is_named_and_a_null_override_reads_null():
    with pytest.raises(ConfigError) as info:
        parse_study({"scenarios": ["lab-6", "irregular-clover", "lab-6"], "reps": 1})
    assert str(info.value) == "scenarios: lists a scenario twice: lab-6"
    with pytest.raises(ConfigError) as info:
        parse_study({"scenarios": ["lab-6"], "seeds": [1, 2, 2, 3, 3]})
    assert str(info.value) == "seeds: lists seed 2, 3 twice"
    from sim_backend.study.aggregate import overrides_text
    from sim_backend.study.grid import cell_name

    # `params: [null]` made the folder lab-6@params=None and summary.csv's overrides `params=None`.
    assert cell_name("lab-6", {"params": None, "params.head_start": True}) == "lab-6@params=null@params.head_start=True"
    assert overrides_text({"params": None}) == "params=null"


def test_a_dry_run_into_a_file_is_refused_as_the_run_would_be(tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    study = write(tmp_path / "s.yaml", "scenarios: [lab-6]\nreps: 1\n")
    assert main(["study", str(study), "--dry-run", "--out", str(tmp_path / "afile")]) == 2
    assert f"--out: {tmp_path / 'afile'} is a file, not a folder" in capsys.readouterr().err


def test_the_report_says_seeds_and_code_keeps_the_papers_unreached_waypoints_and_tells_run_warnings_apart(
        known_study):
    """An audit of the committed report: it never said which seeds or code ran; waypoints no run reached lost
    the paper's numbers beside them (rows 2-9 went missing); and a slow step() on a busy machine was listed
    as what the simulator said before the runs would doom them."""
    seed1 = known_study / "paper-25-straight/seed-1/result.json"
    result = json.loads(seed1.read_text())
    result["warnings"] = ["robot 3's step() took 0.52 s of wall time at t = 195.9 s (said once a run): ...",
                          "object.mass: a cage of about 6 ..."]
    seed1.write_text(json.dumps(result))
    write_study_outputs(known_study, figures=False)
    report = (known_study / "report.md").read_text()
    assert "Seeds: 1-4 (1 cell), 1, 2 (1 cell). Behaviour code: " in report, report
    table = report.split("### paper-25-straight")[1].split("###")[0]
    rows = [line for line in table.split("\n\n")[1].splitlines() if line[2:3].isdigit()]
    assert [row.split(" | ")[0] for row in rows] == [f"| {k}" for k in range(10)]     # the paper's 10 waypoints
    assert rows[5].startswith("| 5 | 0 | – | ") and rows[5].split(" | ")[3] != "–"    # ours empty, the paper's not
    warnings = report.split("## Warnings")[1].split("\n## ")[0]
    before, during = warnings.split("Said during some runs")
    assert "object.mass: a cage of about 6" in before and "wall time" not in before
    assert "- `paper-25-straight` (seed 1): robot 3's step() took 0.52 s of wall time" in during


def test_a_control_character_in_a_scenario_or_an_overlong_study_name_is_named():
    """A NUL in `scenarios` ended `study --dry-run` in a traceback ("embedded null byte"), and a 300-character
    name passed the dry run and failed the real one, blamed on --out."""
    with pytest.raises(ConfigError) as info:
        parse_study({"scenarios": ["lab-6", "a\x00.yaml"], "reps": 1})
    assert str(info.value) == "scenarios[1]: holds a control character (got 'a\\x00.yaml')"
    with pytest.raises(ConfigError) as info:
        parse_study({"name": "n" * 300, "scenarios": ["lab-6"], "reps": 1})
    assert str(info.value) == "name: names the study's folders: at most 100 characters (got 300)"
