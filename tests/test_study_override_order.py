"""A study file whose override keys are written in another order is the same study: its runs resume."""
import csv

from khepri_cli.main import main

STUDY = "name: order\nscenarios: [lab-6]\nseeds: [1]\ntime_limit_s: 1\noverrides:\n{keys}"
DROP, SPACING = "  comm.drop: [0.1]\n", "  params.inter_robot_distance_m: [0.4]\n"


def test_reordering_the_override_keys_resumes_the_same_cells(tmp_path, capsys):
    """The cell's folder is named by its overrides in the order the file lists them: after moving one key above
    another, every finished run was run again into a second folder, and report.md and summary.csv showed the
    one cell twice."""
    study, out = tmp_path / "order.yaml", tmp_path / "out"
    study.write_text(STUDY.format(keys=DROP + SPACING), encoding="utf-8")
    assert main(["study", str(study), "--out", str(out), "--workers", "1", "--no-figures"]) == 0
    first = sorted(p.name for p in out.iterdir() if p.is_dir())
    study.write_text(STUDY.format(keys=SPACING + DROP), encoding="utf-8")
    capsys.readouterr()
    assert main(["study", str(study), "--out", str(out), "--dry-run"]) == 0
    assert "0 to run, 1 finished" in capsys.readouterr().out
    assert main(["study", str(study), "--out", str(out), "--workers", "1", "--no-figures"]) == 0
    assert "ran 0 runs (0 failed), skipped 1 finished" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == first == ["lab-6@comm.drop=0.1@params.inter_robot_"
                                                                           "distance_m=0.4"]
    with open(out / "summary.csv", newline="", encoding="utf-8") as stream:
        assert {row["cell"] for row in csv.DictReader(stream)} == set(first)
    assert "have no result yet" not in (out / "report.md").read_text(encoding="utf-8")
