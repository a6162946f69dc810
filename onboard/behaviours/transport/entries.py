"""What a tuple-space entry of the transport may hold, checked as it arrives from a peer (``new_space``).

The readers (TaskBoard, Liveness, the phases) take a value's shape on trust: ``float(bid["bid"])``, a
waypoint's three numbers, a branch letter that indexes ``BRANCH_DIRECTION``. One malformed entry from one
peer (another version of the behaviour, a bug, a corrupted relay) therefore raised in every robot that
merged it, and a robot whose step raises stops. The replica now refuses such an entry where it arrives: it
is neither stored nor relayed, and the robot counts it (``refused_entries`` in its telemetry), naming the
sender, the key and what was wrong. Keys of families this module does not know pass unchecked, so a
behaviour that extends the transport can add its own.

The shapes (tasks.py's docstring lists what each entry means):

  task/<tid>                 {"x", "y": finite numbers, "branch": "S"|"L"|"R", "index": int, "pred": int|null,
                              "epoch": int, "cancelled": bool}; <tid> is "S", or the branch and the index
  bid/<tid>/<epoch>          {"robot": int, "bid": finite number}
  owner/<tid>                {"robot": int, "bid": finite number, "epoch": int}
  member/<rid>               {"tid": str, "branch": "S"|"L"|"R", "index": int, "dead": bool (optional)}
  pos/<rid>                  [x, y, normal (finite number or null), [sx, sy] or null]
  closed                     {"pair": [int, int]}
  grow                       {"level": int, 0 .. MAX_GROW_LEVEL}
  path                       [[x, y, yaw_deg], ...], at least one waypoint, finite numbers
  arrive/<k>/<phase>/<rid>   1, with <phase> one of p, r, c
  done                       1

Ids (<rid>, <epoch>, <k>, "robot", "index", "epoch") are whole numbers >= 0 written in ASCII digits (int() of
"²" raised), at most 18 of them in a key (int() of 5000 raised too); a number is an int or a float but not a bool,
and finite.
"""
from __future__ import annotations

import math
from typing import Any, Callable, Dict, Optional

from ...config import is_whole_number

MAX_GROW_LEVEL = 200     # I_d grows 2 % per level: 200 levels is 52 times I_d, far beyond any cage
BRANCHES = ("S", "L", "R")
PHASES = ("p", "r", "c")


def entry_problem(key: str, value: Any) -> Optional[str]:
    """What is wrong with entry ``key`` = ``value`` for the transport, or None when it may be stored."""
    family, _, rest = key.partition("/")
    check = _CHECKS.get(family)
    if check is None:
        return None
    try:
        return check(rest, value)
    except Exception as err:      # a check that trips on an odd value has found it odd
        return f"unreadable value ({type(err).__name__})"


def _task(tid: str, value: Any) -> Optional[str]:
    problem = _fields(value, {"x": _number, "y": _number, "branch": _branch, "index": _whole,
                              "pred": _optional_whole, "epoch": _whole, "cancelled": _bool})
    if problem:
        return problem
    expected = "S" if value["branch"] == "S" else f"{value['branch']}{value['index']}"
    return None if tid == expected else f"task id {tid!r} does not match its branch and index ({expected!r})"


def _bid(rest: str, value: Any) -> Optional[str]:
    tid, _, epoch = rest.rpartition("/")
    if not _task_id(tid) or not _digits(epoch):
        return "the key is not bid/<task>/<epoch>"
    return _fields(value, {"robot": _whole, "bid": _number})


def _owner(tid: str, value: Any) -> Optional[str]:
    if not _task_id(tid):
        return "the key is not owner/<task>"
    return _fields(value, {"robot": _whole, "bid": _number, "epoch": _whole})


def _member(rid: str, value: Any) -> Optional[str]:
    if not _digits(rid):
        return "the key is not member/<robot id>"
    problem = _fields(value, {"tid": _text, "branch": _branch, "index": _whole})
    if problem is None and "dead" in value and not _bool(value["dead"]):
        return "dead must be true or false"
    return problem


def _pos(rid: str, value: Any) -> Optional[str]:
    if not _digits(rid):
        return "the key is not pos/<robot id>"
    if type(value) is not list or len(value) != 4:
        return "must be [x, y, normal, surface]"
    x, y, normal, surface = value
    if not (_number(x) and _number(y)):
        return "x and y must be finite numbers"
    if normal is not None and not _number(normal):
        return "normal must be a finite number or null"
    if surface is not None and not (type(surface) is list and len(surface) == 2 and all(map(_number, surface))):
        return "surface must be [x, y] or null"
    return None


def _closed(rest: str, value: Any) -> Optional[str]:
    pair = value.get("pair") if type(value) is dict else None
    if rest or type(pair) is not list or len(pair) != 2 or not all(map(_whole, pair)):
        return "must be {\"pair\": [robot id, robot id]}"
    return None


def _grow(rest: str, value: Any) -> Optional[str]:
    level = value.get("level") if type(value) is dict else None
    if rest or not _whole(level) or level > MAX_GROW_LEVEL:
        return f"must be {{\"level\": 0 .. {MAX_GROW_LEVEL}}}"
    return None


def _path(rest: str, value: Any) -> Optional[str]:
    if rest or type(value) is not list or not value:
        return "must be a list of waypoints [x, y, yaw_deg]"
    for waypoint in value:
        if type(waypoint) is not list or len(waypoint) != 3 or not all(map(_number, waypoint)):
            return "every waypoint must be [x, y, yaw_deg], finite numbers"
    return None


def _arrive(rest: str, value: Any) -> Optional[str]:
    parts = rest.split("/")
    if len(parts) != 3 or not _digits(parts[0]) or parts[1] not in PHASES or not _digits(parts[2]):
        return "the key is not arrive/<waypoint>/<p|r|c>/<robot id>"
    return None if value == 1 and type(value) is int else "must be 1"


def _done(rest: str, value: Any) -> Optional[str]:
    return None if not rest and value == 1 and type(value) is int else "must be 1"


def _fields(value: Any, checks: Dict[str, Callable[[Any], bool]]) -> Optional[str]:
    if type(value) is not dict:
        return "must be a mapping"
    for name, ok in checks.items():
        if name not in value:
            return f"{name} is missing"
        if not ok(value[name]):
            return f"{name} is not {_MEANING[ok]} (got {_short(value[name])})"
    return None


def _number(v: Any) -> bool:
    return (type(v) is float and math.isfinite(v)) or type(v) is int


def _whole(v: Any) -> bool:
    return type(v) is int and v >= 0


def _optional_whole(v: Any) -> bool:
    return v is None or _whole(v)


def _bool(v: Any) -> bool:
    return type(v) is bool


def _text(v: Any) -> bool:
    return type(v) is str


def _branch(v: Any) -> bool:
    return v in BRANCHES and type(v) is str


def _digits(text: str) -> bool:
    return is_whole_number(text)


def _task_id(tid: str) -> bool:
    return tid == "S" or (tid[:1] in ("L", "R") and _digits(tid[1:]))


def _short(value: Any, limit: int = 40) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


_MEANING = {_number: "a finite number", _whole: "a whole number >= 0", _optional_whole: "a whole number or null",
            _bool: "true or false", _text: "a string", _branch: "S, L or R"}
_CHECKS: Dict[str, Callable[[str, Any], Optional[str]]] = {
    "task": _task, "bid": _bid, "owner": _owner, "member": _member, "pos": _pos, "closed": _closed,
    "grow": _grow, "path": _path, "arrive": _arrive, "done": _done}
