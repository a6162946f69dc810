"""An evaluator registered under a name no behaviour has (a typo of the behaviour's name) judged nothing, and no
run said why its result.json lacked the evaluator's fields."""
import json
import re
import sys

import pytest

from khepri_cli.main import main

BEHAVIOUR = '''
from onboard.behaviour import Behaviour, register


@register("sweeper")
class Sweeper(Behaviour):
    def step(self) -> None:
        self.robot.wheels.set_speeds(0.1, 0.1)
'''

EVALUATOR = '''
from sim_backend.metrics import Evaluator, register_evaluator


@register_evaluator("{name}")
class SweeperEvaluator(Evaluator):
    def on_step(self, time_s, telemetry):
        pass

    def result(self):
        return {{"swept": 1}}
'''

SCENARIO = """name: sweep
behaviour: sweeper
robots: {count: 2, spawn: {x: [-0.5, 0.5], y: [-0.5, 0.5]}}
time_limit_s: 1
"""


@pytest.fixture
def folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", list(sys.path))
    (tmp_path / "sweeper.py").write_text(BEHAVIOUR)
    (tmp_path / "sweep.yaml").write_text(SCENARIO)
    modules = ["sweeper"]
    yield modules
    for module in modules:
        sys.modules.pop(module, None)


def test_an_evaluator_for_a_name_no_behaviour_has_is_warned_about(folder, tmp_path, capsys):
    (tmp_path / "sweeper_eval_typo.py").write_text(EVALUATOR.format(name="swepper"))
    folder.append("sweeper_eval_typo")
    assert main(["--import", "sweeper", "--import", "sweeper_eval_typo", "sim", "run", "sweep.yaml", "--no-plot",
                 "--out", "out"]) == 0
    err = capsys.readouterr().err
    said = re.search(r"khepri: warning: --import: sweeper_eval_typo\.SweeperEvaluator is registered to judge "
                     r"'swepper', which is no behaviour's name \(known: (.*)\): no run is judged by it\n", err)
    assert said and "sweeper" in said.group(1).split(", "), err     # other tests' behaviours may be known too
    assert "swept" not in json.loads((tmp_path / "out" / "result.json").read_text())


def test_an_evaluator_for_the_behaviour_is_not_warned_about(folder, tmp_path, capsys):
    (tmp_path / "sweeper_eval.py").write_text(EVALUATOR.format(name="sweeper"))
    folder.append("sweeper_eval")
    assert main(["--import", "sweeper_eval", "--import", "sweeper", "sim", "run", "sweep.yaml", "--no-plot",
                 "--out", "out"]) == 0
    assert "warning" not in capsys.readouterr().err
    assert json.loads((tmp_path / "out" / "result.json").read_text())["swept"] == 1
