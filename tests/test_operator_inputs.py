"""Operator mistakes on the command line that used to wait for ever or mislead (found by following docs/lab.md)."""
import subprocess
import sys

import pytest

from onboard.agent.link import hub_endpoint, load_robot_keys
from onboard.config import ConfigError


@pytest.mark.parametrize("hub", ["", "   "])
def test_an_empty_hub_is_refused(hub):
    """`--hub "$HUB"` with HUB unset made tcp://:5560, which ZeroMQ takes and never reaches: the agent waited for
    ever and `ctl` timed out as if no hub ran."""
    with pytest.raises(ConfigError, match="--hub: is empty"):
        hub_endpoint(hub, 5560)


@pytest.mark.parametrize("hub", ["tcp://:5560", "tcp://  :5560"])
def test_a_whole_address_without_a_host_is_refused(hub):
    with pytest.raises(ConfigError, match="has no host"):
        hub_endpoint(hub, 5560)


def test_ctl_and_agent_refuse_an_empty_hub_at_once():
    ctl = subprocess.run([sys.executable, "-m", "khepri_cli.main", "ctl", "status", "--hub", "", "--port", "6499",
                          "--timeout", "30"], capture_output=True, text=True, timeout=60)
    assert ctl.returncode == 2 and "--hub: is empty" in ctl.stderr, ctl.stderr
    agent = subprocess.run([sys.executable, "-m", "onboard.agent", "--id", "0", "--driver", "sim", "--hub", "",
                            "--port", "6499"], capture_output=True, text=True, timeout=60)
    assert agent.returncode == 2 and "--hub: is empty" in agent.stderr, agent.stderr


def test_a_robot_without_its_key_is_told_to_copy_or_add_it_not_to_init(tmp_path):
    """`keys init` on a lab that has keys refuses (hub.key exists), so pointing a robot there was a dead end."""
    (tmp_path / "robots").mkdir()
    (tmp_path / "hub.key").write_text("")
    with pytest.raises(ConfigError) as err:
        load_robot_keys(tmp_path, 3)
    assert "robot-3.key_secret: copy it from the lab PC's key folder" in str(err.value)
    assert "khepri keys add KEYS --robots 3," in str(err.value) and "keys init" not in str(err.value)
    (tmp_path / "hub.key").unlink()
    (tmp_path / "robots" / "robot-3.key_secret").write_text("")
    with pytest.raises(ConfigError, match="hub.key: copy hub.key from the lab PC"):
        load_robot_keys(tmp_path, 3)


@pytest.mark.parametrize("record", ["logs/run-{tim}.mcap", "logs/run-{Time}.mcap", "run-{ time }.mcap"])
def test_a_mistyped_time_placeholder_in_record_is_refused(record, tmp_path, monkeypatch):
    """`record: logs/run-{tim}.mcap` recorded to that very name, so the hub's next start stopped with `record: ...
    exists ... put {time} in the name`, which the operator believed they had."""
    from hub.config import parse_config
    from hub.factory import record_path

    monkeypatch.chdir(tmp_path)
    config = parse_config({"record": record})
    with pytest.raises(ConfigError, match=r"record: \{.*\} is not something the hub fills in: only \{time\} is"):
        record_path(config)
    assert not list(tmp_path.iterdir())
    config = parse_config({"record": "logs/run-{time}.mcap"})
    assert record_path(config, now=1_790_000_000.0).name.startswith("run-2026")


@pytest.mark.parametrize("record", ["x-{time.mcap", "x-time}.mcap", "logs/{time}-{.mcap"])
def test_an_unpaired_brace_in_record_is_refused(record, tmp_path, monkeypatch):
    """`record: x-{time.mcap` recorded to a file of that very name, braces and all."""
    from hub.config import parse_config
    from hub.factory import record_path

    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match=r"record: .*: a \{ or \} without its pair; only \{time\} is filled in"):
        record_path(parse_config({"record": record}))
    assert not list(tmp_path.iterdir())


def test_a_bad_record_name_is_said_before_the_motion_capture_is_asked_to_connect():
    """It came after `hub: connecting to ...`: with a system that does not answer, only after its timeout."""
    from hub.config import parse_config
    from hub.factory import build_hub

    config = parse_config({"source": {"type": "motioncapture", "system": "mock", "bodies": {"kh0": 0},
                                      "options": {"rigid_bodies": "kh0(0,0,0.05,1,0,0,0)"}},
                           "security": {"insecure": True}, "run": {"behaviour": "aggregate"},
                           "record": "logs/run-{tim}.mcap"})
    said = []
    with pytest.raises(ConfigError, match="is not something the hub fills in"):
        build_hub(config, log=said.append)
    assert not any("connecting to" in line for line in said), said


def test_a_doubled_time_placeholder_in_record_is_refused(tmp_path, monkeypatch):
    """`record: run-{{time}}.mcap` (a Jinja or str.format habit) recorded to `run-{20261128-...}.mcap`: the inner
    {time} was filled in and the outer braces kept in the file name."""
    from hub.config import parse_config
    from hub.factory import record_path

    monkeypatch.chdir(tmp_path)
    config = parse_config({"record": "logs/run-{{time}}.mcap"})
    with pytest.raises(ConfigError, match=r"record: \{\{time\}\}: write \{time\} with single braces"):
        record_path(config)
    assert not list(tmp_path.iterdir())
