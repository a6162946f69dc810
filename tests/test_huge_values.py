"""A huge value in a file (an alias bomb, a pasted text) gets a short error line, and quickly."""
import time
from pathlib import Path

import pytest

from hub.config import load_config
from onboard.config import SHOWN_CHARS, ConfigError, as_written
from onboard.drivers.calibration import load_calibration
from onboard.yamlfile import parse_yaml
from sim_backend.scenario import load_scenario
from sim_backend.study.study_file import load_study_file


def alias_bomb(levels: int) -> str:
    """``levels`` lists of nine aliases to the level below: 9**levels strings in a few hundred bytes."""
    text = "&a0 [x, x, x, x, x, x, x, x, x]"
    for level in range(1, levels):
        text = f"&a{level} [{text}" + f", *a{level - 1}" * 8 + "]"
    return text


def test_a_long_value_is_shown_by_its_start_and_its_length():
    shown = as_written(list(range(10_000)))
    assert shown.startswith("a list of 10000 items: [0, 1, 2, ") and shown.endswith("...")
    assert len(shown) < SHOWN_CHARS + 40
    assert as_written("x" * 10**6) == repr("x" * SHOWN_CHARS)[:SHOWN_CHARS] + "..."
    assert as_written({"a": [1, 2]}) == "{'a': [1, 2]}"            # short values as before
    assert as_written(10**5000) == "an integer of 5001 digits"     # str() refuses it (4300 digits at most)
    assert as_written(None) == "null" and as_written([True]) == "[True]"


def test_a_value_that_holds_itself_is_shown_without_a_loop():
    loop: list = []
    loop.append(loop)
    assert as_written(loop).endswith("...")


def test_an_alias_bomb_below_the_bound_is_shown_in_one_short_line_at_once(tmp_path):
    """Four levels of nine aliases made one error line of 34 KB; nine levels ran for minutes into MemoryError."""
    for field, problem in (("robots: {count: %s}", "robots.count: must be an integer (got a list of 9 items: [[[["),
                           ("name: %s", "name: must be a string (got a list of 9 items: [[[[")):
        path = tmp_path / "bomb.yaml"
        path.write_text(field % alias_bomb(6) + "\n")          # 531441 values: under the loader's bound
        started = time.monotonic()
        with pytest.raises(ConfigError) as caught:
            load_scenario(str(path))
        assert time.monotonic() - started < 5
        assert str(caught.value).startswith(problem) and len(str(caught.value)) < 200


@pytest.mark.parametrize("kind, text", [
    ("scenario", "robots: {count: %s}\n"),
    ("study", "name: %s\nscenarios: [lab-6]\nreps: 1\n"),
    ("study", "scenarios: [lab-6]\nreps: 1\noverrides: {robots.count: [%s]}\n"),
    ("lab", "source: {type: motioncapture, system: mock, bodies: {kh0: %s}}\n"),
    ("calibration", "notes: %s\nproximity: []\n"),
])
def test_an_alias_bomb_is_refused_at_its_line_before_anything_walks_it(tmp_path, kind, text):
    path = tmp_path / "bomb.yaml"
    path.write_text(text % alias_bomb(9))
    load = {"scenario": lambda p: load_scenario(str(p)), "study": load_study_file, "lab": load_config,
            "calibration": load_calibration}[kind]
    started = time.monotonic()
    with pytest.raises(ConfigError) as caught:
        load(path)
    assert time.monotonic() - started < 5
    assert str(caught.value).startswith(f"{path}:")
    assert "expands through its aliases to more than 1,000,000 values (an alias bomb?)" in str(caught.value)


def test_a_list_that_holds_itself_is_refused():
    with pytest.raises(ConfigError, match=r"^loop.yaml:2: an alias refers to a list or mapping that holds it"):
        parse_yaml("name: x\npath: &p [[0, 0, 0], *p]\n", "loop.yaml")


@pytest.mark.parametrize("text, problem", [
    ("scenarios: %s\nreps: 1\n", "scenarios: must be a non-empty list of scenario names or files (got"),
    ("scenarios: [lab-6]\nseeds: [%s]\n", "seeds[0]: must be an integer >= 0 (got"),
    ("scenarios: [lab-6]\nreps: 1\ntime_limit_s: %s\n", "time_limit_s: must be a number of seconds > 0 (got"),
    ("scenarios: [lab-6]\nreps: 1\noverrides: %s\n", "overrides: must be a mapping of scenario key -> list of values"),
])
def test_a_study_shows_a_long_value_by_its_start(tmp_path, text, problem):
    path = tmp_path / "study.yaml"
    path.write_text(text % ("'" + "y" * 100_000 + "'"))
    with pytest.raises(ConfigError) as caught:
        load_study_file(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: {problem}") and "(got 'yyy" in message and len(message) < 300


@pytest.mark.parametrize("text, field", [
    ("source: {type: %s}\n", "source.type: must be one of sim, motioncapture, replay (got 'zzz"),
    ("source: {type: motioncapture, system: mock, bodies: {kh0: %s}}\n",
     "source.bodies.kh0: must be an integer robot id 0..999999 (got 'zzz"),
    ("source: {type: motioncapture, system: mock, bodies: {kh0: 0}, options: {rigid_bodies: %s}}\n",
     "source.options.rigid_bodies: entry 1 ('zzz"),
])
def test_a_lab_config_shows_a_long_value_by_its_start(tmp_path, text, field):
    path = tmp_path / "lab.yaml"
    path.write_text(text % ("'" + "z" * 100_000 + "'"))
    with pytest.raises(ConfigError) as caught:
        load_config(path)
    assert str(caught.value).startswith(f"{path}: {field}") and len(str(caught.value)) < 400


def test_a_motion_capture_option_must_be_text_or_a_number(tmp_path):
    """Each is passed on as str(value): a list was written out whole, as Python shows it."""
    path = tmp_path / "lab.yaml"
    path.write_text("source: {type: motioncapture, system: vicon, bodies: {kh0: 0}, options: {hostname: [a, b]}}\n")
    with pytest.raises(ConfigError, match=r"source.options.hostname: must be a string or a number, passed to the "
                                          r"motion-capture library as text \(got \['a', 'b'\]\)"):
        load_config(path)


def test_a_source_type_that_is_a_list_is_said_so(tmp_path):
    """`type: [sim]` ended in TypeError: unhashable type: 'list'."""
    path = tmp_path / "lab.yaml"
    path.write_text("source: {type: [sim]}\n")
    with pytest.raises(ConfigError, match=r"source.type: must be a string \(got \['sim'\]\)"):
        load_config(path)


def test_a_long_unknown_key_or_scenario_name_is_cut(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text("? " + "k" * 10_000 + "\n: 1\n")     # a plain key may be 1024 characters long
    with pytest.raises(ConfigError) as caught:
        load_scenario(str(path))
    assert caught.value.field == "k" * SHOWN_CHARS + "..."
    path.write_text("object: {shape: '" + "s" * 10_000 + "'}\n")
    with pytest.raises(ConfigError) as caught:
        load_scenario(str(path))
    assert len(str(caught.value)) < 200
    with pytest.raises(ConfigError) as caught:
        load_scenario("n" * 200)
    assert len(str(caught.value)) < 200


def test_a_long_behaviour_name_is_cut(tmp_path):
    path = Path(tmp_path) / "s.yaml"
    path.write_text("behaviour: '" + "b" * 100_000 + "'\n")
    with pytest.raises(ConfigError) as caught:
        load_scenario(str(path))
    assert str(caught.value).startswith("behaviour: unknown behaviour 'bbb") and len(str(caught.value)) < 400
