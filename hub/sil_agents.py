"""The agent processes of a ``khepri sil`` run: how they left, what their logs say, and the throwaway keys
they were given."""
from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path
from typing import List, Optional

from onboard.config import is_whole_number

# How long agents a Ctrl-C reached too get to leave by themselves. They leave within a second on an idle PC;
# at a load of 6 on 2 cores six of them needed more than 1 s (the SIGTERM then caught them on their way out).
INTERRUPTED_WAIT_S = 3.0

def let_leaving_agents_exit(hub, agents: List[subprocess.Popen], ctrl_c: bool, timeout_s: float = 2.0) -> None:
    """An agent whose behaviour raised says so, then exits with code 1 by itself; after a Ctrl-C, the terminal's
    reached the agents too (it goes to the whole process group), and they leave with 0. Wait for those (briefly),
    so that ``agent_exit_codes`` shows their own codes, not the -15 of a SIGTERM that caught them on their way
    out (every agent read -15 after a Ctrl-C). A SIGINT sent to sil alone costs INTERRUPTED_WAIT_S more."""
    deadline = time.monotonic() + (INTERRUPTED_WAIT_S if ctrl_c else timeout_s)
    for robot_id, agent in enumerate(agents):
        error = str((hub.robots[robot_id].telemetry or {}).get("error") or "")
        if ctrl_c or error.startswith(("behaviour crashed", "driver failed")):
            try:
                agent.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass


KEY_FOLDER_PREFIX = "khepri-sil-keys-"      # + the pid of the sil that made it


def remove_stale_key_folders() -> None:
    """The throwaway CURVE keys of a ``khepri sil`` that was killed (SIGKILL runs no cleanup) stay in the temp
    folder, secret keys included: the next sil removes those whose process is gone."""
    for folder in Path(tempfile.gettempdir()).glob(f"{KEY_FOLDER_PREFIX}*-*"):
        pid = folder.name[len(KEY_FOLDER_PREFIX):].split("-")[0]
        if is_whole_number(pid, 9) and not _alive(int(pid)):     # a pid; not '²' (int() refuses it) nor 30 digits
            shutil.rmtree(folder, ignore_errors=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:        # another user's process: alive, and not ours to clean
        return True
    return True


def exit_text(code: int) -> str:
    """``exited with code 1``, or for a signal ``was killed by SIGKILL (exit code -9)``: -9 reads as a bug."""
    if code < 0:
        try:
            return f"was killed by {signal.Signals(-code).name} (exit code {code})"
        except ValueError:
            pass
    return f"exited with code {code}"


LEFT_ON_SIGNAL = ": wheels stopped, leaving"      # how an agent logs leaving on a signal (loop._say_why_leaving)


def signal_it_left_on(out: Path, index: int) -> str:
    """The signal agent ``index`` says it left on (``agent 3: SIGTERM: wheels stopped, leaving``), or ""."""
    own = f"agent {index}: "
    line = next((line for line in reversed(agent_log_lines(out, index))
                 if line.startswith(own + "SIG") and line.endswith(LEFT_ON_SIGNAL)), "")
    return line[len(own):-len(LEFT_ON_SIGNAL)] if line else ""


def stop_failure(out: Path, count: int) -> Optional[str]:
    """The first agent's account of its behaviour's ``stop()`` raising at the end of the run (the agent logs
    it and stops the wheels all the same; ``khepri sim run`` reports the same bug as an error)."""
    for i in range(count):
        marker = f"agent {i}: robot {i}, stop(): "
        rest = agent_log_line(out, i, marker)
        if rest:
            return f"after the run: {marker}{rest}"
    return None


def agent_log_lines(out: Path, index: int) -> List[str]:
    """Agent ``index``'s log, line by line; none when it cannot be read."""
    try:
        return (out / "agents" / f"agent-{index}.log").read_text(encoding="utf-8").splitlines()
    except OSError:
        return []


def agent_log_line(out: Path, index: int, marker: str) -> str:
    """The rest of agent ``index``'s last log line that starts with ``marker``, or ""."""
    lines = agent_log_lines(out, index)
    return next((line[len(marker):] for line in reversed(lines) if line.startswith(marker)), "")


# How an agent logs a step longer than its watchdog (loop._say_if_slow; safety's step watchdog, during the step).
SLOW_STEP_MARKS = ("the behaviour's step took ", "the behaviour's step() has run for ")
SLOW_STEP_AGENTS_LISTED = 5


def slow_step_warnings(out: Path, count: int) -> List[str]:
    """result.json's warnings for the agents whose log says a step() outlasted the watchdog: the first such line
    of each, for at most five agents. `sim run` lists a slow step() among its warnings; sil's was only in the
    agent's log, so a run that passed in sil hid a behaviour that stops a real robot's wheels."""
    found = []
    for index in range(count):
        marks = tuple(f"agent {index}: {mark}" for mark in SLOW_STEP_MARKS)
        line = next((line for line in agent_log_lines(out, index) if line.startswith(marks)), None)
        if line is not None:
            found.append(f"{line} (agents/agent-{index}.log)")
    if len(found) > SLOW_STEP_AGENTS_LISTED:
        rest = len(found) - SLOW_STEP_AGENTS_LISTED
        found = found[:SLOW_STEP_AGENTS_LISTED] + [f"{rest} more agent{'s' if rest > 1 else ''} logged a step() "
                                                   "longer than the watchdog (agents/agent-*.log)"]
    return found


def agent_traceback(out: Path, index: int) -> Optional[List[str]]:
    """The traceback agent ``index`` logged under its last ``behaviour crashed`` (or ``driver failed``) line, as
    `khepri sim run` keeps it in result.json: one string per entry, its source lines joined by newlines."""
    lines = agent_log_lines(out, index)
    heads = (f"agent {index}: behaviour crashed: ", f"agent {index}: driver failed: ")
    starts = [i for i, line in enumerate(lines) if line.startswith(heads)]
    if not starts:
        return None
    entry, own, trace = f"agent {index}:   ", f"agent {index}: ", []
    for line in lines[starts[-1] + 1:]:
        if line.startswith(entry):
            trace.append(line[len(entry):])
        elif line.startswith((own, "agent: ")):      # the agent's next line of its own: the trace is over
            break
        elif trace:
            trace[-1] += "\n" + line
        # else: the rest of an error message of several lines, before the trace
    return trace or None


# --- --agent-python: the robots' interpreter ---------------------------------------------------------------------
AGENT_PYTHON_CHECK_S = 60.0      # importing numpy and scipy (filterpy's) on a cold disk takes a few seconds
# Run by the interpreter --agent-python names, which may be old: %-formatting, no f-strings, to say its version.
_CHECK = """
import importlib, sys
if sys.version_info < (3, 9):
    print("is Python %d.%d: onboard/ needs Python 3.9 or newer" % tuple(sys.version_info[:2]))
    sys.exit(3)
missing = []
for name in ("numpy", "zmq", "yaml", "filterpy.kalman", "onboard.agent"):
    try:
        importlib.import_module(name)
    except Exception as err:
        missing.append("%s (%s: %s)" % (name, type(err).__name__, err))
if missing:
    print("cannot import " + "; ".join(missing))
    sys.exit(3)
print("%d.%d.%d" % tuple(sys.version_info[:3]))
"""


def check_agent_python(python: str) -> str:
    """The version of the interpreter ``--agent-python`` names, once it has shown it can run onboard/: Python 3.9
    or newer with the robots' packages (numpy, pyzmq, pyyaml, filterpy) and this khepri's onboard/ importable.
    A lab checks its behaviour on the robots' Python before deploying; an interpreter that cannot run an agent
    is said here, not as six crashed agents."""
    from onboard.config import ConfigError, as_written

    from .harness import khepri_env

    if not os.path.isfile(python) or not os.access(python, os.X_OK):
        raise ConfigError("--agent-python", f"{python} is not an executable file")
    try:
        check = subprocess.run([python, "-c", _CHECK], capture_output=True, text=True, env=khepri_env(),
                               timeout=AGENT_PYTHON_CHECK_S, errors="backslashreplace")
    except subprocess.TimeoutExpired:
        raise ConfigError("--agent-python", f"{python} did not import onboard/'s packages within "
                                            f"{AGENT_PYTHON_CHECK_S:g} s") from None
    except OSError as err:
        raise ConfigError("--agent-python", f"{python} does not run: {err.strerror}") from None
    said = (check.stdout.strip().splitlines() or check.stderr.strip().splitlines()[-1:] or [""])[-1]
    if check.returncode == 0 and re.fullmatch(r"\d+\.\d+\.\d+", said):
        return said
    if said.startswith("cannot import"):
        raise ConfigError("--agent-python", f"{python} {said}: install numpy, pyzmq, pyyaml and filterpy into it")
    if said.startswith("is Python"):
        raise ConfigError("--agent-python", f"{python} {said}")
    # Not a Python that runs the check (/bin/true, a shell script that fails): what it said, or its exit code.
    raise ConfigError("--agent-python", f"{python} does not run as a Python interpreter (exit code "
                                        f"{check.returncode}{': ' + as_written(said) if said else ''})")


def agent_python_text(python: Optional[str], version: Optional[str] = None) -> str:
    """``3.9.18 (/path/to/python)``: which interpreter ran the agents, for result.json."""
    import platform
    import sys

    if python is None:
        return f"{platform.python_version()} ({sys.executable})"
    return f"{version or '?'} ({python})"
