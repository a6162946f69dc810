"""`--set KEY=VALUE` on `sim run`, `sim show` and `sil`: one field of a scenario changed from the command line,
as a study's overrides change it, recorded in result.json, and every mistake one line naming --set."""
import json

import pytest
import yaml

from khepri_cli.main import main


def test_sim_run_uses_the_values_set_and_records_them(tmp_path, capsys):
    assert main(["sim", "run", "lab-6", "--set", "robots.count=8", "--set", "params.cruise_speed_m_s=0.15",
                 "--time-limit", "2", "--no-plot", "--out", str(tmp_path / "run")]) == 0
    result = json.loads((tmp_path / "run" / "result.json").read_text())
    assert result["robots"] == 8 and result["scenario"] == "lab-6"
    assert result["settings"] == {"robots.count": 8, "params.cruise_speed_m_s": 0.15}
    assert main(["sim", "run", "lab-6", "--time-limit", "2", "--no-plot", "--out", str(tmp_path / "plain")]) == 0
    plain = json.loads((tmp_path / "plain" / "result.json").read_text())
    assert plain["robots"] == 6 and "settings" not in plain


def test_sim_show_prints_the_scenario_with_the_values_set(capsys):
    assert main(["sim", "show", "lab-6", "--set", "params.travel_speed_m_s=0.2", "--set", "object.mass=2.5"]) == 0
    shown = yaml.safe_load(capsys.readouterr().out)
    assert shown["params"]["travel_speed_m_s"] == 0.2 and shown["object"]["mass"] == 2.5


@pytest.mark.parametrize("setting, said", [
    ("cruise", "--set: must be KEY=VALUE with a dotted KEY into the scenario"),
    ("=1", "--set: must be KEY=VALUE"),
    ("params..x=1", "--set: must be KEY=VALUE"),
    ("params.x=[1,", "--set params.x: the value '[1,' is not YAML"),
    ("robots.count.x=2", "--set robots.count.x: robots.count is not a mapping"),
    ("params.cruise_sped=0.1", "--set: params.cruise_sped: unknown key (known: "),
    ("params.cruise_speed_m_s=fast", "--set: params.cruise_speed_m_s: must be a number (got 'fast')"),
    ("robots.count=0", "--set: robots.count: "),
])
def test_a_bad_setting_is_one_line_naming_it(setting, said, tmp_path, capsys):
    assert main(["sim", "run", "lab-6", "--set", setting, "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"khepri: error: {said}") and err.count("\n") == 1, err
    assert not (tmp_path / "run").exists()


def test_sil_runs_the_scenario_with_the_values_set(tmp_path, capsys):
    assert main(["sil", "lab-6", "--set", "robots.count=4", "--time-limit", "3", "--no-record", "--no-plot",
                 "--out", str(tmp_path / "sil")]) == 0
    result = json.loads((tmp_path / "sil" / "result.json").read_text())
    assert result["robots"] == 4 and len(result["sil"]["agent_exit_codes"]) == 4
    assert result["settings"] == {"robots.count": 4}
