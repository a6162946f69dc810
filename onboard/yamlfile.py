"""Reading the YAML files users write (scenarios, studies, lab configs, calibrations), one way everywhere.

PyYAML implements YAML 1.1, whose number rules surprise people: ``1e6`` is a string (1.1 wants ``1.0e+6``),
``010`` is 8 (octal) and ``1:30`` is 90. The loader here reads numbers as YAML 1.2 does (``1e6`` is a float,
``010`` is 10, ``0o10`` is 8), and a key written twice in one mapping is an error naming its line instead
of the last one silently winning. A value that is valid YAML but cannot be read (``!!int "abc"``, a date 2024-02-30,
an integer of 5000 digits) and aliases that expand to millions of values (an alias bomb) are refused at their
line too. Every problem is a :class:`ConfigError` naming the file (and the line).
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

from .config import ConfigError, as_written
from .jsontext import NESTED_TOO_DEEPLY

_INT = "tag:yaml.org,2002:int"
_FLOAT = "tag:yaml.org,2002:float"
_TAG_WORDS = {_INT: "an integer", _FLOAT: "a number", "tag:yaml.org,2002:bool": "true or false",
              "tag:yaml.org,2002:timestamp": "a date", "tag:yaml.org,2002:binary": "base64 data"}
# Python's own default bound on int("..."), here on every version (3.9 has none): no khepri number needs more, and
# beyond it int() raised a ValueError that escaped as a traceback ("Exceeds the limit (4300 digits)").
MAX_INT_DIGITS = 4300
# Values a file may expand to through its aliases. The largest real files (a polygon of 6000 vertices) hold some
# tens of thousands; nine levels of nine aliases hold 387 million, and whatever walked them (an error message,
# a study's cell name) ran for minutes and filled the memory.
MAX_VALUES = 1_000_000


class Unreadable(yaml.constructor.ConstructorError):
    """Valid YAML that the loader refuses (a value its tag cannot read, an alias bomb): said as it is, without
    "not valid YAML"."""


class StrictLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` with YAML 1.2 numbers and no duplicate keys."""

    def construct_mapping(self, node, deep=False):
        seen = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue                       # `<<: *defaults` may be overridden by the keys after it
            key = self.construct_object(key_node, deep=deep)
            try:
                first = seen.setdefault(key, key_node)
            except TypeError:                  # an unhashable key: the constructor below says so
                continue
            if first is not key_node:
                raise yaml.constructor.ConstructorError(
                    None, None, f"the key {as_written(key)} is given twice (first on line {first.start_mark.line + 1})",
                    key_node.start_mark)
        return super().construct_mapping(node, deep=deep)

    def construct_document(self, node):
        _check_expansion(node, {}, set())
        # Deep: each list and mapping is filled within its own construct_object, so an error in it is caught
        # there with its line (filled later, `!!set [1]` raised a bare TypeError).
        self.deep_construct = True
        return super().construct_document(node)

    def construct_object(self, node, deep=False):
        # A scalar its tag cannot read (!!int "abc", !!bool "maybe", 2024-02-30) raised the converter's own
        # ValueError (or KeyError), a traceback naming no file; said here, where the node's line is known.
        try:
            return super().construct_object(node, deep=deep)
        except (ArithmeticError, AttributeError, LookupError, TypeError, ValueError) as err:
            raise Unreadable(None, None, _cannot_read(node, err), node.start_mark) from None

    def construct_yaml_int(self, node):
        text = self.construct_scalar(node)
        sign = -1 if text.startswith("-") else 1
        digits = text.lstrip("+-")
        if len(digits) > MAX_INT_DIGITS:
            raise Unreadable(None, None, f"an integer written with {len(digits)} characters is too long to read "
                                         f"(at most {MAX_INT_DIGITS} digits)", node.start_mark)
        if digits.startswith("0o"):
            return sign * int(digits[2:], 8)
        if digits.startswith("0x"):
            return sign * int(digits[2:], 16)
        return sign * int(digits, 10)


def _cannot_read(node: yaml.Node, err: Exception) -> str:
    what = _TAG_WORDS.get(node.tag, node.tag.replace("tag:yaml.org,2002:", "!!"))
    value = as_written(node.value) if isinstance(node, yaml.ScalarNode) else \
        "a list" if isinstance(node, yaml.SequenceNode) else "a mapping"
    if node.tag == "tag:yaml.org,2002:timestamp":      # 2024-02-30: say why, and how to keep it as text
        why = f" ({err})" if isinstance(err, ValueError) else ""
        return f"cannot read {value} as a date{why}; put it in quotes if it is not one"
    return f"cannot read {value} as {what}"


def _check_expansion(node: yaml.Node, sizes: dict, inside: set) -> int:
    """How many values ``node`` holds with its aliases expanded, each shared node counted once per use but
    visited once; refuses a node that holds itself (an alias to a list it is in: no khepri file needs one, and
    code that walks it never ends) and a document larger than MAX_VALUES."""
    key = id(node)
    if key in sizes:
        return sizes[key]
    if isinstance(node, yaml.ScalarNode):
        return 1
    if key in inside:
        raise Unreadable(None, None, "an alias refers to a list or mapping that holds it (a loop)", node.start_mark)
    inside.add(key)
    children = node.value if isinstance(node, yaml.SequenceNode) else [part for pair in node.value for part in pair]
    total = 1 + sum(_check_expansion(child, sizes, inside) for child in children)
    if total > MAX_VALUES:
        kind = "list" if isinstance(node, yaml.SequenceNode) else "mapping"
        raise Unreadable(None, None, f"this {kind} expands through its aliases to more than {MAX_VALUES:,} values "
                                     "(an alias bomb?)", node.start_mark)
    inside.discard(key)
    sizes[key] = total
    return total


StrictLoader.yaml_implicit_resolvers = {
    first: [(tag, pattern) for tag, pattern in resolvers if tag not in (_INT, _FLOAT)]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()}
# YAML 1.2's core schema; ints are tried first, so `10` stays an int.
StrictLoader.add_implicit_resolver(_INT, re.compile(r"^(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)$"),
                                   list("-+0123456789"))
StrictLoader.add_implicit_resolver(
    _FLOAT, re.compile(r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?"
                       r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"),
    list("-+0123456789."))
StrictLoader.add_constructor(_INT, StrictLoader.construct_yaml_int)


class StrictDumper(yaml.SafeDumper):
    """Writes what :class:`StrictLoader` reads back the same: a string that it would read as a number (``'1e3'``,
    ``'0o10'``) is quoted. ``yaml.safe_dump`` quotes by YAML 1.1's rules and left ``name: 1e3`` bare, which
    came back as the number 1000.0."""


StrictDumper.yaml_implicit_resolvers = StrictLoader.yaml_implicit_resolvers


def dump_yaml(data: Any) -> str:
    """``data`` as YAML text that :func:`parse_yaml` reads back equal, keys in their order."""
    return yaml.dump(data, Dumper=StrictDumper, sort_keys=False)


def parse_yaml(text: str, where: str) -> Any:
    """``text`` as YAML; a syntax error or a repeated key is a ConfigError at ``where:LINE``."""
    try:
        return yaml.load(text, Loader=StrictLoader)     # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        at = f"{where}:{mark.line + 1}" if mark else where
        problem = getattr(err, "problem", None) or err
        raise ConfigError(at, problem if isinstance(err, Unreadable) else f"not valid YAML ({problem})") from None
    except RecursionError:
        # PyYAML reads each level of lists or mappings with a few nested calls: a file nested some hundreds
        # deep (valid YAML or JSON) exhausts Python's stack, and only "maximum recursion depth exceeded" was said.
        raise ConfigError(where, NESTED_TOO_DEEPLY) from None


def read_yaml(path: Path, field: str = "") -> Any:
    """A YAML file's content. ``field`` names what the path was given as (``--config``, ``scenario``) in the
    errors about the path itself; errors about its content name the file."""
    path = Path(path)
    label = field or str(path)
    if path.is_dir():
        raise ConfigError(label, f"{path} is a folder, not a file")
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(label, f"no such file: {path}") from None
    except OSError as err:
        raise ConfigError(label, f"cannot read {path}: {err.strerror or err}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ConfigError(str(path), "not a text (UTF-8) file") from None
    data = parse_yaml(text, str(path))      # the path as given: cfg/lab.yaml:3, not lab.yaml:3 of which folder?
    if data is None and getattr(yaml.compose(text, Loader=StrictLoader), "value", ""):
        # `null` or `~` alone: not an empty file (which each reader calls empty), and no kind of file takes it.
        raise ConfigError(str(path), "the file holds only null, not a mapping of keys")
    return data


__all__ = ["StrictLoader", "parse_yaml", "read_yaml"]
