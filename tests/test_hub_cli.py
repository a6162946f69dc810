"""The commands as a user types them: `khepri hub` with `khepri ctl status` and `khepri agent`, `khepri keys init`,
`khepri bench hub --json`. The hub binds free ports (port 0) and the clients read them from its log, so parallel
test runs cannot collide; the default ports are checked without binding them."""
import json
import math
import os
import re
import signal
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


def khepri(*args, timeout=120, **kwargs):
    return subprocess.run([sys.executable, "-m", "khepri_cli.main", *args], capture_output=True, text=True,
                          env=ENV, timeout=timeout, **kwargs)


def spawn(*args, log):
    return subprocess.Popen([sys.executable, "-m", "khepri_cli.main", *args], stdout=log, stderr=subprocess.STDOUT,
                            env=ENV, text=True)


def test_the_demo_hub_and_the_clients_agree_on_the_default_ports():
    network = demo_config().network
    assert (network.bind, network.robot_port, network.control_port) == ("127.0.0.1", 5560, 5561)
    from khepri_cli.lab_commands import DEFAULT_CONTROL_PORT
    from onboard.agent.cli import DEFAULT_ROBOT_PORT

    parser = build_parser()
    # No --port given: None, which stands for these defaults (a whole --hub address may then carry its own).
    assert parser.parse_args(["agent", "--id", "2", "--driver", "sim"]).port is None
    assert parser.parse_args(["ctl", "status"]).port is None
    assert (DEFAULT_ROBOT_PORT, DEFAULT_CONTROL_PORT) == (network.robot_port, network.control_port)


@pytest.mark.parametrize("bind", ["0.0.0.0", "192.168.1.20", "*", "::", "[::]", "[fe80::1]"])
def test_the_insecure_demo_hub_refuses_to_listen_beyond_loopback(bind, capsys):
    from khepri_cli.main import main

    assert main(["hub", "--demo", "--bind", bind]) == 2
    assert capsys.readouterr().err.startswith("khepri: error: --bind: --demo runs without encryption")


@pytest.mark.ipv6_loopback
@pytest.mark.parametrize("bind", ["[::1]", "::1"])
def test_the_demo_hub_listens_on_the_ipv6_loopback_written_either_way(bind, tmp_path):
    """--bind [::1], as in a URL (and as the hub itself writes it), was refused as beyond loopback; ::1 was not."""
    log_path = tmp_path / "hub.log"
    with open(log_path, "w") as log:
        # On free ports: its own are the defaults, 5560 and 5561, which a running lab may hold.
        hub = spawn("hub", "--demo", "--bind", bind, "--robot-port", "0", "--control-port", "0", log=log)
    try:
        deadline = time.monotonic() + 30
        while log_path.read_text().count("listening ") < 2:
            assert hub.poll() is None and time.monotonic() < deadline, log_path.read_text()
            time.sleep(0.1)
        hub.send_signal(signal.SIGINT)
        assert hub.wait(timeout=15) == 0
    finally:
        stop_processes([hub])
    assert re.search(r"listening robots tcp://\[::1\]:\d+\n", log_path.read_text()), log_path.read_text()


def test_an_insecure_hub_off_loopback_says_where_it_listens(tmp_path):
    """The banner says to run insecure "only on loopback"; a config binding every interface with --insecure
    started with that banner alone."""
    config = tmp_path / "lab.yaml"
    config.write_text(yaml.safe_dump({"source": {"type": "sim", "scenario": "lab-6"},
                                      "network": {"bind": "0.0.0.0", "robot_port": 0, "control_port": 0}}))
    log_path = tmp_path / "hub.log"
    with open(log_path, "w") as log:
        hub = spawn("hub", "--config", str(config), "--insecure", log=log)
    try:
        deadline = time.monotonic() + 30
        while log_path.read_text().count("listening ") < 2:
            assert hub.poll() is None and time.monotonic() < deadline, log_path.read_text()
            time.sleep(0.1)
    finally:
        stop_processes([hub])
    assert "hub: INSECURE and not on loopback: listening on every network interface (network.bind 0.0.0.0)" in \
        log_path.read_text(), log_path.read_text()


def hub_ports(log_path: Path, hub: subprocess.Popen) -> dict:
    """The robots and control ports a hub on port 0 bound, read from its `listening` lines."""
    deadline = time.monotonic() + 30
    while log_path.read_text().count("listening ") < 2:
        assert hub.poll() is None and time.monotonic() < deadline, log_path.read_text()
        time.sleep(0.1)
    ports = dict(re.findall(r"listening (robots|control) tcp://127\.0\.0\.1:(\d+)", log_path.read_text()))
    assert set(ports) == {"robots", "control"}, log_path.read_text()
    return ports


def wait_until_connected(robot_id: int, control_port: str) -> None:
    deadline = time.monotonic() + 60
    while True:
        status = khepri("ctl", "status", "--json", "--port", control_port)
        assert status.returncode == 0, status.stderr
        if json.loads(status.stdout)["robots"][robot_id]["connected"]:
            return
        assert time.monotonic() < deadline, "the agent did not join"
        time.sleep(0.2)


def lab_config(tmp_path: Path, scenario: str) -> Path:
    """The demo (sim source, loopback) on free ports; --insecure is given on the command line."""
    config = tmp_path / "lab.yaml"
    config.write_text(yaml.safe_dump({"source": {"type": "sim", "scenario": scenario},
                                      "network": {"bind": "127.0.0.1", "robot_port": 0, "control_port": 0}}))
    return config


def test_hub_answers_ctl_and_takes_an_agent(tmp_path):
    hub_log = open(tmp_path / "hub.log", "w")
    hub = spawn("hub", "--config", str(lab_config(tmp_path, "lab-6")), "--insecure", log=hub_log)
    agent = None
    try:
        ports = hub_ports(tmp_path / "hub.log", hub)
        assert "WARNING: insecure (--insecure or security.insecure)" in (tmp_path / "hub.log").read_text()
        agent = spawn("agent", "--id", "2", "--driver", "sim", "--port", ports["robots"],
                      log=open(tmp_path / "agent.log", "w"))
        wait_until_connected(2, ports["control"])
        table = khepri("ctl", "status", "--port", ports["control"]).stdout
        assert table.splitlines()[0].startswith("hub: idle") and "INSECURE" in table
    finally:
        codes = stop_processes([p for p in (agent, hub) if p is not None])
        hub_log.close()
    assert codes == [0] * len(codes)


def test_the_demo_hub_runs_on_ports_given_on_the_command_line(tmp_path):
    """--demo could not be moved off 5560 and 5561 (it takes no --config): with those ports taken, no demo."""
    hub_log = open(tmp_path / "hub.log", "w")
    hub = spawn("hub", "--demo", "--robot-port", "0", "--control-port", "0", log=hub_log)
    agent = None
    try:
        ports = hub_ports(tmp_path / "hub.log", hub)
        assert "5560" not in ports.values() and "5561" not in ports.values()
        agent = spawn("agent", "--id", "4", "--driver", "sim", "--port", ports["robots"],
                      log=open(tmp_path / "agent.log", "w"))
        wait_until_connected(4, ports["control"])
        taken = khepri("hub", "--demo", "--robot-port", ports["robots"], "--control-port", "0")
        assert taken.returncode == 2
        assert taken.stderr.strip().splitlines()[-1] == \
            f"khepri: error: --robot-port: port {ports['robots']} on 127.0.0.1 is already in use"
    finally:
        codes = stop_processes([p for p in (agent, hub) if p is not None])
        hub_log.close()
    assert codes == [0] * len(codes)
    same = khepri("hub", "--demo", "--robot-port", "6411", "--control-port", "6411")
    assert same.stderr.strip().splitlines()[-1] == \
        "khepri: error: --control-port: must differ from the robot port (both are 6411)"


def test_the_demo_hub_names_the_option_for_its_own_port_when_taken(monkeypatch, capsys):
    """With 5560 taken (another hub), `hub --demo` said `network.robot_port: ...`: a config key, with no config."""
    import socket

    import hub.config
    from khepri_cli.main import main

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]

        def demo_on_the_taken_port():
            config = demo_config()
            config.network.robot_port = port
            return config

        monkeypatch.setattr(hub.config, "demo_config", demo_on_the_taken_port)
        assert main(["hub", "--demo", "--control-port", "0"]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == \
        f"khepri: error: --robot-port: port {port} on 127.0.0.1 is already in use"


def test_ctl_start_names_the_robots_that_cannot_run_it(tmp_path):
    """`ctl start` said ok (exit 0) when every agent refused the run, here a behaviour only the hub imported."""
    (tmp_path / "hub_only.py").write_text("from onboard.behaviour import Behaviour, register\n\n\n"
                                          "@register('hub-only')\nclass HubOnly(Behaviour):\n"
                                          "    def step(self):\n        pass\n")
    (tmp_path / "hub-only.yaml").write_text("behaviour: hub-only\nrobots: {count: 3}\n")
    hub_log = open(tmp_path / "hub.log", "w")
    hub = subprocess.Popen([sys.executable, "-m", "khepri_cli.main", "--import", "hub_only", "hub", "--config",
                            str(lab_config(tmp_path, "hub-only.yaml")), "--insecure"],
                           stdout=hub_log, stderr=subprocess.STDOUT, env=ENV, text=True, cwd=tmp_path)
    agent = None
    try:
        ports = hub_ports(tmp_path / "hub.log", hub)
        agent = spawn("agent", "--id", "1", "--driver", "sim", "--port", ports["robots"],
                      log=open(tmp_path / "agent.log", "w"))
        wait_until_connected(1, ports["control"])
        start = khepri("ctl", "start", "--port", ports["control"])
        assert start.returncode == 1, start
        # It said "start: ok (...)" above the robot's error.
        assert start.stdout.startswith("start: the hub is running, but 1 robot refused to start (the errors "
                                       "follow); 1 of 3 robots connected and sent it"), start.stdout
        assert "khepri: error: robot 1: cannot start the run: run.behaviour: unknown behaviour 'hub-only'" \
            in start.stderr
        status = json.loads(khepri("ctl", "status", "--json", "--port", ports["control"]).stdout)
        row = next(row for row in status["robots"] if row["id"] == 1)
        assert row["refused_run_id"] == status["run_id"]     # its answer, which `ctl start` waits for
    finally:
        codes = stop_processes([p for p in (agent, hub) if p is not None])
        hub_log.close()
    assert codes == [0] * len(codes)
    said = [line for line in (tmp_path / "hub.log").read_text().splitlines() if "cannot start the run" in line]
    assert len(said) == 1, said          # said once at the hub's console too, not only in `ctl status`
    assert said[0].startswith("hub: robot 1: cannot start the run: run.behaviour: unknown behaviour 'hub-only'")


def test_ctl_stop_and_clear_with_nothing_to_do_say_so(tmp_path):
    """Both printed a bare "ok" with no run going and no e-stop latched: the operator could not tell a stop that
    ended a run from one that found none."""
    hub_log = open(tmp_path / "hub.log", "w")
    hub = spawn("hub", "--config", str(lab_config(tmp_path, "lab-6")), "--insecure", log=hub_log)
    try:
        control = hub_ports(tmp_path / "hub.log", hub)["control"]

        def ctl(command: str) -> str:
            run = khepri("ctl", *command.split(), "--port", control)
            assert run.returncode == 0, run.stderr
            return run.stdout.strip()

        assert ctl("stop") == "stop: nothing to stop: no run is going"
        assert ctl("clear") == "clear: nothing to clear: no e-stop was latched"
        ctl("start")
        ctl("estop")
        # A refused command printed nothing on stdout with --json: a script could not tell why it failed.
        refused = khepri("ctl", "start", "--json", "--port", control)
        assert refused.returncode == 1 and "the hub refused start" in refused.stderr
        said = json.loads(refused.stdout)
        assert said["command"] == "start" and said["ok"] is False and "e-stop is latched" in said["error"], said
        assert ctl("clear") == "clear: ok (robots stay stopped until `khepri ctl start`)"
        assert re.fullmatch(r"stop: ok \(run [0-9a-f]{12} ended; NO ROBOT CONNECTED \(0 of 6\): each is told to "
                            r"stop as it connects\)", ctl("stop"))
        # --json for every command, not only status (start and stop printed plain text)
        assert json.loads(ctl("stop --json")) == {"command": "stop", "ok": True, "nothing_done": True,
                                                  "note": "nothing to stop: no run is going"}
        started = json.loads(ctl("start --json"))
        assert started["command"] == "start" and started["refused"] == [] and "note" in started
        # A second start, like a second stop, says it did nothing (it said "ok (already running)").
        again = ctl("start")
        assert re.fullmatch(r"start: nothing to start: run [0-9a-f]{12} is already going", again), again
        assert json.loads(ctl("start --json"))["nothing_done"] is True
    finally:
        codes = stop_processes([hub])
        hub_log.close()
    assert codes == [0]


def test_keys_init_and_ctl_error_without_a_hub(tmp_path):
    made = khepri("keys", "init", str(tmp_path / "keys"), "--robots", "3", "--operator", "ann")
    assert made.returncode == 0, made.stderr
    assert (tmp_path / "keys" / "robots" / "robot-2.key_secret").is_file()
    again = khepri("keys", "init", str(tmp_path / "keys"))
    assert again.returncode == 2 and "error: FOLDER: " in again.stderr and "already exists" in again.stderr
    lonely = khepri("ctl", "status", "--port", "1", "--timeout", "0.3")
    assert lonely.returncode == 1 and "no answer from the hub" in lonely.stderr


@pytest.mark.parametrize("command", ["status", "estop"])
def test_ctl_json_without_a_hub_prints_a_json_error_for_status_too(command):
    """`ctl estop --json` printed {"ok": false, ...} on stdout, `ctl status --json` nothing at all."""
    lonely = khepri("ctl", command, "--json", "--port", "1", "--timeout", "0.3")
    said = json.loads(lonely.stdout)
    assert lonely.returncode == 1 and said["command"] == command and said["ok"] is False
    assert said["error"].startswith("no answer from the hub at tcp://127.0.0.1:1 within 0.3 s")
    assert "khepri: error: " in lonely.stderr and said["error"] in lonely.stderr


HEAVY_MODULES = ("filterpy", "scipy", "pymunk", "matplotlib", "onboard.behaviours.transport")


@pytest.mark.parametrize("command", ["ctl estop --port 1 --timeout 0.3", "ctl status --port 1 --timeout 0.3",
                                     "keys init {tmp}/keys"])
def test_the_operators_commands_do_not_load_the_simulator_or_the_behaviours(command, tmp_path):
    """`khepri ctl estop` imported the built-in evaluators with the command's error handling, and with them the
    transport behaviour, filterpy and scipy: 3-4 s on a busy lab PC before the e-stop was even sent."""
    argv = command.format(tmp=tmp_path).split()
    probe = subprocess.run(
        [sys.executable, "-c", "import sys\nfrom khepri_cli.main import main\nmain(sys.argv[1:])\n"
         f"print(sorted(m for m in {HEAVY_MODULES!r} if m in sys.modules))", *argv],
        capture_output=True, text=True, env=ENV, timeout=120)
    assert probe.stdout.strip().splitlines()[-1] == "[]", (probe.stdout, probe.stderr)


def test_keys_add_adds_robots_and_operators_to_a_key_folder(tmp_path):
    keys = tmp_path / "keys"
    assert khepri("keys", "init", str(keys), "--robots", "2").returncode == 0
    hub_key = (keys / "hub.key_secret").read_bytes()
    added = khepri("keys", "add", str(keys), "--robots", "2,3", "--operator", "bob")
    assert added.returncode == 0, added.stderr
    assert "added 6 key files" in added.stdout and "every other key is unchanged" in added.stdout
    assert (keys / "robots" / "robot-3.key_secret").is_file() and (keys / "operators" / "bob.key").is_file()
    assert (keys / "operators" / "operator.key").is_file() and (keys / "hub.key_secret").read_bytes() == hub_key
    again = khepri("keys", "add", str(keys), "--robots", "3,")
    assert again.returncode == 2 and "--robots: robot 3 already has a key" in again.stderr
    nothing = khepri("keys", "add", str(keys))
    assert nothing.returncode == 2 and "name the robots" in nothing.stderr


def test_keys_add_gives_a_revoked_robot_a_new_key_and_names_only_files_that_exist(tmp_path, capsys):
    """Revoking a key (deleting its .key) leaves its .key_secret; `keys add` then refused, saying the robot already
    had a key, named the deleted robot-1.key, and the hub's own hint at start (`keys add --robots 1,`) led there."""
    from khepri_cli.main import main

    keys = tmp_path / "keys"
    assert main(["keys", "init", str(keys), "--robots", "3"]) == 0
    (keys / "robots" / "robot-1.key").unlink()                  # robot 1 revoked
    (keys / "robots" / "robot-2.key_secret").unlink()           # robot 2's secret moved onto the robot
    old_secret = (keys / "robots" / "robot-1.key_secret").read_bytes()
    capsys.readouterr()
    assert main(["keys", "add", str(keys), "--robots", "1,"]) == 0
    said = capsys.readouterr().out
    assert "replaced what revoked keys had left (a .key_secret without its .key): " \
           f"{keys / 'robots' / 'robot-1.key_secret'}" in said, said
    assert (keys / "robots" / "robot-1.key").is_file()
    assert (keys / "robots" / "robot-1.key_secret").read_bytes() != old_secret
    assert main(["keys", "add", str(keys), "--robots", "2,"]) == 2
    assert capsys.readouterr().err.strip() == f"khepri: error: --robots: robot 2 already has a key " \
        f"({keys / 'robots' / 'robot-2.key'}); to replace it, delete robot-2.key first"


def test_keys_add_refuses_a_folder_whose_hub_key_is_damaged(tmp_path, capsys):
    """It added the robot and told the user to give it hub.key, which the hub and every agent then refused."""
    from khepri_cli.main import main

    keys = tmp_path / "keys"
    assert main(["keys", "init", str(keys), "--robots", "2"]) == 0
    (keys / "hub.key").write_text("junk\n")
    capsys.readouterr()
    assert main(["keys", "add", str(keys), "--robots", "5,"]) == 2
    assert capsys.readouterr().err.startswith(f"khepri: error: FOLDER: {keys / 'hub.key'}: not a key file")
    assert not (keys / "robots" / "robot-5.key").exists()


def test_keys_init_with_a_refused_operator_name_leaves_nothing_behind(tmp_path):
    refused = khepri("keys", "init", str(tmp_path / "keys"), "--operator", "ann/../bob")
    assert refused.returncode == 2 and "--operator: use letters" in refused.stderr
    assert not (tmp_path / "keys").exists()     # no empty folder for the next `keys init` to trip over


def test_bench_hub_prints_the_three_figures():
    run = khepri("bench", "hub", "--robots", "10", "--rate", "60", "--seconds", "1", "--json")
    assert run.returncode == 0, run.stderr
    figures = json.loads(run.stdout)
    assert set(figures) >= {"latency_p50_ms", "latency_p99_ms", "hub_cpu_percent"}
    # How fast is the benchmark's to say (docs/lab.md), not this test's: a busy CI machine once took a p99 of 210 ms.
    assert 0 < figures["latency_p50_ms"] <= figures["latency_p99_ms"] < math.inf
    assert 0 < figures["hub_cpu_percent"] < math.inf


def test_bench_estop_prints_how_long_every_agent_took_to_stop():
    run = khepri("bench", "estop", "--robots", "2", "--repeats", "1", "--json")
    assert run.returncode == 0, run.stderr
    figures = json.loads(run.stdout)
    assert figures["robots"] == 2 and figures["repeats"] == 1
    # The slowest agent's time includes the request's transit to the hub: never below the slowest acknowledgement.
    assert 0 < figures["ack_ms_p50"] <= figures["ack_ms_max"] <= figures["worst_ms_max"] < math.inf


@pytest.mark.parametrize("option, value, said", [("--robots", "0", "--robots"), ("--repeats", "0", "--repeats"),
                                                 ("--robots", "101", "--robots")])
def test_bench_estop_names_a_bad_option(option, value, said):
    run = khepri("bench", "estop", option, value)
    assert run.returncode == 2 and run.stderr.startswith(f"khepri: error: {said}"), run.stderr


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


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full, a device that is always full")
@pytest.mark.parametrize("command, unbuffered", [(("sim", "list"), ""), (("sim", "list"), "1"),
                                                 (("log", "info", "--help"), "")])
def test_output_onto_a_full_disk_is_one_error_line(command, unbuffered):
    """`khepri sim list > list.txt` on a full disk ended in a traceback: an OSError that names no file was taken
    for a bug. (Unbuffered, argparse ignores a failed --help itself.)"""
    env = {k: v for k, v in ENV.items() if k != "PYTHONUNBUFFERED"}
    if unbuffered:
        env["PYTHONUNBUFFERED"] = unbuffered
    with open("/dev/full", "w") as full:
        run = subprocess.run([sys.executable, "-m", "khepri_cli.main", *command], stdout=full, stderr=subprocess.PIPE,
                             env=env, text=True, timeout=60)
    assert (run.returncode, run.stderr) == (2, "khepri: error: No space left on device: standard output\n")


def test_an_error_said_to_a_terminal_that_is_gone_keeps_its_exit_code():
    """A hub or agent erring once its terminal is gone (the ssh session dropped): `khepri: error: ...` failed
    (EPIPE here, EIO on a pty) and the interpreter ended with a traceback and exit code 1, not the error's 2."""
    run = subprocess.Popen([sys.executable, "-m", "khepri_cli.main", "sim", "run", "no-such-scenario"],
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=ENV)
    run.stderr.close()             # gone before the error is said
    assert run.wait(timeout=60) == 2


@pytest.mark.parametrize("command", [("agent", "--id", "1", "--driver", "sim"), ("ctl", "status")])
def test_a_hub_host_name_that_does_not_resolve_is_an_error_naming_it(command):
    """ZeroMQ resolves a host name only while connecting, and says nothing when it cannot: a typo in --hub made
    the agent wait for ever and ctl time out as if no hub were running. (.invalid never resolves: RFC 6761.)"""
    run = khepri(*command, "--hub", "labpc.invalid", timeout=20)
    assert run.returncode == 2 and "Traceback" not in run.stderr, run.stderr
    assert run.stderr.strip().splitlines()[-1].startswith(
        "khepri: error: --hub: cannot resolve the host name 'labpc.invalid': "), run.stderr


def test_an_agent_whose_dns_is_not_reachable_yet_keeps_trying(monkeypatch):
    """A robot booting before its Wi-Fi is up cannot look the name up yet: said, not fatal."""
    import socket

    from onboard.agent import link as links
    from onboard.agent.cli import open_link

    def no_dns(*args, **kwargs):
        raise socket.gaierror(socket.EAI_AGAIN, "Temporary failure in name resolution")

    monkeypatch.setattr(links.socket, "getaddrinfo", no_dns)
    said = []
    link = open_link(2, "tcp://labpc:5560", None, said.append)
    link.close()
    assert said == ["agent 2: warning: cannot resolve the host name 'labpc': Temporary failure in name resolution "
                    "(a typo? or give the hub PC's IP address); still trying"]


def test_the_insecure_warning_is_a_closed_box():
    """Two of its lines were one character wider than the others, so the box's right edge was ragged."""
    from hub.runner import INSECURE_WARNING

    lines = INSECURE_WARNING.splitlines()
    assert len({len(line) for line in lines}) == 1, [len(line) for line in lines]
    assert all(line.endswith("*") for line in lines)


def test_an_estop_that_got_no_answer_says_so_loudly_and_why(tmp_path):
    """At a demo `ctl estop` without --keys, beside the lab's keys/ folder, read like any other error: the robots
    ran on. It now says the e-stop was not delivered, and why: here, that nothing listens at that port."""
    import socket

    (tmp_path / "keys" / "operators").mkdir(parents=True)
    (tmp_path / "keys" / "operators" / "alice.key_secret").write_text("not read")
    with socket.socket() as probe:        # a port nobody listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    said = khepri("ctl", "estop", "--port", str(port), "--timeout", "0.3", cwd=tmp_path)
    assert said.returncode == 1
    assert said.stderr.startswith("khepri: error: E-STOP NOT DELIVERED: no answer from the hub at "), said.stderr
    # Nothing listens there: keys would not help, and it says what would (the keys' hint: test_security.py).
    assert "nothing accepts a connection there (refused or unreachable): is the hub running" in said.stderr
    assert "--keys keys" not in said.stderr
    quiet = khepri("ctl", "status", "--port", str(port), "--timeout", "0.3", cwd=tmp_path / "keys")
    assert "NOT DELIVERED" not in quiet.stderr and "keys/" not in quiet.stderr
