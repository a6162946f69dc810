"""EvaluatorError in a module of its own: ``khepri`` catches it around every command, and importing it from
``metrics`` registered the built-in evaluators, which import the transport behaviour and with it filterpy and
scipy (1-2 s), before even `khepri ctl estop` could send its command."""
from __future__ import annotations

import traceback
from typing import Any, List

from onboard.tracebacks import traceback_lines, where_in_users_code


class EvaluatorError(RuntimeError):
    """An evaluator's own code raised: which evaluator, in which call, what, and where in the user's file,
    said as a behaviour's bug is (``onboard.behaviour.BehaviourError``); ``lines`` keeps the traceback's end."""

    def __init__(self, evaluator: Any, call: str, exc: BaseException):
        self.call, self.exc = call, exc
        name = evaluator.__name__ if isinstance(evaluator, type) else type(evaluator).__name__
        frames = traceback.extract_tb(exc.__traceback__)[1:]    # [0] is evaluator_call's own frame
        self.lines: List[str] = traceback_lines(frames, exc)
        super().__init__(f"evaluator {name}.{call}: {type(exc).__name__}: {exc}"
                         f"{where_in_users_code(frames)}")
