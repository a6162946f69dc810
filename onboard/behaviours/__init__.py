"""Shipped behaviours. Importing this package imports (and so registers) every module in it: a new
behaviour dropped into this folder is available by name without editing anything else.

A module that fails to import (a syntax error in a behaviour being written) does not take the others down:
it is said once on stderr, and looking its behaviour up says why it is missing (``BROKEN``)."""
import importlib
import os
import pkgutil
import sys
import traceback
from typing import Dict

BROKEN: Dict[str, str] = {}     # module file -> why it did not import


def _why(err: BaseException, file: str) -> str:
    """The error, and for other than a SyntaxError (whose text has its line) the line of ``file`` it came from."""
    text = f"{type(err).__name__}: {err}"
    if isinstance(err, SyntaxError):
        return text
    lines = [f.lineno for f in traceback.extract_tb(err.__traceback__) if f.filename.endswith(os.sep + file)]
    return text + (f" ({file}, line {lines[-1]})" if lines else "")


for _module in pkgutil.iter_modules(__path__):
    try:
        importlib.import_module(f"{__name__}.{_module.name}")
    except Exception as _err:  # noqa: BLE001 - SyntaxError, ImportError, a bug at import time: all the same here
        _file = f"onboard/behaviours/{_module.name}.py"
        BROKEN[_file] = _why(_err, f"{_module.name}.py")
        print(f"khepri: warning: {_file} did not import, so its behaviours are not available: {BROKEN[_file]}",
              file=sys.stderr)
