"""Telemetry near the wire's size limit: `sim run` refuses what an agent could not send the hub, counting the
whole message the agent sends (its loop statistics, clock, counters, run id and driver), not only the
behaviour's part, so that a run that passes in simulation does not stop every agent in `sil` or the lab."""
import json

import pytest

from khepri_cli.main import main
from onboard.protocol import MAX_MESSAGE_BYTES, encode

PADDED = '''
from dataclasses import dataclass

from onboard.behaviour import Behaviour, register


@dataclass
class PaddedParams:
    chars: int = 10


@register("padded")
class Padded(Behaviour):
    Params = PaddedParams

    def step(self) -> None:
        self.robot.wheels.stop()

    def telemetry(self):
        return {"pad": "x" * self.params.chars}
'''

SCENARIO = """name: padded-{bug}
behaviour: padded
params: {{chars: {bug}}}
robots: {{count: 1}}
time_limit_s: 0.5
"""


@pytest.fixture
def padded(user_behaviour):
    return user_behaviour("padded_behaviour", PADDED, SCENARIO)


def chars_for(message_bytes: int) -> int:
    """How many characters of padding make the old, bare check's message this many bytes."""
    bare = len(encode({"type": "telemetry", "id": 0, "step": 0, "mode": "run",
                       "behaviour": {"pad": "", "finished": False}}))
    return message_bytes - bare


def test_telemetry_an_agent_cannot_send_fails_in_sim_run_as_in_sil(padded, tmp_path, capsys):
    """150 bytes short of the limit passed `sim run` (the check encoded a bare message), and in `sil` every
    agent refused it: `telemetry() cannot be sent: message of 65720 bytes exceeds 65536`."""
    scenario = padded(str(chars_for(MAX_MESSAGE_BYTES - 150)))
    assert main(["--import", "padded_behaviour", "sil", scenario, "--no-plot", "--no-record", "--out", "sil"]) == 1
    assert "telemetry() cannot be sent: message of" in capsys.readouterr().err
    assert main(["--import", "padded_behaviour", "sim", "run", scenario, "--no-plot", "--out", "sim"]) == 1
    err = capsys.readouterr().err
    assert "robot 0, telemetry(): ValueError: the hub could not be sent this telemetry" in err, err
    assert json.loads((tmp_path / "sim" / "result.json").read_text())["stop_reason"] == "crashed"


def test_telemetry_that_fits_with_the_agents_fields_still_runs(padded, capsys):
    scenario = padded(str(chars_for(MAX_MESSAGE_BYTES - 1000)))
    assert main(["--import", "padded_behaviour", "sim", "run", scenario, "--no-plot", "--out", "sim"]) == 0
