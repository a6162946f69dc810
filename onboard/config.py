"""Validated configuration records: YAML/dict -> dataclass, with errors that name the field.

Used for behaviour parameters, scenarios and lab configs alike, so a user sees the same kind of message
everywhere, e.g. ``robots.count: must be >= 1 (got 0)``.
"""
from __future__ import annotations

import dataclasses
import datetime
import math
import os
import types
import typing
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Type, TypeVar

from .tracebacks import describe

T = TypeVar("T")

# `float | None` (Python 3.10 and later): the same as Optional[float] to the reader. A robot's 3.9 has no such type.
_UNION_TYPES = tuple(kind for kind in (typing.Union, getattr(types, "UnionType", None)) if kind is not None)
# What coerce reads, for the line that says a behaviour declared a parameter of another type.
READABLE_TYPES = "bool, int, float, str, Literal, Optional, List, Tuple, Dict or a dataclass"


class ConfigError(ValueError):
    """A configuration value is wrong. ``str(err)`` is one line: ``<field path>: <what is wrong>``."""

    def __init__(self, field: str, problem: str):
        self.field = field
        self.problem = problem
        super().__init__(f"{field}: {problem}" if field else problem)


class UnsupportedType(ConfigError):
    """A field's declared type has no reading rule: the record's (a behaviour's Params') mistake, not the file's;
    from_mapping names the record's field and its type."""


def join(where: str, name: Any) -> str:
    if isinstance(name, int):
        return f"{where}[{name}]"
    return f"{where}.{name}" if where else str(name)


def check_range(where: str, value: float, low: float = -math.inf, high: float = math.inf,
                low_open: bool = False) -> float:
    """Reject values outside [low, high] (or (low, high] with ``low_open``)."""
    if low_open and not value > low:
        raise ConfigError(where, f"must be > {_number(low)} (got {_number(value)})")
    if not low_open and value < low:
        raise ConfigError(where, f"must be >= {_number(low)} (got {_number(value)})")
    if value > high:
        raise ConfigError(where, f"must be <= {_number(high)} (got {_number(value)})")
    return value


#: The largest seed (2**63 - 1). numpy takes any size, but a seed names the output folder (out/lab-6-seed<N>:
#: 300 digits were "File name too long", blamed on --out) and goes to every agent in the run's start message.
MAX_SEED = 2 ** 63 - 1


def check_seed(where: str, value: int) -> int:
    """A seed in 0..MAX_SEED (numpy's generators refuse negative ones); else an error naming ``where``."""
    return check_range(where, value, 0, MAX_SEED)


def folder_not_file(text: str) -> Optional[str]:
    """Why the path ``text``, given for a file to write, names a folder ("X names a folder", "X is a folder"), or
    None. Checked on the text as typed: ``Path`` drops a trailing separator, so ``out.gif/``, a folder that does
    not exist yet, became the file ``out.gif``. An empty text names no file (``Path("")`` is the current folder,
    which read "  is a folder")."""
    if not text:
        return "names no file (got an empty string)"
    if text.endswith(("/", os.sep)):
        return f"{text} names a folder"
    if Path(text).is_dir():
        return f"{text} is a folder"
    return None


MAX_NAME_LENGTH = 100     # a scenario's or study's name, which names folders (file systems allow 255 bytes)


def has_control_character(text: str) -> bool:
    """A NUL, newline, tab or other control character: in a name or path it made a folder named across lines,
    or ended the command in a traceback ("embedded null byte")."""
    return any(ord(char) < 32 or ord(char) == 127 for char in text)


def check_boolean(where: str, value: Any) -> bool:
    """A true or false as it is; anything else refused naming ``where``. Not ``bool(value)``: "yes", "false", "0"
    and 1 would all switch the setting on."""
    if isinstance(value, bool):
        return value
    raise ConfigError(where, f"must be true or false (got {as_written(value)})")


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp).replace("typing.", ""))


def _is_sequence_type(tp: Any) -> bool:
    return typing.get_origin(tp) in (list, tuple) or tp in (list, tuple)


def as_integer(value: Any) -> Optional[int]:
    """An integer as it is, a float without a fraction (3.0) as the integer, anything else (booleans too) None."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return None


def is_whole_number(text: str, max_digits: int = 18) -> bool:
    """Whether ``text`` is a whole number int() reads: ASCII digits only (str.isdigit also takes '²', which int()
    refuses), and at most ``max_digits`` of them (int() refuses more than 4300, and no count or id has 19)."""
    return text.isascii() and text.isdigit() and len(text) <= max_digits


def coerce(value: Any, tp: Any, where: str) -> Any:
    """Convert ``value`` to the annotated type ``tp`` or raise ConfigError naming ``where``."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in _UNION_TYPES:
        if value is None and type(None) in args:
            return None
        options = [a for a in args if a is not type(None)]
        same_kind = [a for a in options if _is_sequence_type(a) == isinstance(value, (list, tuple))]
        if len(same_kind) == 1:           # a list for a list option: its own error (with the item's index)
            options = same_kind
        if len(options) == 1:
            return coerce(value, options[0], where)
        errors = []
        for option in options:
            try:
                return coerce(value, option, where)
            except ConfigError as err:
                errors.append(err.problem)
        raise ConfigError(where, " or ".join(dict.fromkeys(errors)))
    if origin is typing.Literal:
        return _literal(value, args, where)
    if dataclasses.is_dataclass(tp):
        return from_mapping(tp, value, where)
    if tp is bool:
        return check_boolean(where, value)
    if tp is int:
        number = as_integer(value)
        if number is None:
            raise ConfigError(where, f"must be an integer (got {as_written(value)})")
        return number
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(where, f"must be a number (got {as_written(value)})")
        if not math.isfinite(value):
            raise ConfigError(where, f"must be a finite number (got {as_written(value)})")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(where, f"must be a string (got {as_written(value)})")
        return value
    if origin in (list, tuple) or tp in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(where, f"must be a list (got {as_written(value)})")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ConfigError(where, f"must have {len(args)} items (got {len(value)})")
            return tuple(coerce(v, a, join(where, i)) for i, (v, a) in enumerate(zip(value, args)))
        item_type = args[0] if args else Any
        items = [coerce(v, item_type, join(where, i)) for i, v in enumerate(value)]
        return tuple(items) if (origin is tuple or tp is tuple) else items
    if origin is dict or tp is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(where, f"must be a mapping (got {as_written(value)})")
        if len(args) == 2:         # Dict[str, float]: every value checked, as a field of that type would be
            return {key: coerce(item, args[1], join(where, key)) for key, item in value.items()}
        return dict(value)
    raise UnsupportedType(where, f"unsupported type {_type_name(tp)}")


def _literal(value: Any, allowed: Any, where: str) -> Any:
    """One of a ``Literal[...]``'s values, as a scenario writes it: 3.0 for 3, but true is not 1."""
    for option in allowed:
        if isinstance(option, bool) or option is None or isinstance(option, str):
            if type(value) is type(option) and value == option:
                return option
        elif isinstance(option, int):
            if as_integer(value) == option:
                return option
        elif isinstance(option, float):
            if not isinstance(value, bool) and isinstance(value, (int, float)) and value == option:
                return option
    shown = ", ".join(as_written(option) for option in allowed)
    raise ConfigError(where, f"must be one of {shown} (got {as_written(value)})")


SHOWN_CHARS = 60     # of a value in an error line: enough to recognise it, and never a whole file in one line


def as_written(value: Any) -> str:
    """A value for an error line, at most about SHOWN_CHARS long; true, false and null as YAML writes them. YAML
    reads an unquoted 2024-01-01 as a date, and its repr ``datetime.date(2024, 1, 1)`` hid that a pair of quotes
    is all it needs. A long list says its length and its start: the whole repr of a YAML alias bomb (nine levels
    of nine aliases) ran for minutes and ended in MemoryError, so the value is rendered only as far as is shown."""
    if isinstance(value, (datetime.date, datetime.datetime)):
        return f"{value.isoformat()}, which YAML reads as a date: put it in quotes"
    if value is None or isinstance(value, bool):     # as the file says it: true, not Python's True
        return {None: "null", True: "true", False: "false"}[value]
    parts: List[str] = []
    _render(value, parts, [SHOWN_CHARS + 1])
    text = "".join(parts)
    if len(text) <= SHOWN_CHARS:
        return text
    kind = "mapping" if isinstance(value, Mapping) else "list" if isinstance(value, (list, tuple)) else None
    size = f"a {kind} of {len(value)} item{'' if len(value) == 1 else 's'}: " if kind else ""
    return f"{size}{text[:SHOWN_CHARS]}..."


_BRACKETS = ((list, "[]"), (tuple, "()"), (Mapping, "{}"), ((set, frozenset), "{}"))


def _render(value: Any, parts: List[str], left: List[int]) -> None:
    """Append the repr of ``value`` to ``parts`` until ``left[0]`` characters are spent, then stop: the cost is
    that of the characters shown, however large (or self-referring) the value is."""
    brackets = next((pair for kind, pair in _BRACKETS if isinstance(value, kind)), None)
    if brackets is None:
        text = _scalar_text(value, left[0])
        parts.append(text)
        left[0] -= len(text)
        return
    parts.append(brackets[0])
    left[0] -= 1
    for i, item in enumerate(value.items() if isinstance(value, Mapping) else value):
        if left[0] <= 0:
            return
        if i:
            parts.append(", ")
            left[0] -= 2
        if isinstance(value, Mapping):
            _render(item[0], parts, left)
            parts.append(": ")
            left[0] -= 2
            item = item[1]
        if left[0] > 0:
            _render(item, parts, left)
    parts.append(brackets[1])
    left[0] -= 1


def _scalar_text(value: Any, room: int) -> str:
    """The repr of one value that is not a list or mapping, cut near ``room`` characters before it is built."""
    if isinstance(value, (str, bytes)):
        return repr(value[:room + 1])
    if isinstance(value, int) and not isinstance(value, bool):
        return _number(value)
    return repr(value)[:room + 1]


def _number(value: float) -> str:
    """An integer as written (100000000000, not 1e+11), or its length if it is too long to show (Python refuses
    to write an integer of more than 4300 digits); a float in its shortest form."""
    if not isinstance(value, int):
        return f"{value:g}"
    if -10 ** SHOWN_CHARS < value < 10 ** SHOWN_CHARS:
        return str(value)
    return f"an integer of {int(math.log10(abs(value))) + 1} digits"


def _takes_none(hint: Any) -> bool:
    return typing.get_origin(hint) in _UNION_TYPES and type(None) in typing.get_args(hint)


def from_mapping(cls: Type[T], data: Any, where: str = "") -> T:
    """Build dataclass ``cls`` from a mapping; reject unknown keys and missing required ones.

    After construction, the dataclass's own ``validate(where)`` method (if any) checks values.
    """
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise ConfigError(where, f"must be a mapping (got {as_written(data)})")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    not_names = [k for k in data if not isinstance(k, str)]
    if not_names:
        raise _key_not_a_name(where, not_names[0], sorted(fields))
    unknown = [k for k in data if k not in fields]
    if unknown:
        known = ", ".join(sorted(fields))
        key = unknown[0] if len(unknown[0]) <= SHOWN_CHARS else unknown[0][:SHOWN_CHARS] + "..."   # a pasted text
        raise ConfigError(join(where, key), f"unknown key (known: {known})")
    kwargs: Dict[str, Any] = {}
    for name, f in fields.items():
        if name in data and data[name] is None and f.default_factory is not dataclasses.MISSING \
                and not _takes_none(hints[name]):
            continue    # `params:` with every line under it commented out: empty, as `comm:` already was
        if name in data:
            try:
                kwargs[name] = coerce(data[name], hints[name], join(where, name))
            except UnsupportedType:
                raise ConfigError(join(where, name), f"{cls.__name__}.{name} is declared as "
                                  f"{_type_name(hints[name])}, a type a scenario cannot give (use "
                                  f"{READABLE_TYPES})") from None
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(join(where, name), "is required")
    obj = cls(**kwargs)
    validate = getattr(obj, "validate", None)
    if callable(validate):
        try:
            validate(where)
        except ConfigError:
            raise
        except ValueError as err:      # a user's Params.validate raising a plain ValueError: name the record
            raise _validate_error(where, str(err)) from None
        except Exception as err:       # a bug in a user's validate: one line with its place, not a traceback
            raise ConfigError(where or cls.__name__, f"{cls.__name__}.validate raised {describe(err)}") from None
    return obj


def _key_not_a_name(where: str, key: Any, known: List[str]) -> ConfigError:
    """YAML reads a key like ``1:``, ``true:``, ``on:`` or ``null:`` as a number, a boolean or None, whose path
    read ``[1]``, ``object[True]`` or ``robots.None``: say what it was read as, where."""
    if isinstance(key, bool):
        spelled, read_as = str(key).lower(), "a boolean (YAML reads true, false, yes, no, on and off so)"
    elif key is None:
        spelled, read_as = "null", "null (YAML reads null, ~ and an empty key so)"
    elif isinstance(key, (int, float)):
        spelled, read_as = str(key), "a number"
    else:
        spelled, read_as = str(key), f"a {type(key).__name__}"
    place = "key" if where else "top-level key"
    return ConfigError(where, f"{place} {spelled} is {read_as}, not a name: keys must be names (known: "
                              f"{', '.join(known)}); quote it (\"{spelled}\") to make it a name")


def _validate_error(where: str, message: str) -> ConfigError:
    """A plain ValueError's message from ``validate(where)`` under the record's path, unless it names a field
    of the record itself (``params.speed_m_s: must be > 0``, made with the ``where`` it was given), which was
    printed as ``params: params.speed_m_s: ...``."""
    field, colon, problem = message.partition(": ")
    if where and colon and (field == where or field.startswith((f"{where}.", f"{where}["))):
        return ConfigError(field, problem)
    return ConfigError(where, message)


def to_mapping(obj: Any) -> Any:
    """The inverse of :func:`from_mapping`, for writing configs back (tuples become lists)."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_mapping(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [to_mapping(v) for v in obj]
    if isinstance(obj, dict):
        return {k: to_mapping(v) for k, v in obj.items()}
    return obj
