"""The commands as a user types them: `khepri hub --demo` with `khepri ctl status` and `khepri agent` defaults,
`khepri keys init`, `khepri bench hub --json`."""
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from hub.harness import stop_processes

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=str(ROOT))


def khepri(*args, **kwargs):
    return subprocess.run([sys.executable, "-m", "khepri_cli.main", *args], capture_output=True, text=True,
                          env=ENV, timeout=120, **kwargs)


def spawn(*args, log):
    return subprocess.Popen([sys.executable, "-m", "khepri_cli.main", *args], stdout=log, stderr=subprocess.STDOUT,
                            env=ENV, text=True)


def test_demo_hub_answers_ctl_and_takes_an_agent_with_defaults(tmp_path):
    hub_log = open(tmp_path / "hub.log", "w")
    hub = spawn("hub", "--demo", log=hub_log)
    agent = None
    try:
        deadline = time.monotonic() + 30
        while (tmp_path / "hub.log").read_text().count("listening ") < 2:
            assert hub.poll() is None and time.monotonic() < deadline, (tmp_path / "hub.log").read_text()
            time.sleep(0.1)
        text = (tmp_path / "hub.log").read_text()
        assert "listening robots tcp://127.0.0.1:5560" in text and "listening control tcp://127.0.0.1:5561" in text
        assert "WARNING: --insecure" in text
        agent = spawn("agent", "--id", "2", "--driver", "sim", log=open(tmp_path / "agent.log", "w"))
        while True:
            status = khepri("ctl", "status", "--json")
            assert status.returncode == 0, status.stderr
            robots = json.loads(status.stdout)["robots"]
            if robots[2]["connected"]:
                break
            assert time.monotonic() < deadline + 30, "the agent did not join"
            time.sleep(0.2)
        table = khepri("ctl", "status").stdout
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
