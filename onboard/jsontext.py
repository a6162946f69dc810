"""JSON from outside the process (a robot's message, a recorded log, a results file), read without a crash.

json.loads raises RecursionError, not ValueError, for JSON nested past Python's recursion limit (valid JSON,
some thousand lists inside one another): a RuntimeError, which every reader that catches ValueError for bad
JSON let through, as a traceback or a dead thread. Readers of such JSON call :func:`parse_json` instead.
"""
from __future__ import annotations

import json
from typing import Any, Union

#: What is said of lists or mappings nested too deeply to read (JSON here, YAML in ``yamlfile``).
NESTED_TOO_DEEPLY = "lists or mappings nested too deeply to read: hundreds of levels, one inside another"


def parse_json(text: Union[str, bytes, bytearray], **options: Any) -> Any:
    """``json.loads(text, **options)``, but JSON nested past Python's recursion limit raises ValueError, as any
    unreadable JSON does (UnicodeDecodeError and json.JSONDecodeError are ValueErrors too)."""
    try:
        return json.loads(text, **options)
    except RecursionError:
        raise ValueError(NESTED_TOO_DEEPLY) from None


def dump_json(value: Any, **options: Any) -> str:
    """``json.dumps(value, **options)``, but a value nested past what the encoder can recurse raises ValueError
    (:data:`NESTED_TOO_DEEPLY`), as for TypeError's unencodable values. json can parse values that it cannot
    print back: on Python 3.12 its encoder's limit is lower than its parser's."""
    try:
        return json.dumps(value, **options)
    except RecursionError:
        raise ValueError(NESTED_TOO_DEEPLY) from None
