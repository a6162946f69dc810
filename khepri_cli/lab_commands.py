"""``khepri hub``, ``khepri agent``, ``khepri ctl``, ``khepri keys``, ``khepri sil``, ``khepri bench hub``."""
from __future__ import annotations


def add_lab(groups) -> None:
    """Register the lab-stack commands (filled in as the hub and agent land)."""


def add_bench_hub(bench_commands) -> None:
    """Register ``khepri bench hub`` under the bench group."""
