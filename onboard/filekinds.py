"""Which kind of khepri file a mapping looks like, to say so when one is given where another is expected.

khepri reads four kinds of YAML file: scenarios, studies, lab configs and IR calibrations. Given the wrong one
(``khepri sim run study.yaml``, ``khepri hub --config scenario.yaml``), each loader said only that the first
key was unknown (``scenarios: unknown key (known: arena, ...)``), naming neither the file nor the mistake. The
top-level keys of each kind are listed here rather than taken from the records, as the calibration loader runs
on robots, which have neither the simulator nor the hub (tests/test_file_kinds.py checks the lists against them).
"""
from __future__ import annotations

from typing import Any, Dict, Mapping, Optional, Tuple

SCENARIO = "scenario"
STUDY = "study"
LAB_CONFIG = "lab config"
CALIBRATION = "calibration file"

#: kind -> (its top-level keys, what to do with such a file)
KINDS: Dict[str, Tuple[frozenset, str]] = {
    SCENARIO: (frozenset({"name", "behaviour", "description", "seed", "robots", "object", "path", "params",
                          "time_limit_s", "comm", "sensors", "physics", "arena", "faults"}),
               "run it with `khepri sim run FILE` or `khepri sil FILE`, or name it in a study's scenarios or a lab "
               "config's source.scenario (docs/scenarios.md)"),
    STUDY: (frozenset({"name", "scenarios", "seeds", "reps", "overrides", "time_limit_s"}),
            "run it with `khepri study FILE` (docs/study.md)"),
    LAB_CONFIG: (frozenset({"source", "robots", "network", "security", "sensing", "relay", "run", "geofence",
                            "watchdog_s", "record"}),
                 "start a hub with it: `khepri hub --config FILE` (docs/lab.md)"),
    CALIBRATION: (frozenset({"proximity", "robot", "notes"}),
                  "an agent reads it: `khepri agent --driver kh4 --calibration FILE` (docs/driver.md)"),
}


def wrong_kind(data: Any, expected: str) -> Optional[str]:
    """"this is a study, not a scenario: run it with ..." when ``data`` has a key the ``expected`` kind does not
    know and more of its keys are another kind's than the expected kind's; else None. Counting every key a kind
    knows (``robots`` is a scenario's and a lab config's) keeps one stray key from renaming a file."""
    if not isinstance(data, Mapping):
        return None
    keys = {key for key in data if isinstance(key, str)}
    known = KINDS[expected][0]
    if keys <= known:
        return None
    counts = {kind: len(keys & kind_keys) for kind, (kind_keys, _) in KINDS.items()}
    best = max(counts[kind] for kind in KINDS if kind != expected)
    likely = [kind for kind in KINDS if kind != expected and counts[kind] == best]
    if best <= counts[expected] or len(likely) != 1:
        return None
    kind = likely[0]
    return f"this is a {kind}, not a {expected}: {KINDS[kind][1]}"


__all__ = ["SCENARIO", "STUDY", "LAB_CONFIG", "CALIBRATION", "KINDS", "wrong_kind"]
