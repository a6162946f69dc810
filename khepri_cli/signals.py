"""`kill` (SIGTERM) ends a long command as Ctrl-C does, so that its cleanup runs and what it recorded is kept."""
from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Iterator


def _interrupt(signum, frame) -> None:
    interrupt = KeyboardInterrupt()
    interrupt.how = "SIGTERM"      # said as such: "interrupted (Ctrl-C)" read wrong after a `kill` or `timeout`
    raise interrupt


@contextmanager
def sigterm_as_ctrl_c() -> Iterator[None]:
    """While the block runs, SIGTERM raises KeyboardInterrupt in the main thread. Without it, `kill` ends the
    process at once: a study's pool workers ran on orphaned, and sil left an MCAP log without its footer."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
