"""The architecture rules that keep behaviours portable to real robots."""
import ast
import io
import tokenize
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN_IN_ONBOARD = {"sim_backend", "hub", "pymunk", "matplotlib", "khepri_cli", "calibration", "deploy"}


def imported_modules(path: Path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name.split(".")[0], node.lineno
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.module.split(".")[0], node.lineno


def test_onboard_imports_neither_the_simulator_nor_the_hub():
    offenders = [f"{path.relative_to(ROOT)}:{line} imports {module}"
                 for path in sorted((ROOT / "onboard").rglob("*.py"))
                 for module, line in imported_modules(path) if module in FORBIDDEN_IN_ONBOARD]
    assert offenders == []


def test_the_check_itself_catches_a_forbidden_import(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("import numpy\nfrom sim_backend.world import World\n")
    assert ("sim_backend", 2) in list(imported_modules(bad))


# What runs on a robot keeps to Python 3.9 (see README): its syntax, and the newer features that parse on 3.9 but
# fail when the module runs there. CI need not have a 3.9 interpreter, so the check reads the code: the syntax
# with ast's feature_version (and, on 3.12+, the f-strings it lets through), and the newer standard library from
# the tables below. Code that uses them only on a newer Python, under `if sys.version_info ...` or in a `try`
# that catches an older one's ImportError, AttributeError, NameError or TypeError, is let be.
NEW_NAMES = {   # module: what it gained after 3.9
    "typing": {"TypeAlias", "ParamSpec", "ParamSpecArgs", "ParamSpecKwargs", "Concatenate", "TypeGuard",
               "is_typeddict", "Self", "Never", "LiteralString", "Required", "NotRequired", "Unpack", "TypeVarTuple",
               "assert_never", "assert_type", "reveal_type", "dataclass_transform", "get_overloads",
               "clear_overloads", "override", "TypeAliasType", "ReadOnly", "TypeIs", "NoDefault"},
    "itertools": {"pairwise", "batched"},
    "contextlib": {"aclosing", "chdir"},
    "sys": {"stdlib_module_names", "orig_argv", "exception", "monitoring"},
    "types": {"NoneType", "EllipsisType", "NotImplementedType", "UnionType", "get_original_bases"},
    "dataclasses": {"KW_ONLY"},
    "inspect": {"get_annotations", "markcoroutinefunction"},
    "statistics": {"correlation", "covariance", "linear_regression"},
    "math": {"cbrt", "exp2", "sumprod", "fma"},
    "enum": {"StrEnum", "ReprEnum", "EnumCheck", "FlagBoundary", "verify", "member", "nonmember", "global_enum"},
    "datetime": {"UTC"},
    "asyncio": {"TaskGroup", "timeout", "timeout_at", "Runner", "Barrier"},
    "operator": {"call"},
    "hashlib": {"file_digest"},
    "logging": {"getLevelNamesMapping", "getHandlerByName", "getHandlerNames"},
    "os": {"eventfd", "splice", "process_cpu_count"},
    "threading": {"gettrace", "getprofile"},
    "copy": {"replace"},
}
NEW_MODULES = {"tomllib"}
NEW_BUILTINS = {"aiter", "anext", "EncodingWarning", "ExceptionGroup", "BaseExceptionGroup"}
NEW_METHODS = {"bit_count": "int.bit_count()", "add_note": "an exception's add_note()",
               "hardlink_to": "Path.hardlink_to()"}
NEW_KEYWORDS = {   # a function's or method's name: the keywords it gained after 3.9
    "zip": {"strict"}, "dataclass": {"slots", "kw_only", "match_args", "weakref_slot"}, "field": {"kw_only"},
    **{name: {"key"} for name in ("bisect", "bisect_left", "bisect_right", "insort", "insort_left", "insort_right")},
    "TemporaryDirectory": {"ignore_cleanup_errors", "delete"}, "glob": {"root_dir", "dir_fd", "include_hidden"},
    "iglob": {"root_dir", "dir_fd", "include_hidden"}, "write_text": {"newline"}, "rmtree": {"onexc"},
    "Formatter": {"defaults"}, "fmean": {"weights"},
    **{name: {"process_group", "pipesize"} for name in ("run", "Popen", "call", "check_call", "check_output")},
}
#: Calls whose arguments 3.9 still requires: the fewest it takes (positional or by these names).
REQUIRED_ARGUMENTS = {"traceback.format_exception": (3, {"etype", "value", "tb"}),
                      "traceback.print_exception": (3, {"etype", "value", "tb"}),
                      "traceback.format_exception_only": (2, {"etype", "value"})}
REQUIRED_METHOD_ARGUMENTS = {"to_bytes": (2, {"length", "byteorder"}), "from_bytes": (2, {"bytes", "byteorder"})}
TYPE_NAMES = {"int", "float", "complex", "str", "bytes", "bool", "list", "dict", "tuple", "set", "frozenset", "type",
              "object", "List", "Dict", "Tuple", "Set", "FrozenSet", "Optional", "Union", "Callable", "Type",
              "Sequence", "Mapping", "Iterable", "Literal", "Any"}
GUARDING_ERRORS = {"ImportError", "ModuleNotFoundError", "AttributeError", "NameError", "TypeError"}


def python39_problems(path: Path):
    source = path.read_text()
    try:
        tree = ast.parse(source, filename=str(path), feature_version=(3, 9))
    except SyntaxError as error:
        return [f"{path.name}:{error.lineno}: not Python 3.9 syntax: {error.msg}"]
    lazy_annotations = any(isinstance(node, ast.ImportFrom) and node.module == "__future__"
                           and any(alias.name == "annotations" for alias in node.names) for node in tree.body)
    module = _ModuleFacts(tree)
    problems = [(node.lineno, problem) for node in _unguarded_nodes(tree)
                for problem in _python310_features(node, lazy_annotations, module)]
    problems += list(_newer_fstrings(source))
    return [f"{path.name}:{line}: {problem}" for line, problem in sorted(problems)]


class _ModuleFacts:
    """What a module's names stand for: ``imported`` maps a local name to what it imports (``it`` ->
    ``itertools``, ``pairwise`` -> ``itertools.pairwise``); ``bound`` is every name the module binds itself."""

    def __init__(self, tree):
        self.imported, self.bound, self.annotation_nodes, self.type_test_nodes = {}, set(), set(), set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    local = alias.asname or alias.name.split(".")[0]
                    self.imported[local] = alias.name if alias.asname else local
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                for alias in node.names:
                    self.imported[alias.asname or alias.name] = f"{node.module}.{alias.name}"
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                self.bound.add(node.name)
            elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
                self.bound.add(node.id)
            elif isinstance(node, ast.arg):
                self.bound.add(node.arg)
            elif isinstance(node, ast.alias):
                self.bound.add(node.asname or node.name.split(".")[0])
            for annotation in _annotations(node):
                if annotation is not None:
                    self.annotation_nodes.update(id(part) for part in ast.walk(annotation))
            if _called_name(node) in ("isinstance", "issubclass") and len(node.args) == 2:
                self.type_test_nodes.add(id(node.args[1]))

    def qualified(self, node):
        """``itertools.pairwise`` for ``it.pairwise`` or ``pairwise`` imported so; None for anything else."""
        if isinstance(node, ast.Name):
            return self.imported.get(node.id)
        if isinstance(node, ast.Attribute):
            owner = self.qualified(node.value)
            return f"{owner}.{node.attr}" if owner else None
        return None


def _unguarded_nodes(tree):
    """Every node but those that run only on a newer Python: an ``if`` testing ``sys.version_info`` (either
    branch), and a ``try`` body whose handler catches what an older Python raises (ImportError, ...)."""
    stack = [tree]
    while stack:
        node = stack.pop()
        yield node
        if isinstance(node, ast.If) and any(isinstance(part, ast.Attribute) and part.attr == "version_info"
                                            for part in ast.walk(node.test)):
            stack.append(node.test)
        elif isinstance(node, ast.Try) and any(_caught_names(handler) & GUARDING_ERRORS for handler in node.handlers):
            stack.extend([*node.handlers, *node.orelse, *node.finalbody])
        else:
            stack.extend(ast.iter_child_nodes(node))


def _caught_names(handler):
    caught = handler.type.elts if isinstance(handler.type, ast.Tuple) else [handler.type]
    return {getattr(name, "id", getattr(name, "attr", None)) for name in caught}


def _annotations(node):
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
        arguments = node.args.posonlyargs + node.args.args + node.args.kwonlyargs
        return [argument.annotation for argument in arguments] + [node.returns]
    return [node.annotation] if isinstance(node, ast.AnnAssign) else []


def _called_name(node):
    return getattr(node.func, "id", getattr(node.func, "attr", "")) if isinstance(node, ast.Call) else None


def _python310_features(node, lazy_annotations, module):
    if not lazy_annotations:
        for annotation in _annotations(node):
            if annotation is not None and any(isinstance(part, ast.BinOp) and isinstance(part.op, ast.BitOr)
                                              for part in ast.walk(annotation)):
                yield "an 'X | Y' annotation needs 'from __future__ import annotations' on 3.9"
    if isinstance(node, ast.Call):
        yield from _call_features(node, module)
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.BitOr) and id(node) not in module.annotation_nodes \
            and id(node) not in module.type_test_nodes and any(map(_is_type, (node.left, node.right))):
        yield "'X | Y' of types outside an annotation is Python 3.10+ (Optional, Union)"
    if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module in NEW_NAMES:
        yield from (f"{node.module}.{alias.name} is not in Python 3.9" for alias in node.names
                    if alias.name in NEW_NAMES[node.module])
    if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Load):
        owner = module.qualified(node.value)
        if owner in NEW_NAMES and node.attr in NEW_NAMES[owner]:
            yield f"{owner}.{node.attr} is not in Python 3.9"
        if node.attr in NEW_METHODS:
            yield f"{NEW_METHODS[node.attr]} is not in Python 3.9"
    if isinstance(node, ast.Name) and isinstance(node.ctx, ast.Load) and node.id in NEW_BUILTINS \
            and node.id not in module.bound:
        yield f"the built-in {node.id} is not in Python 3.9"
    modules = ([alias.name for alias in node.names] if isinstance(node, ast.Import)
               else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
    yield from (f"module {name} is not in Python 3.9" for name in modules if name.split(".")[0] in NEW_MODULES)


def _call_features(node, module):
    name = _called_name(node)
    keywords = {keyword.arg for keyword in node.keywords}
    newer = keywords & NEW_KEYWORDS.get(name, set())
    if newer:
        yield f"{name}({'=, '.join(sorted(newer))}=) is not in Python 3.9"
    if name in ("isinstance", "issubclass") and len(node.args) == 2 and isinstance(node.args[1], ast.BinOp):
        yield f"{name}(x, A | B) is Python 3.10+"
    if None in keywords or any(isinstance(argument, ast.Starred) for argument in node.args):
        return                                    # *args or **kwargs: how many is not known here
    qualified = module.qualified(node.func)
    fewest, names = REQUIRED_ARGUMENTS.get(qualified or "", REQUIRED_METHOD_ARGUMENTS.get(
        name if isinstance(node.func, ast.Attribute) else "", (0, set())))
    if len(node.args) + len(keywords & names) < fewest:
        yield f"{qualified or name}() takes at least {fewest} arguments on Python 3.9"


def _is_type(node):
    if isinstance(node, ast.Constant):
        return node.value is None
    if isinstance(node, ast.Subscript):
        node = node.value
    return isinstance(node, ast.Name) and node.id in TYPE_NAMES


def _newer_fstrings(source):
    """Python 3.12 lets an f-string's expressions reuse its quotes, hold backslashes and comments, and break lines
    (PEP 701). ast.parse's feature_version lets those through, 3.9 cannot read them. 3.12's tokenizer shows an
    f-string's parts; an older Python does not parse such code at all, so the parse above tells already."""
    start = getattr(tokenize, "FSTRING_START", None)
    if start is None:
        return
    opened = []   # the quotes of the f-strings the token is in
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.FSTRING_END:
            opened.pop()
            continue
        if opened and not (token.type == tokenize.FSTRING_MIDDLE and len(opened) == 1):
            quote = _quote(token.string) if token.type in (tokenize.STRING, start) else None
            if quote and any(_closes(quote, outer) for outer in opened):
                yield token.start[0], "an f-string's expression reusing its quotes is Python 3.12+"
            elif "\\" in token.string:
                yield token.start[0], "a backslash in an f-string's expression is Python 3.12+"
            elif token.type == tokenize.COMMENT:
                yield token.start[0], "a comment in an f-string's expression is Python 3.12+"
            elif token.type in (tokenize.NL, tokenize.NEWLINE) and any(len(outer) == 1 for outer in opened):
                yield token.start[0], "a line break in a one-line f-string's expression is Python 3.12+"
        if token.type == start:
            opened.append(_quote(token.string))


def _quote(text):
    body = text.lstrip("rRbBfFuU")
    return body[:3] if body[:3] in ('"""', "'''") else body[:1]


def _closes(quote, outer):
    """Whether a string opened with ``quote`` inside an f-string opened with ``outer`` ended it on 3.9."""
    return quote.startswith(outer) if len(outer) == 3 else quote[0] == outer


def test_onboard_code_runs_on_python_3_9():
    offenders = [problem for path in sorted((ROOT / "onboard").rglob("*.py")) for problem in python39_problems(path)]
    assert offenders == []


NEWER = """\
import tomllib
import itertools as it
import sys, traceback, bisect, typing
from dataclasses import dataclass, field
from typing import TypeAlias
from contextlib import aclosing
@dataclass(slots=True)
class A:
    x: int | None = None
    y: int = field(kw_only=True, default=0)
Number = int | float
def f(a, b, exc):
    list(zip(a, b, strict=True)), isinstance(a, int | str)
    it.pairwise(a)
    bisect.bisect_left(a, 1, key=abs)
    (5).bit_count()
    sys.stdlib_module_names
    typing.ParamSpec
    traceback.format_exception(exc)
    traceback.print_exception(exc)
    b.to_bytes(2)
    int.from_bytes(b)
    return anext(a)
"""
# Newer code that runs only on a newer Python, and 3.9 code that looks like it.
GUARDED = """\
import sys, traceback, itertools
from typing import Optional, Union
if sys.version_info >= (3, 10):
    from itertools import pairwise
else:
    def pairwise(a):
        return zip(a, a[1:])
try:
    from typing import TypeAlias
except ImportError:
    TypeAlias = None
try:
    batched = itertools.batched
except AttributeError:
    batched = None
def anext(a):
    return next(a)
def f(a, b, flags: Optional[int], exc, *args):
    traceback.format_exception(type(exc), exc, exc.__traceback__)
    traceback.format_exception_only(type(exc), exc)
    traceback.print_exception(*args)
    b.to_bytes(2, "little"), int.from_bytes(b, byteorder="big")
    mask = (a > 0) | (b < 1) | flags
    getattr(sys, "stdlib_module_names", ())
    isinstance(a, (int, str)), {**a} | b
    return anext(a), Union[int, None], list(zip(a, b))
"""


def test_the_python_3_9_check_catches_newer_code(tmp_path):
    newer = tmp_path / "newer.py"
    newer.write_text(NEWER)
    problems = python39_problems(newer)
    flagged = sorted({int(problem.split(":")[1]) for problem in problems})
    assert flagged == [1, 5, 6, 7, 9, 10, 11, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23], problems
    assert len(problems) == 19, problems                # line 13: zip(strict=) and isinstance(x, A | B)
    guarded = tmp_path / "guarded.py"
    guarded.write_text(GUARDED)
    assert python39_problems(guarded) == []
    matching = tmp_path / "matching.py"
    matching.write_text("match 1:\n    case 1:\n        pass\n")
    assert "not Python 3.9 syntax" in python39_problems(matching)[0]
    lazy = tmp_path / "lazy.py"
    lazy.write_text("from __future__ import annotations\ndef f(x: int | None) -> list[int] | None:\n    return None\n")
    assert python39_problems(lazy) == []


@pytest.mark.skipif(not hasattr(tokenize, "FSTRING_START"), reason="older Pythons do not parse these at all")
def test_the_python_3_9_check_catches_newer_fstrings(tmp_path):
    newer = tmp_path / "fstrings.py"
    newer.write_text('a = f"{d["k"]}"\nb = f"{chr(10).join(x)!r:>{w}}"\nc = f\'{"\\n".join(x)}\'\n'
                     'd = f"{x # note\n}"\ne = f"""{x\n} {"y"}"""\nf = f"{f\'{x}\'}"\ng = f\'{f"{\'k\'}"}\'\n')
    problems = python39_problems(newer)
    assert [int(problem.split(":")[1]) for problem in problems] == [1, 3, 4, 4, 9], problems   # 4: # and line break


def public_reach(root, depth=4):
    """Every object a behaviour reaches from ``root`` through public attributes (no leading underscore)."""
    seen, frontier, found = {id(root)}, [root], []
    for _ in range(depth):
        next_frontier = []
        for obj in frontier:
            names = list(getattr(obj, "__dict__", {})) + list(getattr(type(obj), "__dataclass_fields__", {}))
            for name in names:
                if name.startswith("_"):
                    continue
                value = getattr(obj, name, None)
                if id(value) not in seen and not isinstance(value, (int, float, str, bytes, type(None))):
                    seen.add(id(value))
                    found.append((name, value))
                    next_frontier.append(value)
        frontier = next_frontier
    return found


def test_a_simulated_robot_reaches_no_simulator_state_through_public_attributes(make_scenario):
    # A behaviour holding its robot must not find the step's frame (every robot's poses and readings),
    # the world or the simulation by walking public attributes: a real robot has none of them.
    from sim_backend.hal import PairColumns, SensorFrame
    from sim_backend.runner import Simulation
    from sim_backend.world import World

    sim = Simulation(make_scenario(robots={"count": 3, "spawn": {"x": [0, 0.5], "y": [0, 0.5]}}))
    sim.step()
    leaks = [(name, type(value).__name__) for robot in sim.robots for name, value in public_reach(robot)
             if isinstance(value, (SensorFrame, PairColumns, World, Simulation))]
    assert leaks == []


def test_the_reach_walk_finds_a_public_frame():
    class Device:
        def __init__(self, frame):
            self.frame = frame

    class Holder:
        def __init__(self, device):
            self.device = device

    frame = object.__new__(type("SensorFrame", (), {}))
    assert ("frame", frame) in public_reach(Holder(Device(frame)))
