"""What a study runs: scenarios x parameter overrides x seeds, from the paper's grid or a YAML study file.

A run is identified by (scenario, overrides, seed). Scenario and overrides make its *cell* (the folder
``<out>/<cell>/``), the seed its run folder ``seed-<n>/``. Each run carries its full scenario mapping, so
a worker on another machine needs neither the study file nor the scenario file. Reading and checking the
study file (or the paper's grid) into a StudySpec is ``study_file.py``'s.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import inspect
import itertools
import json
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

from onboard.behaviour import get_behaviour
from onboard.config import ConfigError, as_written, to_mapping
from sim_backend.scenario import load_builtin, load_scenario, parse_scenario
from sim_backend.scenario_settings import apply_overrides

# A cell's folder name at most (ASCII, so bytes too): what the usual file systems allow a name. A name that fits
# is kept as it is, so the folders of studies run before this still resume.
MAX_CELL_NAME = 255


@dataclass
class StudySpec:
    """A validated study: every scenario is run with every combination of override values and every seed."""

    name: str
    scenarios: List[str]                       # built-in names or paths to scenario files
    seeds: List[int]
    overrides: Dict[str, List[Any]] = field(default_factory=dict)   # dotted scenario key -> values
    time_limit_s: Optional[float] = None       # replaces every scenario's own limit; None = keep those
    # The cells as a list instead (``overrides:`` a list in the study file): each a mapping of dotted key ->
    # one value, values that must change together (robots.count with object.size). None: the product above.
    override_sets: Optional[List[Dict[str, Any]]] = None

    def cells(self) -> List[Dict[str, Any]]:
        """Each cell's overrides, in order: the listed sets, or every combination of the listed values."""
        if self.override_sets is not None:
            return [dict(chosen) for chosen in self.override_sets]
        return [dict(zip(self.overrides, combo)) for combo in itertools.product(*self.overrides.values())]


@dataclass
class RunSpec:
    """One run, as sent to a worker (plain data, picklable)."""

    cell: str
    scenario: str                      # as named in the study (for people); the worker uses scenario_data
    scenario_data: Dict[str, Any]      # the full scenario mapping with the overrides applied
    seed: int
    overrides: Dict[str, Any] = field(default_factory=dict)
    time_limit_s: Optional[float] = None
    wall_limit_s: Optional[float] = None   # stop the run after this much wall time (a hung behaviour); None: never
    # Modules the driver was started with (``khepri --import``), e.g. a user's behaviour: a worker process
    # imports them too, from import_dir (the driver's working folder) or its own path.
    imports: List[str] = field(default_factory=list)
    import_dir: Optional[str] = None
    warnings: List[str] = field(default_factory=list)   # what the simulator knows will doom this cell's runs

    @property
    def run_dir(self) -> str:
        return f"{self.cell}/seed-{self.seed}"

    @property
    def behaviour_sha1(self) -> str:
        """A fingerprint of the behaviour's code (:func:`behaviour_code_sha1`)."""
        return behaviour_code_sha1(str(self.scenario_data.get("behaviour", "")))

    @property
    def scenario_sha1(self) -> str:
        """A fingerprint of the scenario as run (every default filled in, overrides applied): a resumed study
        can tell a finished run of an edited scenario file from one of the scenario it would run now. Only what
        changes a run counts: not the description, nor the scenario's time_limit_s when the study sets the limit
        (the run records that apart, and a change of it is said apart)."""
        return self.scenario_sha1_as_run(study_limit=self.time_limit_s is not None)

    def scenario_sha1_as_run(self, study_limit: bool) -> str:
        """``scenario_sha1`` as a run with (``study_limit``) or without the study's time limit took it: a run kept
        from a command with another limit is compared the way it was fingerprinted, else its limit alone passed
        for a changed scenario."""
        data = {key: value for key, value in self.scenario_data.items() if key != "description"}
        if study_limit:
            data.pop("time_limit_s", None)
        return _fingerprint(data)

    @property
    def full_scenario_sha1(self) -> str:
        """The fingerprint of every field, description included, which runs recorded as scenario_sha1 before
        2026-11-29 (an edited description then warned that the scenario had changed): a study resumed across
        that change compares old runs with it."""
        return _fingerprint(self.scenario_data)


def _fingerprint(data: Dict[str, Any]) -> str:
    text = json.dumps(data, sort_keys=True, default=str)
    return hashlib.sha1(text.encode("utf-8")).hexdigest()[:16]


@functools.cache
def behaviour_code_sha1(name: str) -> str:
    """A fingerprint of the files that hold behaviour ``name``'s code: its module, and when that module is part
    of a package of its own (the transport behaviour is ``onboard.behaviours.transport``), every module in
    that package's folder. A resumed study can then tell runs of an edited behaviour from runs of the code it
    would run now. Shared helpers elsewhere (``onboard.motion``, ...) are not included. "" when the code
    cannot be found."""
    try:
        module = inspect.getmodule(get_behaviour(name))
        source = Path(inspect.getsourcefile(module) or "")
    except (ConfigError, TypeError, OSError):
        return ""
    own_package = bool(module.__package__) and module.__package__ != "onboard.behaviours"
    files = sorted(source.parent.glob("*.py")) if own_package else [source]
    digest = hashlib.sha1()
    for path in files:
        try:
            digest.update(path.name.encode("utf-8") + b"\0" + path.read_bytes())
        except OSError:
            return ""
    return digest.hexdigest()[:16]


def restrict(spec: StudySpec, names: Sequence[str]) -> StudySpec:
    """Keep only the named scenarios (``--scenarios``), in the study's order. A scenario file can be named by
    its path, its file name with or without ``.yaml`` (``bar.yaml``, as a study file beside it lists it, was
    refused when typed from another folder), or the ``name:`` inside it (what its cells are called)."""
    known = {Path(s).stem if s.endswith((".yaml", ".yml")) else s: s for s in spec.scenarios}
    for ref in spec.scenarios:
        if ref.endswith((".yaml", ".yml")):
            known.setdefault(str(scenario_mapping(ref, "scenarios").get("name")), ref)
            known.setdefault(Path(ref).name, ref)
            known.setdefault(ref, ref)

    def scenario_of(name: str) -> Optional[str]:
        # A file's path as typed on the command line (relative to the current folder), or as resolved.
        if name.endswith((".yaml", ".yml")):
            return known.get(name) or known.get(str(Path(name).resolve()))
        return known.get(name)

    missing = [n for n in names if scenario_of(n) is None]
    if missing:
        raise ConfigError("--scenarios", f"not in the study: {', '.join(missing)} "
                          f"(the study has: {', '.join(k for k in known if not Path(k).is_absolute())})")
    wanted = {scenario_of(n) for n in names}
    return dataclasses.replace(spec, scenarios=[s for s in spec.scenarios if s in wanted])


def expand(spec: StudySpec) -> List[RunSpec]:
    """Every run of the study, cell by cell, seeds in order."""
    runs = []
    for i, scenario_ref in enumerate(spec.scenarios):
        base = scenario_mapping(scenario_ref, f"scenarios[{i}]")
        named: Dict[str, Dict[str, Any]] = {}
        for chosen in spec.cells():
            data = apply_overrides(base, chosen)
            cell = cell_name(str(data["name"]), chosen)
            if cell in named:
                raise ConfigError("overrides", f"{overrides_text(named[cell])} and {overrides_text(chosen)} give "
                                  f"the same folder name {as_written(cell)}: their runs would share it (give values "
                                  f"that differ in their first 6 digits and in letters or digits)")
            named[cell] = chosen
            try:
                warnings = check_cell(data, cell, chosen, spec.seeds[0], spec.time_limit_s)
            except ConfigError as err:
                raise ConfigError(err.field, err.problem + list_value_hint(err.problem, base, spec.overrides)) from None
            runs.extend(RunSpec(cell, scenario_ref, data, seed, chosen, spec.time_limit_s, warnings=list(warnings))
                        for seed in spec.seeds)
    runs_per_cell = Counter(r.cell for r in runs)
    duplicate = next((c for c, count in runs_per_cell.items() if count > len(spec.seeds)), None)
    if duplicate:
        raise ConfigError("scenarios", f"two scenarios share the name {as_written(duplicate.split('@')[0])}: "
                          f"their runs would share a folder")
    return runs


def scenario_mapping(scenario_ref: str, where: str) -> Dict[str, Any]:
    """A scenario as a plain mapping with every default filled in (what ``khepri sim show`` prints)."""
    is_file = Path(scenario_ref).is_absolute()      # the study file made its scenario files absolute
    try:
        return to_mapping(load_scenario(scenario_ref) if is_file else load_builtin(scenario_ref))
    except ConfigError as err:
        which = f"{Path(scenario_ref).name}: " if is_file and scenario_ref not in str(err) else ""   # named yet?
        raise ConfigError(where, which + str(err)) from None


def check_cell(data: Dict[str, Any], cell: str, chosen: Dict[str, Any], seed: int,
               time_limit_s: Optional[float] = None) -> List[str]:
    """Build the cell's simulation once, as its first run would, so that what only the world can find (a spawn
    area too small for the robots, an object across the walls) fails now, not in every run; and return the
    simulator's warnings for the cell."""
    from sim_backend.runner import Simulation

    try:
        return Simulation(parse_scenario(data).with_time_limit(time_limit_s), seed=seed).warnings
    except ConfigError as err:
        where = f"overrides ({cell})" if chosen else "scenarios"
        raise ConfigError(where, str(err) + whole_mapping_hint(err.field, chosen)) from None


def whole_mapping_hint(field_name: str, chosen: Dict[str, Any]) -> str:
    """An override of one field can leave its siblings unfit (``object.shape: circle`` keeps the box's two-number
    ``size``); the cartesian product cannot pair them, but overriding the whole mapping can: say how."""
    overridden = [key for key in chosen if field_name == key or field_name.startswith(key + ".")]
    for key in chosen:
        parent = key.rpartition(".")[0]
        if not parent or key in overridden or not field_name.startswith(parent + "."):
            continue
        pair = f"{{{key.rpartition('.')[2]}: ..., {field_name[len(parent) + 1:].split('.')[0]}: ...}}"
        kept = ("is overridden too, and every value of one is paired with every value of the other" if overridden
                else "is the scenario's own, kept beside the override of " + key)
        return (f"; {field_name} {kept}: to change them together, override {parent} as a whole, e.g. "
                f"{parent}: [{pair}] (see docs/study.md)")
    return ""


def list_value_hint(problem: str, base: Dict[str, Any], listed: Dict[str, List[Any]]) -> str:
    """An override of a key that takes a list lists its values, so ``robots.spawn.x: [-1, 0]`` is two cells, x = -1
    and x = 0, each refused as "must be a list". When the failing key is such an override with a value less deeply
    nested than the scenario's own, say how to give the whole list as one value."""
    failing = problem.partition(": ")[0]       # the field the scenario's check named, e.g. path[0]
    for key, values in listed.items():
        own = nested_value(base, key)
        mentioned = failing == key or failing.startswith((key + "[", key + "."))
        if mentioned and isinstance(own, list) and own and any(depth(value) < depth(own) for value in values):
            whole = json.dumps(values)
            return (f"; each value listed under overrides.{key} is one whole {key} (a cell each), which is a "
                    f"list: to give it {whole} as one value, write {key}: [{whole}]")
    return ""


def nested_value(data: Dict[str, Any], dotted_key: str) -> Any:
    for part in dotted_key.split("."):
        if not isinstance(data, dict):
            return None
        data = data.get(part)
    return data


def depth(value: Any) -> int:
    """How deeply lists nest in ``value``, by their first items: 0 for a number, 1 for [x, y], 2 for [[x, y, th]]."""
    return 1 + depth(value[0]) if isinstance(value, list) and value else int(isinstance(value, list))


def overrides_text(chosen: Dict[str, Any]) -> str:
    return ", ".join(f"{key}={as_written(value)}" for key, value in chosen.items())


def cell_name(scenario_name: str, chosen: Dict[str, Any]) -> str:
    """``scenario`` or ``scenario@key=value@key=value``: readable, and safe as a folder name."""
    parts = [scenario_name] + [f"{key}={value_text(value)}" for key, value in chosen.items()]
    return fit_folder_name("@".join(re.sub(r"[^A-Za-z0-9_.,+=-]", "_", part) for part in parts))


def adopt_reordered_cells(runs: List[RunSpec], out_dir: Path) -> None:
    """Give a run whose cell has no folder in ``out_dir`` yet the folder of the same scenario and overrides written
    in another order, when there is one: a cell is named by its overrides in the order the study file lists them,
    so after moving one key above another every finished run was run again into a second folder, and the report
    showed the one cell twice. (A name cut short by ``fit_folder_name`` cannot be compared, and is left.)"""
    try:
        folders = [path.name for path in out_dir.iterdir() if path.is_dir()] if out_dir.is_dir() else []
    except OSError:
        return
    existing: Dict[Tuple[str, Tuple[str, ...]], str] = {}
    for name in sorted(folders):
        existing.setdefault(_cell_key(name), name)
    for run in runs:
        other = existing.get(_cell_key(run.cell))
        if other is not None and other != run.cell and not (out_dir / run.cell).exists():
            run.cell = other


def _cell_key(name: str) -> Tuple[str, Tuple[str, ...]]:
    """The scenario and the set of ``key=value`` parts of a cell's name (no part holds an ``@``: cell_name)."""
    if "~" in name:
        return name, ()
    scenario, *parts = name.split("@")
    return scenario, tuple(sorted(parts))


def fit_folder_name(name: str) -> str:
    """``name``, or when it is longer than ``MAX_CELL_NAME`` its start, ``~`` and a fingerprint of the whole name:
    a long override (a whole object with a few dozen vertices) named a folder that no run of its cell could
    make ("File name too long"). The cell's overrides stay in full in result.json, summary.csv and report.md."""
    if len(name) <= MAX_CELL_NAME:
        return name
    digest = hashlib.sha1(name.encode("utf-8")).hexdigest()[:12]
    return f"{name[:MAX_CELL_NAME - len(digest) - 1]}~{digest}"


def value_text(value: Any) -> str:
    if isinstance(value, dict):         # an override of a whole mapping: key=value pairs, not a dict's repr
        return ",".join(f"{key}={value_text(item)}" for key, item in value.items())
    if isinstance(value, (list, tuple)):
        return ",".join(value_text(v) for v in value)
    if value is None:
        return "null"      # as the study file says it (was params=None); booleans stay True: folders of old studies
    return format(value, "g") if isinstance(value, float) else str(value)


def grid_table(runs: List[RunSpec]) -> List[Tuple[str, str]]:
    """(cell, seeds) lines for ``--dry-run``."""
    seeds: Dict[str, List[int]] = {}
    for run in runs:
        seeds.setdefault(run.cell, []).append(run.seed)
    return [(cell, seed_text(values)) for cell, values in seeds.items()]


def seed_text(seeds: List[int]) -> str:
    contiguous = seeds == list(range(seeds[0], seeds[0] + len(seeds)))
    return f"{seeds[0]}..{seeds[-1]}" if contiguous and len(seeds) > 2 else ",".join(map(str, seeds))
