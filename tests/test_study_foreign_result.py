"""A result.json copied into another seed's folder is not that seed's run: a resume runs the seed again."""
import json
import shutil

from khepri_cli.main import main

STUDY = "name: seeds\nscenarios: [lab-6]\nseeds: [1, 2]\ntime_limit_s: 1\n"


def test_a_result_json_of_another_seed_is_run_again_and_said(tmp_path, capsys):
    """Before, any valid result.json marked its folder's run finished: seed 1's result copied into seed-2 made
    the study skip seed 2 for good, and the report count seed 1's numbers twice."""
    study, out = tmp_path / "seeds.yaml", tmp_path / "out"
    study.write_text(STUDY, encoding="utf-8")
    assert main(["study", str(study), "--out", str(out), "--workers", "1", "--no-figures"]) == 0
    shutil.copyfile(out / "lab-6" / "seed-1" / "result.json", out / "lab-6" / "seed-2" / "result.json")
    main(["study", "report", str(out), "--no-figures"])
    assert "- `lab-6/seed-2/result.json`" in (out / "report.md").read_text(encoding="utf-8")   # not seed 2's
    capsys.readouterr()
    assert main(["study", str(study), "--out", str(out), "--dry-run"]) == 0
    assert "1 to run, 1 finished" in capsys.readouterr().out
    assert main(["study", str(study), "--out", str(out), "--workers", "1", "--no-figures"]) == 0
    said = capsys.readouterr()
    assert "ran 1 run (0 failed), skipped 1 finished" in said.out
    assert f"warning: 1 result.json in {out} (lab-6/seed-2) is another seed's and will be replaced: that run " \
           "runs again" in said.err
    assert json.loads((out / "lab-6" / "seed-2" / "result.json").read_text(encoding="utf-8"))["seed"] == 2
    assert "lab-6/seed-2" not in (out / "report.md").read_text(encoding="utf-8")
