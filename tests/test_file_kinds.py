"""A khepri file of one kind given where another is expected is said as such, naming the file."""
import dataclasses

import pytest

from hub.config import LabConfig, load_config
from onboard.config import ConfigError
from onboard.drivers.calibration import IRCalibration, load_calibration
from onboard.filekinds import CALIBRATION, KINDS, LAB_CONFIG, SCENARIO, STUDY
from sim_backend.scenario import Scenario, load_scenario
from sim_backend.study.study_file import STUDY_KEYS, load_study_file

FILES = {
    SCENARIO: "name: mine\nbehaviour: transport\nrobots: {count: 4}\nobject: {shape: circle, radius: 0.2}\n",
    STUDY: "name: ok\nscenarios: [lab-6]\nreps: 1\n",
    LAB_CONFIG: "source: {type: sim, scenario: lab-6}\nsecurity: {insecure: true}\n",
    CALIBRATION: "robot: 3\nproximity: [" + ", ".join(["{ambient: 0, touch: 1000}"] * 8) + "]\n",
}
LOADERS = {SCENARIO: lambda path: load_scenario(str(path)), STUDY: load_study_file, LAB_CONFIG: load_config,
           CALIBRATION: load_calibration}
DOING = {SCENARIO: "run it with `khepri sim run FILE`", STUDY: "run it with `khepri study FILE`",
         LAB_CONFIG: "start a hub with it: `khepri hub --config FILE`",
         CALIBRATION: "an agent reads it: `khepri agent --driver kh4 --calibration FILE`"}


def test_the_lists_of_keys_are_the_records_own():
    """The lists are written out for the robots' sake (the calibration loader runs there without the hub)."""
    assert KINDS[SCENARIO][0] == {f.name for f in dataclasses.fields(Scenario)}
    assert KINDS[STUDY][0] == set(STUDY_KEYS)
    assert KINDS[LAB_CONFIG][0] == {f.name for f in dataclasses.fields(LabConfig) if f.init}
    assert KINDS[CALIBRATION][0] == {f.name for f in dataclasses.fields(IRCalibration)}


@pytest.mark.parametrize("given, expected", [(given, expected) for given in FILES for expected in FILES
                                             if given != expected])
def test_a_file_of_another_kind_is_named_and_said_to_be_that_kind(tmp_path, given, expected):
    """`sim run study.yaml` said `scenarios: unknown key (known: arena, ...)`, `hub --config scenario.yaml`
    `description: unknown key`: neither the file nor what it was."""
    path = tmp_path / "file.yaml"
    path.write_text(FILES[given])
    with pytest.raises(ConfigError) as caught:
        LOADERS[expected](path)
    assert str(caught.value).startswith(f"{path}: this is a {given}, not a {expected}: {DOING[given]}")


def test_each_file_loads_as_its_own_kind(tmp_path):
    for kind, text in FILES.items():
        path = tmp_path / f"{kind.replace(' ', '-')}.yaml"
        path.write_text(text)
        LOADERS[kind](path)


@pytest.mark.parametrize("text, field", [
    ("robots: {count: 4}\nnotes: my first run\n", "notes"),    # robots is a lab config's too: no calibration
    ("behaviour: transport\nseeds: [1, 2]\n", "seeds"),        # a scenario with a study's key: a typo
    ("seeds: [1]\n", None),                                    # nothing of a scenario's: a study
])
def test_one_stray_key_does_not_rename_a_scenario(tmp_path, text, field):
    path = tmp_path / "s.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as caught:
        load_scenario(str(path))
    if field is None:
        assert "this is a study, not a scenario" in str(caught.value)
    else:
        assert caught.value.field == field and caught.value.problem.startswith("unknown key")
