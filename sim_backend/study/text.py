"""Wording shared by the study's console lines and report."""
from __future__ import annotations


def counted(n: int, noun: str) -> str:
    """'1 run', '2 runs', '0 runs': a count with its noun (the study's nouns all take an s)."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"
