"""``khepri study FILE --time-limit S`` against a study whose cells override time_limit_s."""
from pathlib import Path

from khepri_cli.main import main


def test_time_limit_flag_is_refused_when_the_cells_override_time_limit_s(tmp_path, capsys):
    """The study file's own time_limit_s beside an override of it is refused, but --time-limit was not: the cells
    lab-6@time_limit_s=20 and lab-6@time_limit_s=40 both ran 30 s, and summary.csv and report.md named them by
    limits they never ran with."""
    study = tmp_path / "limits.yaml"
    study.write_text("name: limits\nscenarios: [lab-6]\nreps: 1\noverrides:\n  time_limit_s: [20, 40]\n",
                     encoding="utf-8")
    out = tmp_path / "out"
    assert main(["study", str(study), "--time-limit", "30", "--out", str(out), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert "khepri: error: --time-limit: " in err and "overrides.time_limit_s" in err
    assert not out.exists()
    # Listed cells too, and only when a cell has the key.
    listed = tmp_path / "listed.yaml"
    listed.write_text("name: listed\nscenarios: [lab-6]\nreps: 1\noverrides: [{}, {time_limit_s: 9}]\n",
                      encoding="utf-8")
    assert main(["study", str(listed), "--time-limit", "30", "--out", str(out), "--dry-run"]) == 2
    assert "khepri: error: --time-limit: " in capsys.readouterr().err
    assert main(["study", str(study), "--out", str(out), "--dry-run"]) == 0


def test_time_limit_flag_still_replaces_the_scenarios_own_limit(tmp_path, capsys):
    study = tmp_path / "plain.yaml"
    study.write_text("name: plain\nscenarios: [lab-6]\nreps: 1\noverrides:\n  comm.drop: [0.0, 0.1]\n",
                     encoding="utf-8")
    assert main(["study", str(study), "--time-limit", "30", "--out", str(Path(tmp_path, "o")), "--dry-run"]) == 0
    assert "time limit 30 s" in capsys.readouterr().out
