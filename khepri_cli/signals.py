"""`kill` (SIGTERM), or the terminal closing (SIGHUP), ends a long command as Ctrl-C does, so that its cleanup runs
and what it recorded is kept."""
from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Iterator


def _interrupt(signum, frame) -> None:
    interrupt = KeyboardInterrupt()
    # said as such: "interrupted (Ctrl-C)" read wrong after a `kill`, a `timeout` or a closed ssh session
    interrupt.how = signal.Signals(signum).name
    raise interrupt


@contextmanager
def sigterm_as_ctrl_c() -> Iterator[None]:
    """While the block runs, SIGTERM and SIGHUP raise KeyboardInterrupt in the main thread. Without it, `kill`
    ends the process at once: a study's pool workers ran on orphaned, and sil left an MCAP log without its
    footer and its secret keys in /tmp; the terminal or ssh session closing did the same. Not SIGHUP when it
    is ignored already: `nohup khepri ...` is meant to outlive its terminal (as the hub and agents do,
    onboard/console.py)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    signals = [signal.SIGTERM]
    if hasattr(signal, "SIGHUP") and signal.getsignal(signal.SIGHUP) != signal.SIG_IGN:
        signals.append(signal.SIGHUP)
    previous = {signum: signal.signal(signum, _interrupt) for signum in signals}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
