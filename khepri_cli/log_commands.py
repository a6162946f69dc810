"""``khepri log info FILE``: summarise a recorded MCAP log."""
from __future__ import annotations


def add_log(groups) -> None:
    """Register the ``log`` command group."""
