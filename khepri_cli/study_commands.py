"""``khepri study``: the paper's grid of runs, locally or on Dask."""
from __future__ import annotations


def add_study(groups) -> None:
    """Register the ``study`` command group."""
