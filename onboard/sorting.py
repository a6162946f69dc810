"""Sorting names the way people read them: numbers inside by value (robot 2 before robot 10)."""
from __future__ import annotations

import re


def natural_key(text: str) -> tuple:
    """Text with its numbers compared as numbers: [(0, 'lab-'), (1, 6.0), ...]."""
    parts = re.split(r"(\d+(?:\.\d+)?)", text)
    return tuple((1, float(part)) if i % 2 else (0, part) for i, part in enumerate(parts) if part)
