"""A hub's log is never lost to the hub itself: it does not write over a log (an earlier run's, the one being
replayed, one another hub is writing), a hub that cannot start leaves no file behind, a full disk ends the
recording but not the lab run, and a closed terminal (SIGHUP) stops the hub as Ctrl-C does. Real hub
processes on free ports; the full disk is a file size limit (RLIMIT_FSIZE)."""
import json
import os
import re
import select
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Tuple

import pytest
import yaml
import zmq

from hub.config import parse_config
from hub.control import request
from hub.factory import record_path
from hub.harness import stop_processes
from hub.recording import read_log
from khepri_cli.main import main
from onboard.config import ConfigError
from onboard.protocol import decode, encode

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=str(ROOT))

# The hub under a file size limit, with SIGXFSZ ignored so that a write past it fails (EFBIG) instead of
# killing the process: a disk that fills up during a run.
LIMITED_HUB = """
import resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (6000, 6000))
from khepri_cli.main import main
sys.exit(main(sys.argv[1:]))
"""


def lab_config(tmp_path: Path, record: Path, robot_port: int = 0) -> Path:
    config = tmp_path / "lab.yaml"
    config.write_text(yaml.safe_dump({"source": {"type": "sim", "scenario": "lab-6"},
                                      "network": {"bind": "127.0.0.1", "robot_port": robot_port, "control_port": 0},
                                      "security": {"insecure": True}, "record": str(record)}))
    return config


def start_hub(tmp_path: Path, *command: str, **popen) -> subprocess.Popen:
    log = open(tmp_path / "hub.log", "w")
    hub = subprocess.Popen([sys.executable, *command], stdout=log, stderr=subprocess.STDOUT, env=ENV, text=True,
                           **popen)
    deadline = time.monotonic() + 30
    while (tmp_path / "hub.log").read_text().count("listening ") < 2:
        assert hub.poll() is None and time.monotonic() < deadline, (tmp_path / "hub.log").read_text()
        time.sleep(0.1)
    return hub


def log_info(log: Path) -> dict:
    """``khepri log info --json`` of ``log``, as a user would run it."""
    summary = subprocess.run([sys.executable, "-m", "khepri_cli.main", "log", "info", str(log), "--json"],
                             capture_output=True, text=True, env=ENV, timeout=60)
    return json.loads(summary.stdout)


def control_endpoint(tmp_path: Path) -> str:
    line = next(x for x in (tmp_path / "hub.log").read_text().splitlines() if x.startswith("listening control"))
    return line.split()[-1]


def test_an_existing_log_is_refused_and_left_as_it_was(tmp_path, capsys):
    log = tmp_path / "run.mcap"
    log.write_bytes(b"an earlier run's log")
    assert main(["hub", "--demo", "--record", str(log)]) == 2
    err = capsys.readouterr().err
    assert f"khepri: error: --record: {log} exists" in err and "{time}" in err     # the option typed
    assert log.read_bytes() == b"an earlier run's log"


def test_a_folder_given_as_the_log_is_refused_with_a_file_name_to_use(tmp_path, capsys):
    """It said 'logs exists (an earlier run's log, or one a hub is writing)'."""
    assert main(["hub", "--demo", "--record", str(tmp_path)]) == 2
    assert f"khepri: error: --record: {tmp_path} is a folder: give the log's file name, e.g. " \
           f"{tmp_path / 'run-{time}.mcap'}" in capsys.readouterr().err


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc, where no file can be made")
@pytest.mark.parametrize("log, said", [
    ("/proc/khepri-test.mcap", "--record: /proc/khepri-test.mcap: cannot create the log: "),
    ("/proc/khepri-test/run.mcap", "--record: cannot make the folder /proc/khepri-test: "),
])
def test_a_log_that_cannot_be_made_is_said_as_the_record_option(capsys, log, said):
    """It said '/proc/x.mcap: cannot create the log' without naming the option, and a folder it could not make
    was a traceback."""
    assert main(["hub", "--demo", "--record", log, "--robot-port", "0", "--control-port", "0"]) == 2
    err = capsys.readouterr().err
    assert f"khepri: error: {said}" in err and "Traceback" not in err, err


def test_time_in_the_log_name_gives_each_start_its_own_file(tmp_path):
    config = parse_config({"record": str(tmp_path / "run-{time}.mcap")})
    at = time.mktime((2026, 11, 21, 20, 15, 2, 0, 0, -1))
    assert record_path(config, at) == tmp_path / "run-20261121-201502.mcap"
    # Two hubs started within the same second: the second stopped at `record: ... exists`.
    (tmp_path / "run-20261121-201502.mcap").write_bytes(b"")
    assert record_path(config, at) == tmp_path / "run-20261121-201502-2.mcap"
    (tmp_path / "run-20261121-201502-2.mcap").write_bytes(b"")
    assert record_path(config, at) == tmp_path / "run-20261121-201502-3.mcap"
    fixed = parse_config({"record": str(tmp_path / "run-20261121-201502.mcap")})
    with pytest.raises(ConfigError, match="exists"):      # a fixed name still never writes over a log
        record_path(fixed, at)


def test_a_time_name_taken_between_the_look_and_the_open_goes_to_the_next(tmp_path):
    """Two hubs started in the same instant: both looked, the first opened run-<time>.mcap, and the second
    stopped at `exists` instead of writing run-<time>-2.mcap. A fixed name is still refused."""
    from hub.factory import open_recorder

    taken = tmp_path / "run-20261121-201502.mcap"
    taken.write_bytes(b"the other hub's")
    recorder = open_recorder(taken, {}, next_name_if_taken=True)
    try:
        assert recorder.path == tmp_path / "run-20261121-201502-2.mcap"
    finally:
        recorder.close()
    assert taken.read_bytes() == b"the other hub's"
    with pytest.raises(ConfigError, match=r"^record: .*run-20261121-201502.mcap: exists"):
        open_recorder(taken, {})


def test_recording_onto_the_log_being_replayed_is_refused(tmp_path):
    replayed = tmp_path / "run.mcap"
    replayed.write_bytes(b"a recorded run")
    config = parse_config({"source": {"type": "replay", "file": str(replayed)}, "record": str(replayed)})
    with pytest.raises(ConfigError, match="is the log being replayed"):
        record_path(config)


def test_an_empty_log_name_is_an_error_not_a_run_without_a_log(tmp_path, capsys):
    assert main(["hub", "--demo", "--record", ""]) == 2
    assert "khepri: error: --record: is empty" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="record: is empty"):
        parse_config({"record": " "})


def test_a_hub_that_cannot_bind_leaves_no_log(tmp_path, capsys):
    """It used to erase the log of the hub that held the port; now it would leave an empty one that then
    blocks the next start (the hub does not write over a log). Nor does it say `recording to` the log it removed
    (it did, before the error)."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        log = tmp_path / "run.mcap"
        assert main(["hub", "--config", str(lab_config(tmp_path, log, taken.getsockname()[1]))]) == 2
    said = capsys.readouterr()
    assert "network.robot_port" in said.err
    assert "recording to" not in said.out + said.err
    assert not log.exists()


def test_the_hub_says_where_it_records_once_it_listens(tmp_path):
    log = tmp_path / "run.mcap"
    hub = start_hub(tmp_path, "-m", "khepri_cli.main", "hub", "--config", str(lab_config(tmp_path, log)))
    try:
        deadline = time.monotonic() + 30
        while "recording to" not in (tmp_path / "hub.log").read_text():
            assert hub.poll() is None and time.monotonic() < deadline, (tmp_path / "hub.log").read_text()
            time.sleep(0.1)
        lines = (tmp_path / "hub.log").read_text().splitlines()
        listening = [i for i, line in enumerate(lines) if line.startswith("listening ")]
        assert len(listening) == 2 and lines[listening[-1] + 1] == f"hub: recording to {log}", lines
    finally:
        hub.send_signal(signal.SIGINT)
        hub.wait(timeout=15)


def test_a_full_disk_ends_the_recording_not_the_run(tmp_path):
    log = tmp_path / "run.mcap"
    hub = start_hub(tmp_path, "-c", LIMITED_HUB, "hub", "--config", str(lab_config(tmp_path, log)))
    try:
        deadline = time.monotonic() + 30
        while "RECORDING STOPPED" not in (tmp_path / "hub.log").read_text():
            assert hub.poll() is None and time.monotonic() < deadline, (tmp_path / "hub.log").read_text()
            time.sleep(0.1)
        status = request(control_endpoint(tmp_path), "status", timeout_s=5.0)["status"]   # still serving
        assert status["recording"]["path"] == str(log) and "File too large" in status["recording"]["error"]
        assert request(control_endpoint(tmp_path), "start", timeout_s=5.0)["ok"]
        hub.send_signal(signal.SIGINT)
        assert hub.wait(timeout=15) == 0
    finally:
        stop_processes([hub])
    assert "hub: stopped" in (tmp_path / "hub.log").read_text()
    assert log_info(log)["message_count"] > 0        # what was written before the disk filled is readable


def test_a_closed_terminal_stops_the_hub_as_ctrl_c_does(tmp_path):
    log = tmp_path / "run.mcap"
    hub = start_hub(tmp_path, "-m", "khepri_cli.main", "hub", "--config", str(lab_config(tmp_path, log)))
    try:
        time.sleep(1.0)
        hub.send_signal(signal.SIGHUP)
        assert hub.wait(timeout=15) == 0
    finally:
        stop_processes([hub])
    assert "hub: stopped" in (tmp_path / "hub.log").read_text()
    assert log_info(log)["truncated"] is False       # closed properly: footer and summary written



@pytest.mark.parametrize("stop", [signal.SIGTERM, signal.SIGINT])
def test_a_hub_stopped_by_a_signal_mid_run_names_the_run_it_ended(tmp_path, stop):
    """Its last lines said `hub: stopped`, and its log nothing of the run it cut short: which run, and that a
    signal, not an operator, ended it."""
    log = tmp_path / "run.mcap"
    hub = start_hub(tmp_path, "-m", "khepri_cli.main", "hub", "--config", str(lab_config(tmp_path, log)))
    try:
        control = control_endpoint(tmp_path)
        assert request(control, "start", timeout_s=5.0)["ok"]
        run_id = request(control, "status", timeout_s=5.0)["status"]["run_id"]
        hub.send_signal(stop)
        assert hub.wait(timeout=15) == 0
    finally:
        stop_processes([hub])
    name = stop.name
    lines = (tmp_path / "hub.log").read_text().splitlines()
    assert lines[-1] == f"hub: stopped by {name}; run {run_id} ended", lines
    assert lines[-2].startswith(f"hub: {name}: run {run_id} ended by the signal: not completed (cage did not "
                                "close); object at ("), lines
    summary = log_info(log)
    assert summary["truncated"] is False
    assert [(r["run_id"], r["end_cause"], r["ended_by"]) for r in summary["runs"]] == [(run_id, "signal", name)]
    text = subprocess.run([sys.executable, "-m", "khepri_cli.main", "log", "info", str(log)], capture_output=True,
                          text=True, env=ENV, timeout=60).stdout
    assert re.search(rf"^run: +{run_id} \(transport\): started .*; ended \d\d:\d\d:\d\d by {name}: not completed",
                     text, re.M), text


def test_a_hub_started_with_nohup_outlives_its_terminal(tmp_path):
    """SIGHUP ignored at start (`nohup khepri hub ...`) is the user's wish to keep the hub running, as for the
    agent; it used to stop the hub all the same."""
    log = tmp_path / "run.mcap"
    hub = start_hub(tmp_path, "-m", "khepri_cli.main", "hub", "--config", str(lab_config(tmp_path, log)),
                    preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN))
    try:
        hub.send_signal(signal.SIGHUP)
        time.sleep(1.0)
        assert hub.poll() is None, "the hub stopped on SIGHUP under nohup"
        hub.send_signal(signal.SIGTERM)
        assert hub.wait(timeout=15) == 0
    finally:
        stop_processes([hub])
    assert log_info(log)["truncated"] is False


def start_hub_on_a_terminal(tmp_path: Path, record: Path, controlling: bool) -> Tuple[subprocess.Popen, int, str]:
    """A hub whose stdout and stderr are a pty (a hub started by hand over ssh), and the robots endpoint it
    said there. ``controlling``: the pty is its controlling terminal, so closing it sends the hub SIGHUP."""
    import fcntl
    import pty
    import termios

    def take_the_terminal():
        if controlling:
            fcntl.ioctl(0, termios.TIOCSCTTY, 0)

    terminal, its_side = pty.openpty()
    command = ["-m", "khepri_cli.main", "hub", "--config", str(lab_config(tmp_path, record))]
    hub = subprocess.Popen([sys.executable, *command], stdin=its_side, stdout=its_side, stderr=its_side, env=ENV,
                           start_new_session=True, preexec_fn=take_the_terminal)
    os.close(its_side)
    said = read_terminal_until(terminal, hub, lambda text: text.count("listening ") >= 2)
    return hub, terminal, re.search(r"listening robots (tcp://\S+)", said).group(1)


def read_terminal_until(terminal: int, hub: subprocess.Popen, done: Callable[[str], bool]) -> str:
    said, deadline = "", time.monotonic() + 30
    while not done(said):
        assert hub.poll() is None and time.monotonic() < deadline, said
        if select.select([terminal], [], [], 0.1)[0]:
            said += os.read(terminal, 4096).decode(errors="replace")
    return said


@pytest.mark.parametrize("stop", ["SIGHUP", "SIGTERM"])
def test_a_hub_whose_terminal_is_gone_stops_cleanly_and_closes_its_log(tmp_path, stop):
    """Its lines to the dead terminal fail (EIO): `hub: stopped` turned exit code 0 into 1, and a line said while
    the hub stopped (here a robot answering its stop with garbage) skipped closing the log, which lost its footer.
    SIGHUP: the terminal closing hangs up the hub; SIGTERM: `kill` once the hub's terminal is gone."""
    log = tmp_path / "run.mcap"
    hub, terminal, robots = start_hub_on_a_terminal(tmp_path, log, controlling=stop == "SIGHUP")
    robot = zmq.Context.instance().socket(zmq.DEALER)
    robot.linger = 0
    robot.connect(robots)
    try:
        robot.send(encode({"type": "hello", "id": 0, "driver": "sim"}))
        # The whole line, its end too: closing the terminal while the hub still writes it is another test.
        read_terminal_until(terminal, hub, lambda text: "robot 0 connected from 127.0.0.1\r\n" in text)
        os.close(terminal)               # the terminal goes: every later line to it fails with EIO
        terminal = None
        if stop == "SIGTERM":
            hub.send_signal(signal.SIGTERM)
        answer_the_hubs_stop_with_garbage(robot)
        code = hub.wait(timeout=15)
    finally:
        robot.close(0)
        if terminal is not None:
            os.close(terminal)
        stop_processes([hub])
    info = log_info(log)
    assert (code, info["truncated"]) == (0, False), info         # footer and summary written
    assert info["drops"] == {"bad message": 1}, info


def answer_the_hubs_stop_with_garbage(robot: zmq.Socket) -> None:
    """While the hub waits for the robots to acknowledge its shutdown stop: a drop it says on the console."""
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline:
        if robot.poll(100):
            message = decode(robot.recv(), "hub")
            if message["type"] == "command" and message["cmd"] == "stop":
                robot.send(b"not json")
                return
    raise AssertionError("the hub sent no stop")


def test_agents_end_with_the_process_that_started_them(tmp_path):
    """A `khepri sil` killed with SIGKILL left its agents running for ever."""
    starter = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from pathlib import Path; from hub.harness import spawn_agent\n"
        f"agent = spawn_agent('tcp://127.0.0.1:9', 0, Path({str(tmp_path / 'agent.log')!r}))\n"
        "print(agent.pid, flush=True); time.sleep(60)")], stdout=subprocess.PIPE, text=True, env=ENV)
    agent_pid = int(starter.stdout.readline())
    # An agent that died by itself before its starter would pass the check below without proving anything: wait
    # until it runs (a loaded machine takes seconds to start an interpreter) and check it still does.
    started = time.monotonic() + 30
    while "connecting to tcp://127.0.0.1:9" not in (tmp_path / "agent.log").read_text():
        assert time.monotonic() < started, (tmp_path / "agent.log").read_text()
        time.sleep(0.1)
    time.sleep(0.5)
    assert "zombie" not in _state(agent_pid), (tmp_path / "agent.log").read_text()
    starter.kill()
    starter.wait()
    deadline = time.monotonic() + 10
    while Path(f"/proc/{agent_pid}").exists() and "zombie" not in _state(agent_pid):
        assert time.monotonic() < deadline, "the agent outlived its starter"
        time.sleep(0.1)


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/status").read_text().split("State:")[1].split("\n")[0]
    except (OSError, IndexError):
        return "zombie"


@pytest.mark.parametrize("parent", ["\u00b2", "9" * 30])
def test_a_parent_pid_that_is_no_pid_is_ignored(monkeypatch, parent):
    """'²' passed str.isdigit and int() refused it: the agent ended in a ValueError before it started."""
    from onboard.agent.parent import PARENT_ENV, end_with_parent

    monkeypatch.setenv(PARENT_ENV, parent)
    end_with_parent()       # nothing to watch: no error, no signal


def test_the_keys_of_a_killed_sil_are_removed_by_the_next_one(tmp_path, monkeypatch):
    """SIGKILL runs no cleanup: a killed `khepri sil` left its temporary folder of secret keys behind."""
    import tempfile

    from hub.sil import KEY_FOLDER_PREFIX, remove_stale_key_folders

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / f"{KEY_FOLDER_PREFIX}{dead.pid}-abc"
    live = tmp_path / f"{KEY_FOLDER_PREFIX}{os.getpid()}-def"
    for folder in (stale, live):
        (folder / "robots").mkdir(parents=True)
        (folder / "robots" / "robot-0.key_secret").write_text("secret")
    odd = [tmp_path / f"{KEY_FOLDER_PREFIX}\u00b2-x", tmp_path / f"{KEY_FOLDER_PREFIX}{'9' * 30}-x"]
    for folder in odd:        # '²' passed str.isdigit, and int() refused it; 30 digits overflowed os.kill
        folder.mkdir()
    remove_stale_key_folders()
    assert not stale.exists() and live.exists() and all(folder.exists() for folder in odd)


def test_a_robots_text_with_a_lone_surrogate_neither_stops_the_recording_nor_ctl_status(tmp_path):
    """A behaviour state holding a lone surrogate (a file name read with surrogateescape, sent as the JSON escape
    \\ud800): the hub could not write that telemetry as UTF-8 and stopped recording for the rest of the run,
    and `khepri ctl status` ended with a UnicodeEncodeError. Now the log holds it escaped and ctl prints it."""
    log = tmp_path / "run.mcap"
    hub = start_hub(tmp_path, "-m", "khepri_cli.main", "hub", "--config", str(lab_config(tmp_path, log)))
    robots = next(x for x in (tmp_path / "hub.log").read_text().splitlines() if x.startswith("listening robots"))
    agent = zmq.Context.instance().socket(zmq.DEALER)
    agent.linger = 0
    agent.connect(robots.split()[-1])
    try:
        agent.send(encode({"type": "hello", "id": 0, "driver": "sim"}))
        for step in range(1, 11):
            agent.send(encode({"type": "telemetry", "id": 0, "step": step, "mode": "idle",
                               "behaviour": {"state": "bad\ud800name"}}))
            time.sleep(0.05)
        ctl = subprocess.run([sys.executable, "-m", "khepri_cli.main", "ctl", "status", "--hub",
                              control_endpoint(tmp_path)], capture_output=True, env=ENV, timeout=30)
        assert ctl.returncode == 0 and b"Traceback" not in ctl.stderr, ctl.stderr
        assert b"bad\\ud800name" in ctl.stdout, ctl.stdout
        hub.send_signal(signal.SIGINT)
        assert hub.wait(timeout=15) == 0
    finally:
        agent.close(0)
        stop_processes([hub])
    said = (tmp_path / "hub.log").read_text()
    assert "RECORDING STOPPED" not in said and "not recorded" not in said, said
    states = [r.payload["behaviour"]["state"] for r in read_log(log, topics=["/robot/0/telemetry"])]
    assert states == ["bad\ud800name"] * 10
