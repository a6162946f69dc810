"""The types a behaviour's Params may declare, as a scenario's `params` sets them: what Python's typing lets a
user write for a parameter (`Literal["a", "b"]` for a mode, `float | None` on the PC's Python) is read, and a
type the reader has no rule for is said to be the behaviour's, not the scenario's, mistake."""
import sys

import pytest

from onboard.behaviour import build_params, get_behaviour
from onboard.config import ConfigError
from onboard.plugins import import_user_modules

MODES = '''
from dataclasses import dataclass
from typing import Literal, Optional

from onboard.behaviour import Behaviour, register


@dataclass
class ModesParams:
    mode: Literal["sweep", "hold"] = "sweep"
    level: Literal[1, 2, 3] = 1
    maybe: Optional[Literal["x"]] = None
    anything: object = None


@register("modes-{tag}")
class Modes(Behaviour):
    Params = ModesParams

    def step(self) -> None:
        self.robot.wheels.stop()
'''


@pytest.fixture(autouse=True)
def restore_sys_path(monkeypatch):
    monkeypatch.setattr(sys, "path", list(sys.path))


def _load(tmp_path, source, name):
    module = tmp_path / f"{name.replace('-', '_')}.py"
    module.write_text(source)
    import_user_modules([str(module)])
    return get_behaviour(name)


def test_a_literal_parameter_takes_its_values_and_names_them_when_wrong(tmp_path):
    """`mode: Literal["sweep", "hold"]` was `params.mode: unsupported type Literal` for any value, a right one
    too: the scenario looked wrong, and the behaviour's own type was to blame."""
    cls = _load(tmp_path, MODES.replace("{tag}", "lit"), "modes-lit")
    params = build_params(cls, {"mode": "hold", "level": 3.0, "maybe": "x"})
    assert (params.mode, params.level, params.maybe) == ("hold", 3, "x")
    assert build_params(cls, {"maybe": None}).maybe is None
    with pytest.raises(ConfigError, match=r"^params\.mode: must be one of 'sweep', 'hold' \(got 'swep'\)$"):
        build_params(cls, {"mode": "swep"})
    with pytest.raises(ConfigError, match=r"^params\.level: must be one of 1, 2, 3 \(got 4\)$"):
        build_params(cls, {"level": 4})
    with pytest.raises(ConfigError, match=r"^params\.level: must be one of 1, 2, 3 \(got true\)$"):
        build_params(cls, {"level": True})       # True == 1 in Python, not in a scenario


def test_a_type_no_scenario_can_set_is_said_to_be_the_behaviours(tmp_path):
    cls = _load(tmp_path, MODES.replace("{tag}", "obj"), "modes-obj")
    with pytest.raises(ConfigError) as err:
        build_params(cls, {"anything": [1]})
    assert str(err.value) == ("params.anything: ModesParams.anything is declared as object, a type a scenario "
                              "cannot give (use bool, int, float, str, Literal, Optional, List, Tuple, Dict or a "
                              "dataclass)")


@pytest.mark.skipif(sys.version_info < (3, 10), reason="`X | Y` is evaluated only from Python 3.10 on")
def test_a_union_written_with_a_bar_is_read_on_the_pcs_python(tmp_path):
    """`limit: float | None` was `params.limit: unsupported type float | None`, while the --import warning said
    that such a behaviour runs here and fails only on a robot."""
    source = MODES.replace("{tag}", "bar").replace(
        '    anything: object = None\n', '    limit: float | None = None\n    names: list[str] | None = None\n')
    cls = _load(tmp_path, "from __future__ import annotations\n" + source, "modes-bar")
    params = build_params(cls, {"limit": 2, "names": ["a"]})
    assert (params.limit, params.names) == (2.0, ["a"])
    assert build_params(cls, {"limit": None}).limit is None
    with pytest.raises(ConfigError, match=r"^params\.limit: must be a number \(got 'x'\)$"):
        build_params(cls, {"limit": "x"})


NO_PARAMS = '''
from dataclasses import dataclass

from onboard.behaviour import Behaviour, register


@dataclass
class EmptyParams:
    pass


@register("noparams-{tag}")
class Forgot(Behaviour):
    {params}

    def step(self) -> None:
        self.robot.wheels.stop()
'''


def test_params_given_to_a_behaviour_without_any_name_the_behaviour_not_an_empty_list(tmp_path):
    """A behaviour whose author forgot `Params = WanderParams` was told `params.speed_m_s: unknown key (known: )`,
    which points at the scenario; the line says that the behaviour declares no parameters, and how to give it
    some."""
    forgot = _load(tmp_path, NO_PARAMS.replace("{tag}", "forgot").replace("{params}", "pass"), "noparams-forgot")
    with pytest.raises(ConfigError, match=r"^params\.speed_m_s: unknown key: behaviour Forgot sets no Params "
                                          r"\(class attribute `Params = <a dataclass of its parameters>`\)$"):
        build_params(forgot, {"speed_m_s": 0.1})
    empty = _load(tmp_path, NO_PARAMS.replace("{tag}", "empty").replace("{params}", "Params = EmptyParams"),
                  "noparams-empty")
    with pytest.raises(ConfigError, match=r"^params\.k: unknown key: behaviour Forgot has no parameters "
                                          r"\(EmptyParams has no fields\)$"):
        build_params(empty, {"k": 1})
    assert build_params(forgot, {}) is not None and build_params(empty, None) is not None
