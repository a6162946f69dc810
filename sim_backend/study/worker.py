"""One study run, as executed in a worker process (local pool or Dask worker).

The worker writes the run's files itself and also returns the result, so a remote worker that cannot see
the driver's output folder still delivers its result: the driver writes result.json when it is missing.
A run never raises: whatever goes wrong becomes a result with ``failed: true`` and the reason in ``error``.
"""
from __future__ import annotations

import hashlib
import os
import secrets
import shutil
import sys
import tempfile
import traceback
from pathlib import Path
from typing import Any, Dict, List, Optional

from onboard.jsontext import parse_json
from onboard.plugins import import_user_modules, user_module_name

from ..metrics import result_text
from ..scenario import Scenario
from .grid import RunSpec, behaviour_code_sha1

RESULT_FILE = "result.json"
TRACEBACK_LINES = 6   # enough to find the failing line without flooding result.json


def execute_run(spec: RunSpec, out_root: str) -> Dict[str, Any]:
    """Run one (scenario, overrides, seed) and write ``<out_root>/<cell>/seed-<n>/``; return its result."""
    try:
        from sim_backend.runner import Simulation
        from sim_backend.scenario import parse_scenario

        import_current_modules(spec.imports, spec.import_dir)
        sim = Simulation(parse_scenario(spec.scenario_data).with_time_limit(spec.time_limit_s), seed=spec.seed)
        result = sim.run(time_limit_s=spec.time_limit_s, wall_limit_s=spec.wall_limit_s)
    except Exception as exc:  # a run that cannot start is recorded as failed with its reason, not lost
        result = failed_result(spec, f"{type(exc).__name__}: {exc}", traceback.format_exc())
        try:
            write_result(result, Path(out_root) / spec.run_dir)
        except OSError:
            pass
        return result
    result = with_study_fields(result, spec, failed="error" in result)
    try:
        write_run_files(sim, result, Path(out_root) / spec.run_dir)
    except OSError:
        pass   # e.g. a remote worker without the shared folder: the driver writes result.json
    return result


#: The user's modules (``--import``) this process imported for a run: file -> sha1 of its bytes then.
_IMPORTED: Dict[str, str] = {}


def import_current_modules(names: List[str], base_dir: Optional[str]) -> None:
    """Import the user's modules as their files are now. A Dask worker serves one study after another: it kept
    the module it imported for the first, so after the user fixed their behaviour the next study on the same
    scheduler ran the old code. A module whose file changed since this process imported it is imported again
    (its @register then replaces the old class: the same name and qualified name); helpers it imports are not."""
    for name in names:
        module = sys.modules.get(user_module_name(name, base_dir))
        path = getattr(module, "__file__", None)
        if module is not None and path in _IMPORTED and _IMPORTED[path] != _file_sha1(path):
            del sys.modules[module.__name__]
            del _IMPORTED[path]
            behaviour_code_sha1.cache_clear()      # it fingerprints the code this process runs
    import_user_modules(names, base_dir)
    for name in names:
        path = getattr(sys.modules.get(user_module_name(name, base_dir)), "__file__", None)
        if path and path not in _IMPORTED:
            _IMPORTED[path] = _file_sha1(path)


def _file_sha1(path: str) -> str:
    try:
        return hashlib.sha1(Path(path).read_bytes()).hexdigest()
    except OSError:
        return ""


def with_study_fields(result: Dict[str, Any], spec: RunSpec, failed: bool) -> Dict[str, Any]:
    result = dict(result)
    result["failed"] = failed
    result["study"] = {"cell": spec.cell, "scenario": spec.scenario, "overrides": spec.overrides,
                       "time_limit_s": spec.time_limit_s, "scenario_sha1": spec.scenario_sha1,
                       "scenario_sha1_full": spec.full_scenario_sha1,
                       "behaviour_sha1": spec.behaviour_sha1}
    return result


def failed_result(spec: RunSpec, reason: str, trace: str = "") -> Dict[str, Any]:
    """The result.json of a run that crashed outside the simulation loop (or whose worker died)."""
    result: Dict[str, Any] = {
        "scenario": str(spec.scenario_data.get("name", spec.scenario)),
        "seed": spec.seed,
        "robots": (spec.scenario_data.get("robots") or {}).get("count"),
        "behaviour": spec.scenario_data.get("behaviour") or Scenario.behaviour,   # the report's tables go by it
        "error": reason,
    }
    if trace:
        result["traceback"] = trace.strip().splitlines()[-TRACEBACK_LINES:]
    return with_study_fields(result, spec, failed=True)


def write_run_files(sim, result: Dict[str, Any], run_dir: Path) -> None:
    """Write the run's files through ``write_run`` in a staging folder, then move them in, result.json last.

    So a result.json that exists is always complete: a run killed half-way leaves no result.json and is
    run again on resume.
    """
    from sim_backend.outputs import write_run

    run_dir.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".staging-", dir=run_dir))
    try:
        files = write_run(sim, result, staging, plot=False)
        for name, path in files.items():
            if name != "result":
                os.replace(path, run_dir / path.name)
        os.replace(files["result"], run_dir / RESULT_FILE)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def write_result(result: Dict[str, Any], run_dir: Path) -> Path:
    """Write result.json atomically (temporary file, then rename), with the permissions of any file written here
    (the umask's): ``tempfile.mkstemp`` makes its files 0600, which kept the rest of a lab from reading them."""
    run_dir.mkdir(parents=True, exist_ok=True)
    target = run_dir / RESULT_FILE
    temporary = run_dir / f".result-{os.getpid()}-{secrets.token_hex(4)}.json"
    handle = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(handle, "w", encoding="utf-8") as stream:
            stream.write(result_text(result))
        os.replace(temporary, target)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    return target


def read_result(run_dir: Path) -> Dict[str, Any]:
    """A run's result.json, or {} when it is missing, unreadable or not a run's result (then the run counts
    as not done): valid JSON is not enough, it must say which run it is and how it ended."""
    try:
        data = parse_json((run_dir / RESULT_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):      # ValueError: not JSON, or nested past Python's limit
        return {}
    return data if is_run_result(data) else {}


def is_run_result(data: Any) -> bool:
    """What every result.json a run writes has: its scenario and seed, and how it ended (``stop_reason``, or
    ``failed`` with its ``error``)."""
    if not isinstance(data, dict) or not isinstance(data.get("scenario"), str):
        return False
    if not isinstance(data.get("seed"), int) or isinstance(data.get("seed"), bool):
        return False
    ended = isinstance(data.get("stop_reason"), str)
    return (ended or (data.get("failed") is True and isinstance(data.get("error"), str))) and has_run_shape(data)


def has_run_shape(data: Dict[str, Any]) -> bool:
    """The records the aggregation reads into have the shape a run writes them in: a hand-edited result.json
    with a list for ``study``, a string for a waypoint's ``index`` or a number for ``warnings`` crashed
    ``khepri study report`` (and the study's own report) with a traceback, rather than being listed as not a
    run's result."""
    study = data.get("study")
    if study is not None:
        if not isinstance(study, dict) or not isinstance(study.get("overrides") or {}, dict):
            return False
        if not all(isinstance(study.get(key), (str, type(None)))
                   for key in ("behaviour_sha1", "scenario_sha1", "scenario_sha1_full")):
            return False
        if not _number_or_none(study.get("time_limit_s")):
            return False
    waypoints = data.get("waypoints")
    if waypoints is not None and not (isinstance(waypoints, list) and all(map(is_waypoint_record, waypoints))):
        return False
    # `"completed": "maybe"` counted as completed, and `"final_position_error_m": "far"` was left out unsaid.
    if any(not isinstance(data.get(key), (bool, type(None))) for key in RESULT_FLAGS):
        return False
    if not all(_number_or_none(data.get(key)) for key in RESULT_NUMBERS):
        return False
    return isinstance(data.get("warnings") or [], list)


RESULT_FLAGS = ("caged", "completed", "cage_encloses_object")
RESULT_NUMBERS = ("robots", "sim_time_s", "wall_time_s", "time_to_cage_s", "time_to_complete_s", "cage_size",
                  "final_position_error_m", "final_orientation_error_rad")
WAYPOINT_NUMBERS = ("reached_s", "position_error_m", "orientation_error_rad", "centroid_estimation_error_m",
                    "yaw_estimation_error_rad", "effective_pushers", "effective_rotators")


def is_waypoint_record(record: Any) -> bool:
    index = record.get("index", 0) if isinstance(record, dict) else None
    return isinstance(index, int) and not isinstance(index, bool) \
        and all(_number_or_none(record.get(key)) for key in WAYPOINT_NUMBERS)


def _number_or_none(value: Any) -> bool:
    return value is None or (isinstance(value, (int, float)) and not isinstance(value, bool))
