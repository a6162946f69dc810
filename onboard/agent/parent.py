"""An agent started by a lab PC's tool (``khepri sil``, tests) ends with the process that started it.

Without this, a ``khepri sil`` killed with SIGKILL left its agents running for ever, waiting for a hub that
was gone. The starter names itself in ``KHEPRI_AGENT_PARENT_PID``; on a robot nobody sets it, so an agent
started from a shell or a service manager is unaffected.
"""
from __future__ import annotations

import ctypes
import os
import signal

from onboard.config import is_whole_number

PARENT_ENV = "KHEPRI_AGENT_PARENT_PID"
PR_SET_PDEATHSIG = 1      # linux/prctl.h


def end_with_parent() -> None:
    """Ask Linux for SIGTERM when the starter ends (the agent stops its wheels and exits on SIGTERM); if it
    ended already, before the request, act as if the signal had come. Elsewhere nothing happens: the
    watchdog still stops the wheels once the hub is silent."""
    expected = os.environ.get(PARENT_ENV)
    if not expected or not is_whole_number(expected, 9):     # a pid: not '²', which int() refuses
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0) != 0:
            return
    except (OSError, AttributeError):
        return
    if os.getppid() != int(expected):
        os.kill(os.getpid(), signal.SIGTERM)
