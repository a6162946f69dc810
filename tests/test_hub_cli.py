"""The commands as a user types them: `khepri hub` with `khepri ctl status` and `khepri agent`, `khepri keys init`,
`khepri bench hub --json`. The hub binds free ports (port 0) and the clients read them from its log, so parallel
test runs cannot collide; the default ports are checked without binding them."""
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from hub.config import demo_config
from hub.harness import stop_processes
from khepri_cli.main import build_parser

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=str(ROOT))


def khepri(*args, **kwargs):
    return subprocess.run([sys.executable, "-m", "khepri_cli.main", *args], capture_output=True, text=True,
                          env=ENV, timeout=120, **kwargs)


def spawn(*args, log):
    return subprocess.Popen([sys.executable, "-m", "khepri_cli.main", *args], stdout=log, stderr=subprocess.STDOUT,
                            env=ENV, text=True)


def test_the_demo_hub_and_the_clients_agree_on_the_default_ports():
    network = demo_config().network
    assert (network.bind, network.robot_port, network.control_port) == ("127.0.0.1", 5560, 5561)
    parser = build_parser()
    assert parser.parse_args(["agent", "--id", "2", "--driver", "sim"]).port == network.robot_port
    assert parser.parse_args(["ctl", "status"]).port == network.control_port


@pytest.mark.parametrize("bind", ["0.0.0.0", "192.168.1.20", "*"])
def test_the_insecure_demo_hub_refuses_to_listen_beyond_loopback(bind, capsys):
    from khepri_cli.main import main

    assert main(["hub", "--demo", "--bind", bind]) == 2
    assert capsys.readouterr().err.startswith("khepri: error: --bind: --demo runs without encryption")


def test_hub_answers_ctl_and_takes_an_agent(tmp_path):
    config = tmp_path / "lab.yaml"     # the demo (sim source on lab-6, loopback) on free ports; --insecure below
    config.write_text(yaml.safe_dump({"source": {"type": "sim", "scenario": "lab-6"},
                                      "network": {"bind": "127.0.0.1", "robot_port": 0, "control_port": 0}}))
    hub_log = open(tmp_path / "hub.log", "w")
    hub = spawn("hub", "--config", str(config), "--insecure", log=hub_log)
    agent = None
    try:
        deadline = time.monotonic() + 30
        while (tmp_path / "hub.log").read_text().count("listening ") < 2:
            assert hub.poll() is None and time.monotonic() < deadline, (tmp_path / "hub.log").read_text()
            time.sleep(0.1)
        text = (tmp_path / "hub.log").read_text()
        ports = dict(re.findall(r"listening (robots|control) tcp://127\.0\.0\.1:(\d+)", text))
        assert set(ports) == {"robots", "control"}, text
        assert "WARNING: --insecure" in text
        agent = spawn("agent", "--id", "2", "--driver", "sim", "--port", ports["robots"],
                      log=open(tmp_path / "agent.log", "w"))
        while True:
            status = khepri("ctl", "status", "--json", "--port", ports["control"])
            assert status.returncode == 0, status.stderr
            robots = json.loads(status.stdout)["robots"]
            if robots[2]["connected"]:
                break
            assert time.monotonic() < deadline + 30, "the agent did not join"
            time.sleep(0.2)
        table = khepri("ctl", "status", "--port", ports["control"]).stdout
        assert table.splitlines()[0].startswith("hub: idle") and "INSECURE" in table
    finally:
        codes = stop_processes([p for p in (agent, hub) if p is not None])
        hub_log.close()
    assert codes == [0] * len(codes)


def test_keys_init_and_ctl_error_without_a_hub(tmp_path):
    made = khepri("keys", "init", str(tmp_path / "keys"), "--robots", "3", "--operator", "ann")
    assert made.returncode == 0, made.stderr
    assert (tmp_path / "keys" / "robots" / "robot-2.key_secret").is_file()
    again = khepri("keys", "init", str(tmp_path / "keys"))
    assert again.returncode == 2 and "already exists" in again.stderr
    lonely = khepri("ctl", "status", "--port", "1", "--timeout", "0.3")
    assert lonely.returncode == 1 and "no answer from the hub" in lonely.stderr


def test_bench_hub_prints_the_three_figures():
    run = khepri("bench", "hub", "--robots", "10", "--rate", "60", "--seconds", "1", "--json")
    assert run.returncode == 0, run.stderr
    figures = json.loads(run.stdout)
    assert set(figures) >= {"latency_p50_ms", "latency_p99_ms", "hub_cpu_percent"}
    assert 0 < figures["latency_p50_ms"] <= figures["latency_p99_ms"] < 100


@pytest.mark.parametrize("unbuffered", ["", "1"])
def test_output_into_a_closed_pipe_ends_quietly(unbuffered):
    """`khepri sim list | head -1`: no BrokenPipeError traceback when the reader goes away, whether the output
    fails at a print (unbuffered) or at the final flush (a pipe's usual block buffering)."""
    env = {k: v for k, v in ENV.items() if k != "PYTHONUNBUFFERED"}
    if unbuffered:
        env["PYTHONUNBUFFERED"] = unbuffered
    reader = subprocess.Popen([sys.executable, "-m", "khepri_cli.main", "sim", "list"], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, env=env)
    reader.stdout.close()          # gone before the first line is written
    stderr = reader.stderr.read().decode()
    assert reader.wait(timeout=60) == 1
    assert "Traceback" not in stderr and "BrokenPipeError" not in stderr, stderr
