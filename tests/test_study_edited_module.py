"""A long-lived Dask worker (``--executor dask:ADDRESS``) and a user's ``--import`` module edited between studies."""
import json
from pathlib import Path

import pytest

from khepri_cli.main import main

BEHAVIOUR = """
from dataclasses import dataclass

from onboard.behaviour import Behaviour, register


@dataclass
class EditedParams:
    speed: float = 0.0


@register("edited")
class Edited(Behaviour):
    Params = EditedParams

    def step(self):
        raise RuntimeError("{version}")
"""
SCENARIO = """name: edited-1
behaviour: edited
robots: {count: 1, spawn: {x: [-1, 1], y: [-1, 1]}}
arena: {walls: [-2, -2, 2, 2]}
time_limit_s: 1
"""


@pytest.fixture
def cluster():
    """A real LocalCluster of one single-threaded worker process, used as a lab's scheduler would be."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as local:
        yield local.scheduler_address


def errors(out: Path):
    return [json.loads(path.read_text())["error"] for path in sorted(out.glob("*/seed-*/result.json"))]


def test_a_dask_worker_runs_the_users_module_as_it_is_now_not_as_it_was_first_imported(tmp_path, monkeypatch,
                                                                                          cluster):
    """The worker process kept the module it imported for the first study: after the user fixed their behaviour,
    the next study on the same scheduler ran the old code (and the driver's warning told them to give every
    worker the same commit, which they had)."""
    monkeypatch.chdir(tmp_path)
    module = tmp_path / "edited_behaviour.py"
    (tmp_path / "edited.yaml").write_text(SCENARIO)
    study = tmp_path / "study.yaml"
    study.write_text("name: edited\nscenarios: [edited.yaml]\nseeds: [1]\n")
    module.write_text(BEHAVIOUR.replace("{version}", "version one"))
    command = ["--import", str(module), "study", str(study), "--executor", f"dask:{cluster}", "--no-figures"]
    assert main(command + ["--out", str(tmp_path / "first")]) == 1
    assert ["robot 0, step(): RuntimeError: version one" in e for e in errors(tmp_path / "first")] == [True]
    module.write_text(BEHAVIOUR.replace("{version}", "version two"))
    assert main(command + ["--out", str(tmp_path / "second")]) == 1
    assert ["robot 0, step(): RuntimeError: version two" in e for e in errors(tmp_path / "second")] == [True]
    sha = {json.loads(p.read_text())["study"]["behaviour_sha1"] for p in tmp_path.glob("*/*/seed-1/result.json")}
    assert len(sha) == 2        # each run's fingerprint is of the code it ran
