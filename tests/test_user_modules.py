"""`--import`: the user's behaviour module, loaded the same way by `khepri`, study workers and the agents that
`khepri sil` starts (the behaviour must run unchanged from simulation to the lab stack)."""
import dataclasses
import json
import re
import sys

import numpy as np
import pytest

import hub.sil
from khepri_cli.main import main
from onboard.config import ConfigError
from onboard.plugins import import_user_modules

DRIVE_BEHAVIOUR = '''
from dataclasses import dataclass

from onboard.behaviour import Behaviour, register


@dataclass
class DriveParams:
    speed_m_s: float = 0.1


@register("{name}")
class Drive(Behaviour):
    Params = DriveParams

    def step(self) -> None:
        self.robot.wheels.set_speeds(self.params.speed_m_s, self.params.speed_m_s)
'''

SCENARIO = """name: drive
behaviour: {name}
robots: {{count: 3, spawn: {{x: [-0.5, 0.5], y: [-0.5, 0.5]}}}}
arena: {{walls: [-3, -3, 3, 3]}}
time_limit_s: 3
"""


@pytest.fixture(autouse=True)
def restore_sys_path(monkeypatch):
    """import_user_modules puts the user's folder first on sys.path, as it must in the process it runs in. A test's
    folder left there (one holds a random.py) was inherited by later tests' study workers, which imported it in
    place of the standard library's random and died: test_behaviour_errors failed when run after this file."""
    monkeypatch.setattr(sys, "path", list(sys.path))


def test_a_module_name_a_file_path_and_what_goes_wrong(tmp_path, monkeypatch):
    (tmp_path / "lab").mkdir()
    (tmp_path / "lab" / "plugin_by_path.py").write_text("LOADED = True\n")
    (tmp_path / "lab" / "flock7.yaml").write_text("name: flock7\n")     # a scenario given to --import
    (tmp_path / "plugin_by_name.py").write_text("LOADED = True\n")
    (tmp_path / "plugin_broken.py").write_text("x = (\n")
    (tmp_path / "plugin_raises.py").write_text("1 / 0\n")
    import_user_modules(["plugin_by_name", "lab/plugin_by_path.py"], str(tmp_path))
    assert sys.modules["plugin_by_name"].LOADED and sys.modules["plugin_by_path"].LOADED
    for name, problem in [("plugin_broken", f"plugin_broken.py:1: {syntax_error_message('x = (')}"),
                          ("no_such_plugin", "cannot import 'no_such_plugin': No module named 'no_such_plugin'"),
                          ("lab/absent.py", f"no such file: {tmp_path / 'lab' / 'absent.py'}"),
                          ("lab/", f"{tmp_path / 'lab'} is a folder: give the .py file"),
                          ("lab/flock7.yaml", "flock7.yaml is not a .py file: --import takes the Python file"),
                          (".relative", "'.relative' is neither a module name"),
                          ("", "'' is neither a module name")]:
        with pytest.raises(ConfigError) as caught:
            import_user_modules([name], str(tmp_path))
        assert caught.value.field == "--import" and problem in caught.value.problem, caught.value
    # The module's own bug: one line with its place (it was a raw traceback, which outputs.md says is khepri's)
    with pytest.raises(ConfigError, match=r"importing 'plugin_raises' raised ZeroDivisionError: division by zero "
                                          r"at plugin_raises\.py:1"):
        import_user_modules(["plugin_raises"], str(tmp_path))
    (tmp_path / "plugin_clash.py").write_text(DRIVE_BEHAVIOUR.format(name="transport"))
    with pytest.raises(ConfigError, match="'transport' is taken by onboard.behaviours.transport.+plugin_clash.Drive"):
        import_user_modules(["plugin_clash"], str(tmp_path))     # the user's module is told, not the built-in


def test_a_non_python_file_beside_is_said_not_a_py_file_and_a_module_that_exits_is_named(tmp_path):
    """`--import lab6copy.yaml` (no folder part) was read as the module lab6copy's submodule yaml: "No module named
    'lab6copy'"; a module calling sys.exit(3) as it was imported made khepri exit 3 without a word."""
    (tmp_path / "lab6copy.yaml").write_text("name: lab6copy\n")
    (tmp_path / "notes.txt").write_text("x\n")
    (tmp_path / "quits.py").write_text("import sys\n\nsys.exit(3)\n")
    for name, problem in [("lab6copy.yaml", "lab6copy.yaml is not a .py file: --import takes the Python file"),
                          ("notes.txt", "notes.txt is not a .py file"),
                          ("absent.yaml", f"no such file: {tmp_path / 'absent.yaml'}"),
                          ("quits", "importing 'quits' called sys.exit(3) at quits.py:3: a behaviour's module must "
                                    "not exit when imported (put a script's own code under if __name__ == "
                                    "\"__main__\":)")]:
        with pytest.raises(ConfigError) as caught:
            import_user_modules([name], str(tmp_path))
        assert caught.value.field == "--import" and caught.value.problem.startswith(problem), caught.value


@pytest.mark.parametrize("name, shown", [("3", "3"), ("None", "None"), ('""', "''"), ('"  "', "'  '")])
def test_a_behaviour_name_that_is_no_name_is_refused_where_it_is_registered(tmp_path, name, shown):
    """@register(3) was taken, and a later unknown-behaviour error became "Scenario.validate raised TypeError: '<'
    not supported between instances of 'int' and 'str'" (sorting the names); @register("") was taken too."""
    (tmp_path / "oddname.py").write_text(f"from onboard.behaviour import Behaviour, register\n\n\n@register({name})\n"
                                         "class Odd(Behaviour):\n    def step(self):\n        pass\n")
    with pytest.raises(ConfigError) as caught:
        import_user_modules(["oddname"], str(tmp_path))
    assert str(caught.value) == (f"register: @register({shown}) above oddname.Odd: a behaviour's name must be a "
                                 "non-empty string, e.g. @register(\"wander\")")
    sys.modules.pop("oddname", None)


def syntax_error_message(source: str) -> str:
    """What this Python says of ``source``: 3.10 made "unexpected EOF while parsing" "'(' was never closed"."""
    try:
        compile(source, "broken.py", "exec")
    except SyntaxError as err:
        return err.msg
    raise AssertionError(f"{source!r} compiles")


def test_sil_agents_import_the_users_behaviour_and_run_it(tmp_path, monkeypatch, capsys):
    (tmp_path / "sil_drive.py").write_text(DRIVE_BEHAVIOUR.format(name="sil-drive"))
    (tmp_path / "drive.yaml").write_text(SCENARIO.format(name="sil-drive"))
    monkeypatch.chdir(tmp_path)
    assert main(["--import", "sil_drive.py", "sil", "drive.yaml", "--out", "out", "--no-plot", "--no-record"]) == 0
    arrays = np.load(tmp_path / "out" / "trajectory.npz")
    moved = np.hypot(*(arrays["robot_pose"][-1, :, :2] - arrays["robot_pose"][0, :, :2]).T)
    assert moved.min() > 0.2, moved                   # 3 s at 0.1 m/s: every agent ran the user's behaviour


def test_sil_stops_with_the_reason_when_an_agent_cannot_start_the_run(tmp_path, monkeypatch, capsys):
    (tmp_path / "sil_lonely.py").write_text(DRIVE_BEHAVIOUR.format(name="sil-lonely"))
    (tmp_path / "lonely.yaml").write_text(SCENARIO.format(name="sil-lonely"))
    monkeypatch.chdir(tmp_path)
    spawn = hub.sil.spawn_agents
    monkeypatch.setattr(hub.sil, "spawn_agents",       # agents without it
                        lambda *args: spawn(*args[:-1], dataclasses.replace(args[-1], imports=[])))
    assert main(["--import", "sil_lonely", "sil", "lonely.yaml", "--out", "out", "--no-plot", "--no-record"]) == 1
    err = capsys.readouterr().err
    assert "agent 0: cannot start the run: run.behaviour: unknown behaviour 'sil-lonely'" in err
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    assert result["stop_reason"] == "crashed" and result["sim_time_s"] < 1.0


# --- mistakes in a behaviour module ---------------------------------------------------------------------------

def test_finished_written_as_a_method_is_refused_where_it_is_registered(tmp_path):
    """As a method (no @property) it is always truthy: every run ended after its first step, 'finished'."""
    module = tmp_path / "early.py"
    method = "\n    def finished(self):\n        return False\n"
    module.write_text(DRIVE_BEHAVIOUR.format(name="early_finisher") + method)
    with pytest.raises(ConfigError, match=r"early\.Drive\.finished must be a property: put @property above"):
        import_user_modules([str(module)])


def test_a_broken_module_in_the_behaviours_folder_does_not_take_the_others_down(tmp_path):
    """A syntax error in a behaviour being written gave a traceback on every command, built-in scenarios too."""
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    broken = root / "onboard" / "behaviours" / f"zz_test_broken_{tmp_path.name[-12:].replace('-', '_')}.py"
    broken.write_text("from onboard.behaviour import register\n\n\ndef half_written(:\n")
    try:
        run = subprocess.run([sys.executable, "-m", "khepri_cli.main", "sim", "run", "lab-6", "--time-limit", "1",
                              "--no-plot", "--out", str(tmp_path / "out")], capture_output=True, text=True,
                             cwd=tmp_path, env={"PYTHONPATH": str(root), "PATH": "/usr/bin:/bin"}, timeout=120)
    finally:
        broken.unlink()
    assert run.returncode == 0, run.stderr
    assert f"khepri: warning: onboard/behaviours/{broken.name} did not import" in run.stderr
    assert "SyntaxError" in run.stderr and "line 4" in run.stderr and "Traceback" not in run.stderr


HANGS_AT_STEP_5 = DRIVE_BEHAVIOUR + '''
    def stop(self) -> None:
        self.robot.wheels.stop()

    @property
    def finished(self) -> bool:
        return False


class Hangs(Drive):
    """Robot 0 waits in its fifth step for ever (a 'wait for a message' loop); the others drive on."""

    def step(self) -> None:
        import time

        self.steps = getattr(self, "steps", 0) + 1
        while self.robot.id == 0 and self.steps >= 5:
            time.sleep(0.01)
        super().step()


register("{name}-hangs")(Hangs)
'''


def test_sil_ends_as_crashed_when_an_agent_stops_answering(tmp_path, monkeypatch, capsys):
    """A hung agent was written off by the lockstep, and the run went on to its time limit: exit 0."""
    (tmp_path / "sil_hangs.py").write_text(HANGS_AT_STEP_5.format(name="sil-drive2"))
    (tmp_path / "hangs.yaml").write_text(SCENARIO.format(name="sil-drive2-hangs").replace("time_limit_s: 3",
                                                                                          "time_limit_s: 30"))
    monkeypatch.chdir(tmp_path)
    assert main(["--import", "sil_hangs.py", "sil", "hangs.yaml", "--out", "out", "--no-plot"]) == 1
    err = capsys.readouterr().err
    assert "khepri: error: agent 0 stopped answering (3 frames in a row, 2 s each): the behaviour's step() has run " \
           "for " in err
    # The agent's own step watchdog, from its log; in lockstep it leaves the simulated wheels to the hub.
    assert "s: lockstep: its simulated wheels wait for it; a robot's would stop here" in err
    # How long step() has run when the hub gives up (3 frames of 2 s), not the 0.26 s of the agent's first note.
    running = re.search(r"step\(\) has run for ([0-9.]+) s, since t = 0\.4 s: lockstep", err)
    assert running and 5.9 <= float(running.group(1)) < 10.0, err
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    assert result["stop_reason"] == "crashed" and result["sim_time_s"] < 2.0
    # The figures the clean runs' tests find at 0 (tests/test_sil.py) count the three unanswered frames here.
    assert result["sil"]["step_timeouts"] >= 3 and result["sil"]["missing_answers"] >= 3, result["sil"]
    # The recording says why sil ended the run: `log info` said only "stopped by sil: not completed".
    assert main(["log", "info", "out/hub.mcap", "--json"]) == 0
    run, = json.loads(capsys.readouterr().out)["runs"]
    assert run["end_note"].startswith("crashed: agent 0 stopped answering (3 frames in a row"), run
    assert main(["log", "info", "out/hub.mcap"]) == 0
    assert re.search(r"stopped [0-9:]+ by sil \(crashed: agent 0 stopped answering", capsys.readouterr().out)


def test_a_realtime_sil_ends_as_crashed_when_an_agent_stops_answering(tmp_path, monkeypatch, capsys):
    """With --realtime the hung agent's robot only went silent, and the run went on to its time limit: exit 0."""
    (tmp_path / "sil_hangs_rt.py").write_text(HANGS_AT_STEP_5.format(name="sil-drive3"))
    (tmp_path / "hangs.yaml").write_text(SCENARIO.format(name="sil-drive3-hangs").replace("time_limit_s: 3",
                                                                                          "time_limit_s: 30"))
    monkeypatch.chdir(tmp_path)
    assert main(["--import", "sil_hangs_rt.py", "sil", "hangs.yaml", "--realtime", "--out", "out", "--no-plot",
                 "--no-record"]) == 1
    err = capsys.readouterr().err
    said = re.search(r"khepri: error: agent 0 stopped answering \(([0-9.]+) s without a message\): the behaviour's "
                     r"step\(\) has run for ", err)
    assert said and 6.0 <= float(said.group(1)) < 10.0, err
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    assert result["stop_reason"] == "crashed" and result["sim_time_s"] < 15.0


def test_the_values_of_a_dict_parameter_are_checked(tmp_path):
    """`Dict[str, float]` params took {a: x} without a word: the behaviour met the string mid-run."""
    from onboard.behaviour import build_params, get_behaviour

    module = tmp_path / "weighted.py"
    module.write_text(DRIVE_BEHAVIOUR.replace("speed_m_s: float = 0.1", "speed_m_s: float = 0.1\n"
                                              "    weights: Dict[str, float] = field(default_factory=dict)")
                      .replace("from dataclasses import dataclass", "from dataclasses import dataclass, field\n"
                               "from typing import Dict").format(name="weighted"))
    import_user_modules([str(module)])
    cls = get_behaviour("weighted")
    assert build_params(cls, {"weights": {"a": 1, "b": 0.5}}).weights == {"a": 1.0, "b": 0.5}
    with pytest.raises(ConfigError, match=r"params\.weights\.a: must be a number \(got 'x'\)"):
        build_params(cls, {"weights": {"a": "x"}})


def test_a_file_whose_name_is_taken_is_refused_not_swapped_for_the_other_module(tmp_path):
    """--import path/random.py silently imported the standard library's random, and a second wander.py
    elsewhere was silently skipped."""
    (tmp_path / "random.py").write_text(DRIVE_BEHAVIOUR.format(name="not-random"))
    with pytest.raises(ConfigError, match=r"random\.py: the module name 'random' is taken by .*random\.py; "
                                          r"rename the file"):
        import_user_modules([str(tmp_path / "random.py")])
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    for folder in ("a", "b"):
        (tmp_path / folder / "twin_walk.py").write_text(DRIVE_BEHAVIOUR.format(name=f"twin-{folder}"))
    import_user_modules([str(tmp_path / "a" / "twin_walk.py")])
    import_user_modules([str(tmp_path / "a" / "twin_walk.py")])          # the same file again: fine
    with pytest.raises(ConfigError, match=r"b/twin_walk\.py: the module name 'twin_walk' is taken by .*a/twin_walk"):
        import_user_modules([str(tmp_path / "b" / "twin_walk.py")])



def test_a_module_name_that_imports_something_else_or_registers_nothing_is_said(tmp_path, monkeypatch):
    """`--import random` next to the user's random.py imported the standard library's random, silently."""
    (tmp_path / "random.py").write_text(DRIVE_BEHAVIOUR.format(name="not-random-either"))
    with pytest.raises(ConfigError, match=r"--import: 'random' imports .*random\.py \(the standard library\), "
                                          r"not .*/random\.py; rename random\.py"):
        import_user_modules(["random"], str(tmp_path))
    (tmp_path / "no_register.py").write_text("from onboard.behaviour import Behaviour\n\n\n"
                                             "class Forgot(Behaviour):\n    def step(self):\n        pass\n")
    warnings = import_user_modules(["no_register"], str(tmp_path))
    assert warnings == [f"no_register: imported {tmp_path / 'no_register.py'}, which registers no behaviour "
                        '(@register("name") above a Behaviour class)']
    assert import_user_modules(["no_register"], str(tmp_path)) == []      # imported already: nothing new to say

@pytest.mark.parametrize("stdlib_names", ["sys.stdlib_module_names", "without it, as on Python 3.9"])
def test_a_standard_library_name_is_told_on_every_python(tmp_path, monkeypatch, stdlib_names):
    """Python 3.9 has no sys.stdlib_module_names: `--import random` beside the user's random.py did not say that
    it was the standard library's, and a file named like a standard module not loaded yet (tabnanny.py) was
    imported under that name, in place of the standard library's."""
    if stdlib_names.startswith("without"):
        monkeypatch.delattr(sys, "stdlib_module_names", raising=False)
    elif not hasattr(sys, "stdlib_module_names"):
        pytest.skip("Python 3.9 has no sys.stdlib_module_names")
    (tmp_path / "random.py").write_text(DRIVE_BEHAVIOUR.format(name="not-random-at-all"))
    with pytest.raises(ConfigError, match=r"'random' imports .*random\.py \(the standard library\), not "):
        import_user_modules(["random"], str(tmp_path))
    assert "tabnanny" not in sys.modules
    (tmp_path / "tabnanny.py").write_text(DRIVE_BEHAVIOUR.format(name="not-tabnanny"))
    with pytest.raises(ConfigError, match=r"tabnanny\.py: 'tabnanny' is a standard library module's name; rename"):
        import_user_modules([str(tmp_path / "tabnanny.py")], str(tmp_path))
    assert "tabnanny" not in sys.modules


def test_a_bug_in_a_params_validate_is_one_line_with_its_place(tmp_path):
    module = tmp_path / "typo_params.py"
    module.write_text(DRIVE_BEHAVIOUR.replace("speed_m_s: float = 0.1", "speed_m_s: float = 0.1\n\n"
                                              "    def validate(self, where):\n"
                                              "        if self.sped_m_s > 1:\n            pass")
                      .format(name="typo-params"))
    from onboard.behaviour import build_params, get_behaviour

    import_user_modules([str(module)])
    with pytest.raises(ConfigError, match=r"^params: DriveParams\.validate raised AttributeError: .*'sped_m_s' "
                                          r"at typo_params\.py:\d+$"):
        build_params(get_behaviour("typo-params"), {})


def test_import_may_also_follow_the_command(tmp_path, monkeypatch):
    """`khepri sim run drive.yaml --import late_drive` was refused ("unrecognized arguments") while `khepri
    agent ... --import` is how a robot takes it."""
    (tmp_path / "late_drive.py").write_text(DRIVE_BEHAVIOUR.format(name="late-drive"))
    (tmp_path / "drive.yaml").write_text(SCENARIO.format(name="late-drive"))
    monkeypatch.chdir(tmp_path)
    assert main(["sim", "run", "drive.yaml", "--import", "late_drive", "--time-limit", "1", "--no-plot",
                 "--out", "out"]) == 0
    assert json.loads((tmp_path / "out" / "result.json").read_text())["behaviour"] == "late-drive"


@pytest.mark.parametrize("decorator, cls, said", [
    ('""', "E(Evaluator)", "@register_evaluator('') above {m}.E: the name must be the behaviour's, a non-empty string"),
    ("3", "E(Evaluator)", "@register_evaluator(3) above {m}.E: the name must be the behaviour's, a non-empty string"),
    ('"mine"', "E", "@register_evaluator('mine') above {m}.E: the class must subclass sim_backend.metrics.Evaluator"),
    ('"transport"', "E(Evaluator)", "the behaviour 'transport' is judged by sim_backend.transport_metrics."
                                    "TransportEvaluator already; {m}.E cannot judge it too"),
])
def test_register_evaluator_refuses_what_no_run_could_use(tmp_path, capsys, decorator, cls, said):
    """It took any name and any class: @register_evaluator(3) could never be named, a class without on_step or
    result failed in the middle of a run, and a user's "transport" evaluator was silently replaced by the
    built-in one (or replaced it) depending on which was imported first."""
    module = f"evaluator_{abs(hash(said)) % 10 ** 8}"
    (tmp_path / f"{module}.py").write_text("from sim_backend.metrics import Evaluator, register_evaluator\n\n\n"
                                           f"@register_evaluator({decorator})\nclass {cls}:\n    pass\n")
    assert main(["--import", str(tmp_path / f"{module}.py"), "sim", "list"]) == 2
    assert capsys.readouterr().err == f"khepri: error: register_evaluator: {said.format(m=module)}\n"


def test_a_behaviour_module_that_imports_the_simulator_is_warned_about(tmp_path, capsys):
    """It ran in `sim run` and `sil` and would fail only on a robot, which has onboard/ alone. An evaluator's
    module (no behaviour in it) may import the simulator."""
    (tmp_path / "peeking.py").write_text(DRIVE_BEHAVIOUR.format(name="peeking") + "\n\ndef later():\n"
                                         "    from sim_backend.runner import Simulation\n    return Simulation\n")
    (tmp_path / "my_eval.py").write_text("from sim_backend.metrics import Evaluator, register_evaluator\n\n\n"
                                         "@register_evaluator('peeking')\nclass PeekingEvaluator(Evaluator):\n"
                                         "    pass\n")
    warnings = import_user_modules(["peeking", "my_eval"], str(tmp_path))
    assert warnings == ["peeking: registers the behaviour peeking and imports sim_backend: it runs in simulation "
                        "but will fail on a robot, which has only onboard/ (put an evaluator in a module of its own)"]
    # A helper module beside it that imports the simulator fails on the robot all the same: it was not warned.
    (tmp_path / "peek_helper.py").write_text("import pymunk\nfrom peek_deeper import x\n")
    (tmp_path / "peek_deeper.py").write_text("import hub.sil\nfrom peek_helper import *\nx = 1\n")    # a cycle
    (tmp_path / "helped.py").write_text(DRIVE_BEHAVIOUR.format(name="helped") + "\nimport peek_helper\n")
    assert import_user_modules(["helped"], str(tmp_path)) == [
        "helped: registers the behaviour helped and imports pymunk (in peek_helper.py), hub (in peek_deeper.py): it "
        "runs in simulation but will fail on a robot, which has only onboard/ (put an evaluator in a module of its "
        "own)"]
    (tmp_path / "peeking_cli.py").write_text(DRIVE_BEHAVIOUR.format(name="peeking-cli") + "import hub.sil\n")
    assert main(["--import", str(tmp_path / "peeking_cli.py"), "sim", "list"]) == 0
    assert "khepri: warning: --import " + str(tmp_path / "peeking_cli.py") + ": registers the behaviour " \
        "peeking-cli and imports hub:" in capsys.readouterr().err


@pytest.mark.parametrize("stdlib_names", ["sys.stdlib_module_names", "without it, as on Python 3.9"])
def test_a_behaviour_module_that_imports_a_lab_pc_package_is_warned_about(tmp_path, monkeypatch, stdlib_names):
    """A behaviour importing mcap, dask or scipy (installed with khepri on the lab PC) ran in `sim run` and `sil`
    without a word and failed only on a robot, which has the standard library, numpy, pyzmq, pyyaml and
    filterpy. Its own helper module beside it, and what a robot has, are fine. Python 3.9 has no
    sys.stdlib_module_names, and said nothing: the standard library is then told by where a module lives."""
    if stdlib_names.startswith("without"):
        monkeypatch.delattr(sys, "stdlib_module_names", raising=False)
    elif not hasattr(sys, "stdlib_module_names"):
        pytest.skip("Python 3.9 has no sys.stdlib_module_names")
    (tmp_path / "pc_helper.py").write_text("GAIN = 2\n")
    (tmp_path / "pc_only.py").write_text(DRIVE_BEHAVIOUR.format(name="pc-only") + "\nimport json\nimport numpy\n"
                                         "import filterpy\nimport pc_helper\nfrom zmq import Context\n"
                                         "import sys, math, _thread, asyncio, xml.dom, email.mime, sqlite3, "
                                         "ctypes, zipimport\n\n\n"
                                         "def later():\n    import mcap.reader\n    return mcap\n")
    try:
        warnings = import_user_modules(["pc_only"], str(tmp_path))
    finally:
        sys.modules.pop("pc_only", None)
        sys.modules.pop("pc_helper", None)
    assert warnings == ["pc_only: registers the behaviour pc-only and imports mcap, which a robot does not have "
                        "(it has the standard library, numpy, pyzmq, pyyaml and filterpy): it runs in simulation "
                        "but will fail on a robot unless installed there too"]


def test_a_behaviour_written_for_a_newer_python_than_the_robots_is_warned_about(tmp_path):
    """A behaviour with `match` or `speed: float | None` in its Params ran in `sim run` and `sil` here without a
    word, and would fail at import on a robot with Python 3.9."""
    import textwrap

    from onboard.plugins import syntax_after_python_39

    union = tmp_path / "union_params.py"
    union.write_text("from __future__ import annotations\n" + DRIVE_BEHAVIOUR.format(name="union-params")
                     + "\n\ndef gain(x: float | None = None) -> float:\n    return x or 1.0\n")
    assert syntax_after_python_39(str(union)) == ("uses `X | Y` in a type annotation at union_params.py:21 (write "
                                                  "Optional[X] or Union[X, Y] from typing)")
    matching = tmp_path / "matching.py"
    matching.write_text(textwrap.dedent("""\
        def pick(x):
            match x:
                case 0:
                    return 1


        def after():
            return 2
        """))      # the parser gave up at `def after` (line 7): the match is what to point at
    assert syntax_after_python_39(str(matching)).startswith("uses syntax of a newer Python at matching.py:2 (")
    plain = tmp_path / "plain.py"
    plain.write_text(DRIVE_BEHAVIOUR.format(name="plain") + "\n\ndef size(x: 'int | None', y: list[int]) -> int:\n"
                     "    return 1 if x | 1 else 0\n")      # a string annotation, list[int] and | in code: all 3.9's
    assert syntax_after_python_39(str(plain)) is None
    try:
        warnings = import_user_modules(["union_params"], str(tmp_path))
    finally:
        sys.modules.pop("union_params", None)
    assert warnings == ["union_params: registers the behaviour union-params and uses `X | Y` in a type annotation at "
                        "union_params.py:21 (write Optional[X] or Union[X, Y] from typing), which Python 3.9 "
                        "cannot run: it runs here but will fail on a robot with Python 3.9 (khepri's onboard code "
                        "keeps to 3.9)"]
