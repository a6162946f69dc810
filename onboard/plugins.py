"""Importing the user's own behaviour modules (``--import``), the same way in every process that runs one:
``khepri`` itself, a study's worker processes, and the agents (on a robot, or started by ``khepri sil``).

A module registers its behaviours with ``@register`` when it is imported, so importing it is all it takes.
"""
from __future__ import annotations

import ast
import importlib
import importlib.machinery
import importlib.util
import os
import sys
import sysconfig
import traceback
from pathlib import Path
from typing import Any, Callable, Iterable, List, Optional

from .config import ConfigError, as_written
from .tracebacks import describe, where_in_users_code

#: What a robot does not have: a behaviour's module that imports these runs in simulation and fails on a robot.
NOT_ON_ROBOTS = ("sim_backend", "hub", "khepri_cli", "pymunk", "matplotlib")
#: What a robot has besides the standard library (docs/lab.md, "Setting up a robot"), by import name.
ON_ROBOTS = ("onboard", "numpy", "zmq", "yaml", "filterpy")


def import_user_modules(names: Iterable[str], base_dir: Optional[str] = None) -> List[str]:
    """Import each of ``names``: a module name (``wander``, ``mylab.behaviours``) found in ``base_dir`` (default:
    the current folder) or on ``sys.path``, or the path of a ``.py`` file (relative to ``base_dir``).

    A module that cannot be found or imported, whose file does not parse, or whose own code raises while it is
    imported, is a ConfigError naming it (and, for the last, the file and line). Returns warnings: a module that
    registers a behaviour and imports what robots do not have (:data:`NOT_ON_ROBOTS`)."""
    from .behaviour import _REGISTRY, behaviour_names

    behaviour_names()      # the built-ins first: a user's module reusing one of their names is then the one told
    base = base_dir or os.getcwd()
    if base not in sys.path:
        sys.path.insert(0, base)
    warnings = []
    for name in names:
        module = _module_name(name, base)
        known, fresh = set(_REGISTRY), module not in sys.modules
        try:
            loaded = importlib.import_module(module)
        except SyntaxError as err:
            raise ConfigError("--import", f"{err.filename}:{err.lineno}: {err.msg}") from None
        except ImportError as err:
            raise ConfigError("--import", f"cannot import {name!r}: {err}") from None
        except ConfigError:
            raise                  # e.g. @register refusing a name: it says what is wrong already
        except SystemExit as err:  # khepri exited with the module's code and said nothing
            code = "" if err.code is None else as_written(err.code)
            raise ConfigError("--import", f"importing {as_written(name)} called sys.exit({code})"
                                          f"{where_in_users_code(traceback.extract_tb(err.__traceback__))}: a "
                                          "behaviour's module must not exit when imported (put a script's own "
                                          "code under if __name__ == \"__main__\":)") from None
        except Exception as err:   # the module's own code raised while it was imported: where, in one line
            raise ConfigError("--import", f"importing {name!r} raised {describe(err)}") from None
        _check_not_shadowed(name, loaded, base)
        registered = sorted(set(_REGISTRY) - known)
        if fresh and not _defines_behaviours(loaded):
            warnings.append(f"{name}: imported {getattr(loaded, '__file__', None) or 'a built-in module'}, which "
                            "registers no behaviour (@register(\"name\") above a Behaviour class)")
        missing = imports_robots_lack(getattr(loaded, "__file__", None)) if registered else []
        if missing:
            warnings.append(f"{name}: registers the behaviour {', '.join(registered)} and imports "
                            f"{', '.join(missing)}: it runs in simulation but will fail on a robot, which has only "
                            "onboard/ (put an evaluator in a module of its own)")
        newer = syntax_after_python_39(getattr(loaded, "__file__", None)) if registered else None
        if newer:
            warnings.append(f"{name}: registers the behaviour {', '.join(registered)} and {newer}, which Python "
                            "3.9 cannot run: it runs here but will fail on a robot with Python 3.9 (khepri's "
                            "onboard code keeps to 3.9)")
        extra = packages_robots_lack(loaded, base) if registered else []
        if extra:
            warnings.append(f"{name}: registers the behaviour {', '.join(registered)} and imports "
                            f"{', '.join(extra)}, which a robot does not have (it has the standard library, numpy, "
                            "pyzmq, pyyaml and filterpy): it runs in simulation but will fail on a robot unless "
                            "installed there too")
    return warnings


def packages_robots_lack(module: Any, base: str) -> List[str]:
    """Third-party packages the module's file imports that are not on a robot: the lab PC's (``mcap``, ``dask``,
    ``scipy``, ...) install with khepri, so a behaviour that uses one runs in ``sim run`` and ``sil`` and fails
    only on the robot. Modules beside it (a helper copied along) and its own package are fine."""
    path = getattr(module, "__file__", None)
    if not path:
        return []
    own = (module.__name__.split(".")[0], "__future__", *ON_ROBOTS, *NOT_ON_ROBOTS)   # the last: warned above
    folders = (Path(path).parent, Path(base))
    return [top for top in _top_level_imports(path)
            if top not in own and not any(_is_beside(top, f) for f in folders) and _is_standard(top) is False]


def _is_standard(top: str) -> Optional[bool]:
    """Whether the top-level module ``top`` is the standard library's. None when Python 3.9, which does not list
    the standard library, cannot find the module at all: it would not run on the PC either."""
    if _standard_name(top):
        return True
    if hasattr(sys, "stdlib_module_names"):
        return False
    try:
        spec = importlib.util.find_spec(top)   # a top-level name: imports nothing
    except (ImportError, ValueError):          # ValueError: in sys.modules without a __spec__
        return None
    return None if spec is None else False


def _standard_name(top: str) -> bool:
    """Whether ``top`` is a standard library module's name, whatever else sys.path holds. Python >= 3.10 lists
    them (``sys.stdlib_module_names``); 3.9 does not, so there it is told by where this interpreter has the
    module: built into it, frozen, or in its standard library's folders (sysconfig's ``stdlib`` and
    ``platstdlib``, with lib-dynload, not the site-packages inside them), not in the user's folder before them."""
    names = getattr(sys, "stdlib_module_names", None)
    if names is not None:
        return top in names
    if top in sys.builtin_module_names or importlib.machinery.FrozenImporter.find_spec(top) is not None:
        return True
    folders = [entry for entry in sys.path if entry and _in_standard_folders(Path(entry))]
    try:
        return importlib.machinery.PathFinder.find_spec(top, folders) is not None   # imports nothing
    except (ImportError, ValueError):
        return False


def _in_standard_folders(place: Path) -> bool:
    paths = sysconfig.get_paths()
    place = place.resolve()
    standard = {Path(paths[key]).resolve() for key in ("stdlib", "platstdlib")}
    installed = {Path(paths[key]).resolve() for key in ("purelib", "platlib")}
    return (any(_within(place, folder) for folder in standard)
            and not any(_within(place, folder) for folder in installed)
            and not {"site-packages", "dist-packages"} & set(place.parts))


def _within(place: Path, folder: Path) -> bool:
    return place == folder or folder in place.parents


def _is_beside(top: str, folder: Path) -> bool:
    return (folder / f"{top}.py").is_file() or (folder / top).is_dir()


def imports_robots_lack(path: Optional[str], _seen: Optional[set] = None) -> List[str]:
    """The packages of :data:`NOT_ON_ROBOTS` that the file at ``path`` imports, at any depth of its code, and
    those that the modules beside it that it imports do (a helper copied along: ``sim_backend (in helper.py)``)."""
    seen = set() if _seen is None else _seen
    if not path or path in seen:
        return []
    seen.add(path)
    tops = _top_level_imports(path)
    found = [top for top in tops if top in NOT_ON_ROBOTS]
    for top in tops:
        beside = Path(path).parent / f"{top}.py"
        if top not in NOT_ON_ROBOTS and beside.is_file():
            found += [name if " (in " in name else f"{name} (in {beside.name})"
                      for name in imports_robots_lack(str(beside), seen)]
    return found


def syntax_after_python_39(path: Optional[str]) -> Optional[str]:
    """Where the file at ``path`` uses what Python 3.9 cannot run, said as ``uses ... at file:line``, or None:
    syntax of 3.10 and later (``match``, ...), and ``X | Y`` in a type annotation, which 3.9 parses but cannot
    evaluate (a Params dataclass's ``float | None`` fails as its class is made, or when khepri reads its hints)."""
    if not path:
        return None
    try:
        source = Path(path).read_text(encoding="utf-8")
        tree = ast.parse(source)
    except (OSError, SyntaxError, ValueError):
        return None
    where = Path(path).name
    try:
        ast.parse(source, feature_version=(3, 9))
    except SyntaxError as err:
        # The parser names where it gave up (after a match block); the statement itself is where to look.
        match = getattr(ast, "Match", None)
        found = next((n for n in ast.walk(tree) if match is not None and isinstance(n, match)), None)
        line = err.lineno if found is None else found.lineno
        return f"uses syntax of a newer Python at {where}:{line} ({err.msg})"
    for node in ast.walk(tree):
        for annotation in _annotations(node):
            union = next((n for n in ast.walk(annotation) if isinstance(n, ast.BinOp)
                          and isinstance(n.op, ast.BitOr)), None)
            if union is not None:
                return (f"uses `X | Y` in a type annotation at {where}:{union.lineno} (write Optional[X] or "
                        "Union[X, Y] from typing)")
    return None


def _annotations(node: ast.AST) -> List[ast.AST]:
    if isinstance(node, ast.AnnAssign):
        return [node.annotation]
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
        arguments = node.args
        every = [*arguments.posonlyargs, *arguments.args, *arguments.kwonlyargs, arguments.vararg, arguments.kwarg]
        return [a.annotation for a in every if a is not None and a.annotation is not None] + \
            ([node.returns] if node.returns is not None else [])
    return []


def _top_level_imports(path: Optional[str]) -> List[str]:
    """The top-level names of every absolute import in the file at ``path``, at any depth of its code, sorted."""
    if not path:
        return []
    try:
        tree = ast.parse(Path(path).read_text(encoding="utf-8"))
    except (OSError, SyntaxError, ValueError):
        return []
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        else:
            continue
        found.update(n.split(".")[0] for n in names)
    return sorted(found)


def _check_name_is_free(path: Path) -> None:
    """A file is imported by its name: one that a loaded module or the standard library already has would
    silently be that other module (``random.py``), and a second file of the same name would be skipped."""
    taken = sys.modules.get(path.stem)
    if taken is not None:
        where = getattr(taken, "__file__", None)
        if where is None or Path(where).resolve() != path.resolve():
            raise ConfigError("--import", f"{path}: the module name {path.stem!r} is taken by "
                                          f"{where or 'a built-in module'}; rename the file")
    elif _standard_name(path.stem):
        raise ConfigError("--import", f"{path}: {path.stem!r} is a standard library module's name; rename the file")


def _check_not_shadowed(name: str, loaded: Any, base: str) -> None:
    """``--import random`` next to the user's random.py imports the standard library's random: say so."""
    local = Path(base, *name.split(".")).with_suffix(".py")
    where = getattr(loaded, "__file__", None)
    if name.endswith(".py") or not local.is_file() or (where and Path(where).resolve() == local.resolve()):
        return
    stdlib = _standard_name(name.split(".")[0])
    raise ConfigError("--import", f"{name!r} imports {where or 'a built-in module'}"
                                  f"{' (the standard library)' if stdlib else ''}, not {local}; rename {local.name}")


#: Other registries a user's module may add to (the simulator's evaluators add theirs when imported): each
#: returns the classes registered so far.
OTHER_REGISTRIES: List[Callable[[], Iterable[type]]] = []


def _defines_behaviours(module: Any) -> bool:
    """Whether ``module`` holds a registered behaviour (or evaluator) class."""
    from .behaviour import _REGISTRY

    registered = list(_REGISTRY.values()) + [cls for listed in OTHER_REGISTRIES for cls in listed()]
    return any(getattr(cls, "__module__", None) == module.__name__ for cls in registered)


def _names_a_file(name: str, base: str) -> bool:
    """A path rather than a module name: a .py or YAML suffix, a folder part, or a file there by that name
    (lab6copy.yaml was read as the module lab6copy's submodule yaml: "No module named 'lab6copy'")."""
    return name.endswith((".py", ".yaml", ".yml")) or "/" in name or os.sep in name or Path(base, name).is_file()


def user_module_name(name: str, base_dir: Optional[str] = None) -> str:
    """The name under which :func:`import_user_modules` imports ``name`` (its key in ``sys.modules``)."""
    return _module_name(name, base_dir or os.getcwd())


def _module_name(name: str, base: str) -> str:
    """The importable name of ``name``; a file's folder goes on ``sys.path`` first."""
    if not _names_a_file(name, base):
        if not all(part.isidentifier() for part in name.split(".")):
            raise ConfigError("--import", f"{name!r} is neither a module name (like wander or mylab.wander) "
                                          "nor a .py file")
        return name
    path = Path(base, name)
    if path.is_dir():
        raise ConfigError("--import", f"{path} is a folder: give the .py file that holds your behaviour")
    if not path.is_file():
        raise ConfigError("--import", f"no such file: {path}")
    if path.suffix != ".py":      # a scenario given to --import said "No module named 'flock7'"
        raise ConfigError("--import", f"{path.name} is not a .py file: --import takes the Python file that holds "
                                      "your behaviour (a scenario goes after the command, e.g. sim run FILE.yaml)")
    if not path.stem.isidentifier():
        raise ConfigError("--import", f"{path.name}: a module's file name must be a Python identifier")
    _check_name_is_free(path)
    folder = str(path.resolve().parent)
    if folder not in sys.path:
        sys.path.insert(0, folder)
    return path.stem
