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
