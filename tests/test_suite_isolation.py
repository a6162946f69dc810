"""The test suite's own hygiene: what one test module registers must not reach the tests of another."""
import json
import subprocess
import sys
from pathlib import Path

TESTS = Path(__file__).resolve().parent

IMPORT_EVERY_TEST_MODULE = """
import importlib, json, pathlib, sys
sys.path.insert(0, sys.argv[1])
from onboard.behaviour import _REGISTRY, behaviour_names
from sim_backend import metrics
behaviours, evaluators = set(behaviour_names()), set(metrics._EVALUATORS)
for path in sorted(pathlib.Path(sys.argv[1]).glob("test_*.py")):
    importlib.import_module(path.stem)
print(json.dumps({"behaviours": sorted(set(_REGISTRY) - behaviours),
                  "evaluators": sorted(set(metrics._EVALUATORS) - evaluators)}))
"""


def test_importing_a_test_module_registers_no_behaviour_or_evaluator():
    """pytest imports every test module before it runs any test. test_agent.py registered "test-explode" as it
    was imported, so the behaviours known in every later test depended on which files the session collected
    first: test_scenarios.py's expected message, built as it was imported, listed it or not, and
    `pytest tests/test_scenarios.py tests/test_agent.py` failed. Register in a fixture that unregisters."""
    done = subprocess.run([sys.executable, "-c", IMPORT_EVERY_TEST_MODULE, str(TESTS)], capture_output=True,
                          text=True, timeout=120, cwd=TESTS.parent)
    assert done.returncode == 0, done.stderr[-2000:]
    assert json.loads(done.stdout.splitlines()[-1]) == {"behaviours": [], "evaluators": []}
