"""Software in the loop, end to end: the hub's sim source and one real agent process per robot over loopback
CURVE sockets run lab-6 and lab-6-payload in lockstep; evaluated like `khepri sim run`, with the MCAP log beside it."""
import json

import numpy as np
import pytest

from hub.recording import read_log
from hub.sil import SilOptions, run_sil
from sim_backend.scenario import load_scenario


@pytest.mark.parametrize("name", ["lab-6", "lab-6-payload"])
def test_sil_lab6_cages_and_reaches_every_waypoint(tmp_path, name):
    scenario = load_scenario(name)
    result = run_sil(scenario, tmp_path, SilOptions(plot=False))
    print(json.dumps({k: v for k, v in result.items() if k != "waypoints"}, indent=1))
    assert "error" not in result
    assert result["caged"] is True and result["completed"] is True, result["failures"]
    assert [w["index"] for w in result["waypoints"]] == list(range(len(scenario.path)))
    assert result["final_position_error_m"] <= 0.05
    sil = result["sil"]
    assert sil["lockstep"] and sil["agents"] == 6 and sil["agent_exit_codes"] == [0] * 6
    assert sil["step_timeouts"] == 0 and sil["missing_answers"] == 0
    assert sil["dropped"]["hub_rejected"] == {} and sil["dropped"]["frames_lost_at_agents"] == 0
    assert result["radio"]["delivered"] > 0

    saved = json.loads((tmp_path / "result.json").read_text())
    assert saved["caged"] is True and saved["sil"]["latency_ms"]["p50"] > 0
    arrays = np.load(tmp_path / "trajectory.npz")
    assert arrays["robot_pose"].shape == (len(arrays["t"]), 6, 3)
    topics = {record.topic for record in read_log(tmp_path / "hub.mcap")}
    assert {"/mocap/poses", "/robot/0/frame", "/robot/5/telemetry", "/robot/3/broadcast", "/robot/1/command",
            "/control"} <= topics
