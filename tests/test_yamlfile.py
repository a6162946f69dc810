"""The one YAML reader behind scenarios, studies, lab configs and calibrations."""
from pathlib import Path

import pytest
import yaml

from onboard.config import ConfigError
from onboard.yamlfile import parse_yaml, read_yaml
from sim_backend.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]


def test_numbers_read_as_yaml_1_2_does():
    data = parse_yaml("a: 1e6\nb: -3e-1\nc: 010\nd: 0o10\ne: 0x1F\nf: 1:30\ng: .inf\nh: 2.5\ni: -7\nj: '1e6'\n", "x")
    assert data == {"a": 1e6, "b": -0.3, "c": 10, "d": 8, "e": 31, "f": "1:30", "g": float("inf"), "h": 2.5,
                    "i": -7, "j": "1e6"}
    assert isinstance(data["c"], int) and isinstance(data["a"], float)


def test_a_key_given_twice_names_both_lines():
    with pytest.raises(ConfigError) as caught:
        parse_yaml("robots:\n  count: 6\n  count: 3\n", "mine.yaml")
    assert str(caught.value) == "mine.yaml:3: not valid YAML (the key 'count' is given twice (first on line 2))"
    merged = parse_yaml("base: &b {count: 6, radius: 1}\nrobots:\n  <<: *b\n  count: 3\n", "x")
    assert merged["robots"] == {"count": 3, "radius": 1}        # a merge key may be overridden


def test_a_folder_or_a_file_that_is_not_text_is_named(tmp_path):
    with pytest.raises(ConfigError, match="is a folder, not a file") as caught:
        read_yaml(tmp_path, "--config")
    assert caught.value.field == "--config"
    latin = tmp_path / "latin.yaml"
    latin.write_bytes(b"name: caf\xe9\n")
    with pytest.raises(ConfigError, match="latin.yaml: not a text"):
        read_yaml(latin)
    (tmp_path / "dir.yaml").mkdir()
    with pytest.raises(ConfigError, match="dir.yaml is a folder"):
        load_scenario(str(tmp_path / "dir.yaml"))
    (tmp_path / "my-runs").mkdir()                 # a folder without .yaml was `no such file`
    with pytest.raises(ConfigError, match="my-runs is a folder, not a file"):
        load_scenario(str(tmp_path / "my-runs"))
    (tmp_path / "empty.yaml").write_text("# nothing yet\n")
    with pytest.raises(ConfigError, match="empty.yaml: the file is empty"):
        load_scenario(str(tmp_path / "empty.yaml"))


@pytest.mark.parametrize("text", ["[" * 5000 + "]" * 5000, "a: " + "{a: " * 5000 + "1" + "}" * 5000,
                                  "".join("  " * i + f"k{i}:\n" for i in range(3000)) + "  " * 3000 + "1\n"],
                         ids=["json-lists", "flow-mappings", "block-mappings"])
def test_a_file_nested_thousands_deep_is_refused_naming_it(text):
    """PyYAML recurses once per level: it ended in Python's 'maximum recursion depth exceeded', naming nothing."""
    with pytest.raises(ConfigError) as caught:
        parse_yaml(text, "deep.yaml")
    assert caught.value.field == "deep.yaml"
    assert caught.value.problem.startswith("lists or mappings nested too deeply to read")


@pytest.mark.parametrize("path", sorted(p.relative_to(ROOT) for folder in ("sim_backend", "hub", "docs", "calibration")
                                        for p in (ROOT / folder).rglob("*.y*ml")), ids=str)
def test_every_yaml_file_we_ship_reads_the_same_as_before(path):
    text = (ROOT / path).read_text(encoding="utf-8")
    assert parse_yaml(text, path.name) == yaml.safe_load(text)


@pytest.mark.parametrize("text, problem", [
    ('seed: !!int "abc"', "cannot read 'abc' as an integer"),
    ('seed: !!int ""', "cannot read '' as an integer"),
    ('seed: !!int "-"', "cannot read '-' as an integer"),
    ('seed: !!float "abc"', "cannot read 'abc' as a number"),
    ('seed: !!float ""', "cannot read '' as a number"),
    ('static: !!bool "maybe"', "cannot read 'maybe' as true or false"),
    ("description: 2024-02-30", "cannot read '2024-02-30' as a date (day is out of range for month); put it in "
                                "quotes if it is not one"),
    ("path: !!set [1]", "cannot read a list as !!set"),
    ("seed: " + "9" * 5000, "an integer written with 5000 characters is too long to read (at most 4300 digits)"),
])
def test_a_value_its_tag_cannot_read_is_refused_at_its_line(text, problem):
    """Each raised the converter's own ValueError (KeyError, IndexError), a traceback naming no file."""
    with pytest.raises(ConfigError) as caught:
        parse_yaml("name: x\n" + text + "\n", "mine.yaml")
    assert str(caught.value) == f"mine.yaml:2: {problem}"


@pytest.mark.parametrize("name, text", [("study.yaml", "name: x\nscenarios: [lab-6]\nreps: !!int x\n"),
                                        ("lab.yaml", "source: {type: sim, seed: !!int x}\n"),
                                        ("cal.yaml", "proximity: []\nrobot: !!int x\n")])
def test_every_kind_of_file_names_itself_and_the_line(tmp_path, name, text):
    from hub.config import load_config
    from onboard.drivers.calibration import load_calibration
    from sim_backend.study.study_file import load_study_file

    path = tmp_path / name
    path.write_text(text)
    load = {"study.yaml": load_study_file, "lab.yaml": load_config, "cal.yaml": load_calibration}[name]
    with pytest.raises(ConfigError) as caught:
        load(path)
    line = text.count("\n")      # the last line of each
    assert str(caught.value) == f"{path}:{line}: cannot read 'x' as an integer"


@pytest.mark.parametrize("text", ["null\n", "~\n", "# nothing but\nNull\n", "--- null\n"])
def test_a_file_holding_only_null_is_said_so_not_called_empty(tmp_path, text):
    """It was "the file is empty", which sent the user looking for a lost copy of a file that holds a word."""
    path = tmp_path / "null.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as caught:
        read_yaml(path)
    assert str(caught.value) == f"{path}: the file holds only null, not a mapping of keys"


@pytest.mark.parametrize("text", ["", "# only a comment\n", "---\n", "---\n...\n"])
def test_an_empty_file_or_document_is_still_none(tmp_path, text):
    path = tmp_path / "empty.yaml"
    path.write_text(text)
    assert read_yaml(path) is None
