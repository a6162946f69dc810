"""What a radio message may carry, checked the same way by every backend.

A payload crosses the wire as JSON, so receivers get dicts with string keys, lists, strings, finite numbers,
booleans and None. ``plain_payload`` makes that copy on the sender's side and says which field is wrong
when something would not arrive as sent: a set, an object, NaN, or a number as a dict key (JSON would turn
``{3: x}`` into ``{"3": x}`` and the receiver's ``payload[3]`` would fail far from the cause). numpy
numbers and arrays are taken as the Python values they hold, as telemetry takes them.
"""
from __future__ import annotations

import math
from typing import Any, Dict, Mapping


class RadioPayloadError(ValueError):
    """A payload that JSON cannot carry as sent; the message names the field (``payload["pos"][1]``)."""


def plain_payload(payload: Any) -> Dict[str, Any]:
    """A fresh copy of ``payload`` made of plain JSON values, or RadioPayloadError naming the first bad field
    (TypeError if it is not a mapping at all)."""
    if not isinstance(payload, Mapping):
        raise TypeError(f"radio payload must be a mapping (a dict), got {type(payload).__name__}")
    try:
        return _plain_mapping(payload, "payload")
    except RecursionError:      # the walk below is recursive; so is every JSON encoder and decoder on the way
        raise RadioPayloadError("radio payload nests lists or mappings hundreds of levels deep, which the wire "
                                "cannot carry") from None


def _plain_mapping(mapping: Mapping, where: str) -> Dict[str, Any]:
    copy = {}
    for key, value in mapping.items():
        if not isinstance(key, str):
            raise RadioPayloadError(f"radio {where} has the key {key!r} ({type(key).__name__}); JSON keys are "
                                    f"strings, so send str({key!r}) and look it up as a string")
        copy[key] = _plain(value, f"{where}[{key!r}]")
    return copy


def _plain(value: Any, where: str) -> Any:
    if value is None or isinstance(value, bool):
        return value
    if isinstance(value, (str, int)):
        return value if type(value) in (str, int) else (str if isinstance(value, str) else int)(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise RadioPayloadError(f"radio {where} is {value}, which JSON cannot carry; send None or leave it out")
        return float(value)
    if isinstance(value, Mapping):
        return _plain_mapping(value, where)
    if isinstance(value, (list, tuple)):
        return [_plain(item, f"{where}[{index}]") for index, item in enumerate(value)]
    if hasattr(value, "tolist") and hasattr(value, "dtype"):     # numpy, without importing it here
        return _plain(value.tolist(), where)
    raise RadioPayloadError(f"radio {where} is {a_kind(value)}, which JSON cannot carry; send dicts "
                            f"with string keys, lists, strings, numbers, booleans or None")


def a_kind(value: Any) -> str:
    """``value``'s type with its article, for messages: "an object", "a set"."""
    kind = type(value).__name__
    return f"an {kind}" if kind[:1].lower() in "aeiou" else f"a {kind}"
