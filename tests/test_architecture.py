"""The architecture rules that keep behaviours portable to real robots."""
import ast
from pathlib import Path

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


# What runs on a robot keeps to Python 3.9 (see README): its syntax, and the 3.10+ features that parse on 3.9
# but fail when the module is imported there. This machine has no 3.9 interpreter, so the check reads the code.
NEW_TYPING_NAMES = {"TypeAlias", "ParamSpec", "Concatenate", "TypeGuard", "Self", "Never", "LiteralString",
                    "Required", "NotRequired", "Unpack", "TypeVarTuple", "assert_never", "reveal_type", "override",
                    "dataclass_transform"}
NEW_MODULES = {"tomllib"}
NEW_DATACLASS_OPTIONS = {"slots", "kw_only", "match_args"}


def python39_problems(path: Path):
    source = path.read_text()
    try:
        tree = ast.parse(source, filename=str(path), feature_version=(3, 9))
    except SyntaxError as error:
        return [f"{path.name}:{error.lineno}: not Python 3.9 syntax: {error.msg}"]
    lazy_annotations = any(isinstance(node, ast.ImportFrom) and node.module == "__future__"
                           and any(alias.name == "annotations" for alias in node.names) for node in tree.body)
    return [f"{path.name}:{node.lineno}: {problem}" for node in ast.walk(tree)
            for problem in _python310_features(node, lazy_annotations)]


def _annotations(node):
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
        arguments = node.args.posonlyargs + node.args.args + node.args.kwonlyargs
        return [argument.annotation for argument in arguments] + [node.returns]
    return [node.annotation] if isinstance(node, ast.AnnAssign) else []


def _python310_features(node, lazy_annotations):
    if not lazy_annotations:
        for annotation in _annotations(node):
            if annotation is not None and any(isinstance(part, ast.BinOp) and isinstance(part.op, ast.BitOr)
                                              for part in ast.walk(annotation)):
                yield "an 'X | Y' annotation needs 'from __future__ import annotations' on 3.9"
    if isinstance(node, ast.Call):
        name = getattr(node.func, "id", getattr(node.func, "attr", ""))
        keywords = {keyword.arg for keyword in node.keywords}
        if name == "zip" and "strict" in keywords:
            yield "zip(strict=) is Python 3.10+"
        if name == "dataclass" and keywords & NEW_DATACLASS_OPTIONS:
            yield f"dataclass({', '.join(sorted(keywords & NEW_DATACLASS_OPTIONS))}=) is Python 3.10+"
        if name == "isinstance" and len(node.args) == 2 and isinstance(node.args[1], ast.BinOp):
            yield "isinstance(x, A | B) is Python 3.10+"
    if isinstance(node, ast.ImportFrom) and node.module == "typing":
        yield from (f"typing.{alias.name} is not in Python 3.9" for alias in node.names
                    if alias.name in NEW_TYPING_NAMES)
    modules = ([alias.name for alias in node.names] if isinstance(node, ast.Import)
               else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
    yield from (f"module {module} is not in Python 3.9" for module in modules
                if module.split(".")[0] in NEW_MODULES)


def test_onboard_code_runs_on_python_3_9():
    offenders = [problem for path in sorted((ROOT / "onboard").rglob("*.py")) for problem in python39_problems(path)]
    assert offenders == []


def test_the_python_3_9_check_catches_newer_code(tmp_path):
    newer = tmp_path / "newer.py"
    newer.write_text("import tomllib\nfrom dataclasses import dataclass\nfrom typing import TypeAlias\n"
                     "@dataclass(slots=True)\nclass A:\n    x: int | None = None\n"
                     "def f(a, b):\n    return list(zip(a, b, strict=True)), isinstance(a, int | str)\n")
    problems = python39_problems(newer)
    assert len(problems) == 6, problems
    matching = tmp_path / "matching.py"
    matching.write_text("match 1:\n    case 1:\n        pass\n")
    assert "not Python 3.9 syntax" in python39_problems(matching)[0]
    lazy = tmp_path / "lazy.py"
    lazy.write_text("from __future__ import annotations\ndef f(x: int | None) -> list[int] | None:\n    return None\n")
    assert python39_problems(lazy) == []


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
