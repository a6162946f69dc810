"""Wording shared by the study's console lines and report."""
from __future__ import annotations


def counted(n: int, noun: str) -> str:
    """'1 run', '2 runs', '0 runs': a count with its noun (the study's nouns all take an s)."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def are(n: int) -> str:
    """The verb that goes with ``counted(n, ...)``: '1 run is', '2 runs are'."""
    return "is" if n == 1 else "are"


def them(n: int) -> str:
    return "it" if n == 1 else "them"


def first_few(names, shown: int = 5) -> str:
    """'a, b, c' or, past ``shown`` names, 'a, b, c, d, e ...': the runs or cells a warning is about."""
    names = list(names)
    return ", ".join(names[:shown]) + (" ..." if len(names) > shown else "")
