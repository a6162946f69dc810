"""Where in the user's code an exception came from: the line a behaviour's author should look at."""
from __future__ import annotations

import os
import sys
import traceback
from typing import List, Optional, Tuple

_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# khepri's own code, which a behaviour calls (the HAL, motion helpers, the simulator): an error raised in it
# is about the behaviour's call, so the line to show is the behaviour's. Behaviours live in onboard/behaviours.
_FRAMEWORK = tuple(os.path.join(_ROOT, name) + os.sep for name in ("onboard", "sim_backend", "hub", "khepri_cli"))
_BEHAVIOURS = os.path.join(_ROOT, "onboard", "behaviours") + os.sep


def users_frame(frames: traceback.StackSummary) -> Optional[traceback.FrameSummary]:
    """The innermost frame outside Python's, the installed packages' and khepri's own files: the line to look
    at (for NaN wheel speeds, the behaviour's ``set_speeds`` call, not the HAL's check)."""
    library = tuple({sys.prefix, sys.base_prefix, os.path.dirname(os.__file__)})
    for frame in reversed(frames):
        name = os.path.abspath(frame.filename)
        if name.startswith(library) or frame.filename.startswith("<"):
            continue
        if name.startswith(_FRAMEWORK) and not name.startswith(_BEHAVIOURS):
            continue
        return frame
    return frames[-1] if frames else None


def where_in_users_code(frames: traceback.StackSummary) -> str:
    """`` at wander.py:9`` for the user's frame among ``frames``, or "" when there is none."""
    where = users_frame(frames)
    return f" at {os.path.basename(where.filename)}:{where.lineno}" if where is not None else ""


def describe(exc: BaseException) -> str:
    """``ZeroDivisionError: division by zero at wander.py:12``: one line for an exception in the user's code."""
    return f"{type(exc).__name__}: {exc}{where_in_users_code(traceback.extract_tb(exc.__traceback__))}"


SHOWN_FRAMES = 6     # a traceback's end as printed for a bug in the user's code: enough to follow, not a page


def traceback_lines(frames: traceback.StackSummary, exc: BaseException) -> List[str]:
    """The end of the traceback of ``exc`` raised in the user's code, as Python prints it, one line per item:
    ``frames`` (from ``traceback.extract_tb``, the caller's own frame left out) and the exception's line. The
    user's own frame is always among them: a check deep in khepri's code (a radio payload's nested key, say)
    had pushed the behaviour's call out of the last six, leaving only hal.py and payload.py."""
    shown, left_out, checked = _frames_to_show(frames)
    lines = [line.rstrip() for line in traceback.format_list(shown[:1])]
    if left_out:
        lines.append(f"  ... ({left_out} frame{'' if left_out == 1 else 's'} in khepri's or Python's code left out)")
    lines += [line.rstrip() for line in traceback.format_list(shown[1:])]
    if checked:
        lines.append(f"  (raised in khepri's code for that call, {checked} frame{'' if checked == 1 else 's'} "
                     "further in, left out)")
    return lines + [line.rstrip() for line in traceback.format_exception_only(type(exc), exc)]


def _frames_to_show(frames: traceback.StackSummary) -> Tuple[List[traceback.FrameSummary], int, int]:
    """The frames to print: the last SHOWN_FRAMES, or the user's frame and the last ones after it; how many
    are skipped between the first shown and the second; and how many are left off the end because they are
    all khepri's own (a HAL check of the user's call raised: its lines are noise to the user)."""
    users = users_frame(frames)
    start = next((i for i, frame in enumerate(frames) if frame is users), 0)
    checked = 0
    if users is not None and start < len(frames) - 1 and all(_is_khepris(frame) for frame in frames[start + 1:]):
        checked = len(frames) - start - 1
        frames = frames[:start + 1]
    if start >= len(frames) - SHOWN_FRAMES:
        return list(frames[-SHOWN_FRAMES:]), 0, checked
    tail = list(frames[-(SHOWN_FRAMES - 1):])
    return [frames[start]] + tail, len(frames) - start - 1 - len(tail), checked


def _is_khepris(frame: traceback.FrameSummary) -> bool:
    """A frame of khepri's own code (not a behaviour's)."""
    name = os.path.abspath(frame.filename)
    return name.startswith(_FRAMEWORK) and not name.startswith(_BEHAVIOURS)
