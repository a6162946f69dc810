"""The onboard agent, as a real process (or the real Agent class in a thread) against a scripted hub socket."""
import argparse
import os
import re
import select
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import zmq

from hub.harness import ScriptedHub, spawn_agent, stop_processes
from onboard.agent.devices import AgentClock, HubState, apply_frame
from onboard.agent.link import HubLink
from onboard.agent.loop import Agent
from onboard.behaviour import _REGISTRY, Behaviour, register
from onboard.drivers.sim import SimDriver
from onboard.hal import WheelOdometry
from onboard.protocol import DOWNLINK_TYPES, ProtocolError, encode
from onboard.protocol import decode as decode_message

RUN = {"run_id": "r1", "behaviour": "aggregate", "params": {}, "control_hz": 10.0, "lockstep": False,
       "clock": "local", "spec": {"max_wheel_speed_m_s": 0.81}}
FAR_NEIGHBOUR = [[1, 2.0, 0.5]]          # aggregate drives towards it: the wheels turn


@pytest.fixture
def scripted():
    hub = ScriptedHub()
    yield hub
    hub.close()


@pytest.fixture
def agent_process(scripted, tmp_path):
    process = spawn_agent(scripted.endpoint, 0, tmp_path / "agent.log")
    scripted.wait_for(lambda m: m["type"] == "hello")
    yield process
    stop_processes([process])


def wheels_after(hub, t0, moving):
    return lambda m: m["type"] == "wheels" and m["_at"] > t0 and ((m["left"], m["right"]) != (0.0, 0.0)) == moving


def feed(hub, seconds, **fields):
    """Frames at 20 Hz for ``seconds``; returns when the last one was sent."""
    end = time.monotonic() + seconds
    last = time.monotonic()
    while time.monotonic() < end:
        hub.frame(**fields)
        last = time.monotonic()
        hub.pump(0.05)
    return last


def start_run(hub, run=RUN):
    hub.send({"type": "command", "cmd": "start", "run": run})
    hub.wait_for(lambda m: m["type"] == "ack" and m["cmd"] == "start")


def test_agent_runs_the_behaviour_the_hub_starts(scripted, agent_process):
    start_run(scripted)
    t0 = time.monotonic()
    feed(scripted, 0.6, neighbours=FAR_NEIGHBOUR)
    scripted.wait_for(wheels_after(scripted, t0, moving=True))
    telemetry = scripted.wait_for(lambda m: m["type"] == "telemetry" and m["_at"] > t0 and m["behaviour"]
                                  and m["behaviour"]["state"] != "init")
    assert telemetry["run_id"] == "r1" and telemetry["behaviour"]["state"] == "gathering"
    assert telemetry["behaviour"]["finished"] is False and telemetry["loop"]["steps"] >= 1


def test_watchdog_stops_wheels_within_0_3_s_of_hub_silence_and_resumes(scripted, agent_process):
    start_run(scripted)
    t0 = time.monotonic()
    last_frame = feed(scripted, 1.0, neighbours=FAR_NEIGHBOUR)
    scripted.wait_for(wheels_after(scripted, t0, moving=True))
    stopped = scripted.wait_for(wheels_after(scripted, last_frame, moving=False), timeout_s=2.0)
    # When the agent stopped them (its own clock, the same monotonic clock on this machine): the arrival here
    # adds this test's and the socket's delays, which a real robot's wheels do not wait for.
    silence_to_stop = stopped["at_s"] - last_frame
    assert silence_to_stop < 0.3, (f"wheels stopped {silence_to_stop:.3f} s after the last frame "
                                   f"(arrived here after {stopped['_at'] - last_frame:.3f} s)")
    held = scripted.wait_for(lambda m: m["type"] == "telemetry" and m["_at"] > stopped["_at"])
    assert held["mode"] == "watchdog"
    # Held while the hub stays silent: the behaviour is not stepped, so nothing turns the wheels on again.
    scripted.pump(0.5)
    assert not [m for m in scripted.received if wheels_after(scripted, stopped["_at"], moving=True)(m)]
    resumed_at = time.monotonic()
    feed(scripted, 0.5, neighbours=FAR_NEIGHBOUR)
    scripted.wait_for(wheels_after(scripted, resumed_at, moving=True), timeout_s=2.0)


def test_the_agent_stops_its_wheels_after_the_watchdog_it_is_given(scripted, tmp_path):
    """--watchdog was checked for its range, but nothing showed the loop used it and not its 0.25 s default."""
    process = spawn_agent(scripted.endpoint, 0, tmp_path / "agent.log", extra=["--watchdog", "0.1"])
    try:
        scripted.wait_for(lambda m: m["type"] == "hello")
        start_run(scripted)
        t0 = time.monotonic()
        last_frame = feed(scripted, 1.0, neighbours=FAR_NEIGHBOUR)
        scripted.wait_for(wheels_after(scripted, t0, moving=True))
        stopped = scripted.wait_for(wheels_after(scripted, last_frame, moving=False), timeout_s=2.0)
        # Not before 0.1 s (frames came every 0.05 s, so the watchdog did not trip during the feed), and well
        # before the default 0.25 s.
        assert 0.09 <= stopped["at_s"] - last_frame < 0.2, stopped["at_s"] - last_frame
    finally:
        stop_processes([process])


def test_estop_stops_the_wheels_before_the_acknowledgement(scripted, agent_process):
    start_run(scripted)
    t0 = time.monotonic()
    feed(scripted, 0.5, neighbours=FAR_NEIGHBOUR)
    scripted.wait_for(wheels_after(scripted, t0, moving=True))
    sent = time.monotonic()
    scripted.send({"type": "command", "cmd": "estop", "reason": "test"})
    ack = scripted.wait_for(lambda m: m["type"] == "ack" and m["cmd"] == "estop")
    stop = scripted.wait_for(wheels_after(scripted, sent, moving=False))
    assert stop["_at"] <= ack["_at"] and ack["_at"] - sent < 0.05
    # Frames that still say run cannot undo a latched e-stop... only the hub's mode can, and it says estop.
    t1 = time.monotonic()
    feed(scripted, 0.4, mode="estop", neighbours=FAR_NEIGHBOUR)
    assert not [m for m in scripted.received if wheels_after(scripted, t1, moving=True)(m)]


def test_a_held_agent_reports_a_loop_rate_of_zero_not_its_last_runs(scripted, agent_process):
    """`ctl status` showed `estop ... loop Hz 10.0` through an e-stop: the rate of the last stepping second."""
    start_run(scripted)
    feed(scripted, 1.5, neighbours=FAR_NEIGHBOUR)
    stepping = scripted.wait_for(lambda m: m["type"] == "telemetry" and m["loop"]["hz"] > 5.0)
    assert stepping["mode"] == "run"
    scripted.send({"type": "command", "cmd": "estop", "reason": "operator e-stop"})
    t0 = time.monotonic()
    feed(scripted, 2.5, mode="estop")
    held = [m for m in scripted.received if m["type"] == "telemetry" and m["_at"] > t0]
    assert held[-1]["mode"] == "estop" and held[-1]["loop"]["hz"] == 0.0, held[-1]["loop"]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_sigterm_and_sighup_stop_the_wheels_before_exit_and_tell_the_hub(scripted, agent_process, sig):
    """SIGHUP (the ssh session the agent was started from closing) killed the agent with its wheels turning."""
    start_run(scripted)
    t0 = time.monotonic()
    feed(scripted, 0.5, neighbours=FAR_NEIGHBOUR)
    scripted.wait_for(wheels_after(scripted, t0, moving=True))
    agent_process.send_signal(sig)
    assert agent_process.wait(timeout=5.0) == 0
    scripted.pump(0.2)
    wheels = [m for m in scripted.received if m["type"] == "wheels"]
    assert (wheels[-1]["left"], wheels[-1]["right"]) == (0.0, 0.0)
    assert scripted.received[-1]["type"] == "telemetry" and scripted.received[-1]["mode"] == "exiting"


def spawn_agent_on_a_terminal(endpoint: str, ignore_sighup: bool = False):
    """An agent started by hand in a terminal (a pseudo-terminal here, as sshd gives): its own session, with
    the terminal as its controlling one, so that closing the terminal's other end hangs it up as an ssh
    session dropping does: SIGHUP, and every later write to it fails (EIO). The process and that other end."""
    import fcntl
    import pty
    import termios

    from hub.harness import ROOT

    def take_the_terminal():
        fcntl.ioctl(0, termios.TIOCSCTTY, 0)
        if ignore_sighup:                            # as `nohup` does
            signal.signal(signal.SIGHUP, signal.SIG_IGN)

    terminal, its_side = pty.openpty()
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    command = [sys.executable, "-m", "onboard.agent", "--id", "0", "--hub", endpoint, "--driver", "sim"]
    process = subprocess.Popen(command, stdin=its_side, stdout=its_side, stderr=its_side, env=env,
                               start_new_session=True, preexec_fn=take_the_terminal)
    os.close(its_side)
    return process, terminal


def read_terminal(terminal: int) -> bytes:
    said = b""
    while select.select([terminal], [], [], 0)[0]:
        said += os.read(terminal, 4096)
    return said


def test_a_stopped_agent_is_ended_by_sigterm_not_left_for_sigkill(scripted, tmp_path):
    """An agent stopped with SIGSTOP (or Ctrl-Z) handles SIGTERM only once it runs again: stop_processes waited
    its whole timeout and then killed it (exit -9, and 20 s in sil)."""
    process = spawn_agent(scripted.endpoint, 0, tmp_path / "agent.log")
    try:
        scripted.wait_for(lambda m: m["type"] == "hello")
        process.send_signal(signal.SIGSTOP)
        assert stop_processes([process], timeout_s=5.0) == [0]
    finally:
        process.kill()


def test_closing_the_agents_terminal_stops_its_wheels_and_it_leaves_cleanly(scripted):
    """The terminal hung up: the agent must stop its wheels and tell the hub, as for SIGTERM, and its lines to
    the dead terminal (EIO) must neither cut that short nor fail its exit."""
    process, terminal = spawn_agent_on_a_terminal(scripted.endpoint)
    try:
        scripted.wait_for(lambda m: m["type"] == "hello")
        start_run(scripted)
        t0 = time.monotonic()
        feed(scripted, 0.5, neighbours=FAR_NEIGHBOUR)
        scripted.wait_for(wheels_after(scripted, t0, moving=True))
        assert b"run r1: aggregate" in read_terminal(terminal)
        os.close(terminal)                 # the terminal closes: SIGHUP to the agent, its console gone
        terminal = None
        assert process.wait(timeout=5.0) == 0
        scripted.pump(0.2)
        wheels = [m for m in scripted.received if m["type"] == "wheels"]
        assert (wheels[-1]["left"], wheels[-1]["right"]) == (0.0, 0.0)
        assert scripted.received[-1]["type"] == "telemetry" and scripted.received[-1]["mode"] == "exiting"
    finally:
        if terminal is not None:
            os.close(terminal)
        stop_processes([process])


def test_an_agent_started_with_nohup_outlives_its_terminal(scripted):
    """SIGHUP ignored at start (`nohup khepri agent ...`) is the user's wish to keep the agent running."""
    process, terminal = spawn_agent_on_a_terminal(scripted.endpoint, ignore_sighup=True)
    try:
        scripted.wait_for(lambda m: m["type"] == "hello")
        read_terminal(terminal)
        process.send_signal(signal.SIGHUP)
        t0 = time.monotonic()
        feed(scripted, 0.5)
        assert process.poll() is None
        scripted.wait_for(lambda m: m["type"] == "telemetry" and m["_at"] > t0 and m["mode"] == "run")
    finally:
        os.close(terminal)
        assert stop_processes([process]) == [0]


def test_lockstep_agent_answers_each_frame_once_on_the_hub_clock(scripted, agent_process):
    start_run(scripted, {**RUN, "run_id": "lock", "lockstep": True, "clock": "hub"})
    for k in range(20):
        frame = scripted.frame(clock_s=round(k * 0.1, 3), neighbours=FAR_NEIGHBOUR)
        answer = scripted.wait_for(lambda m, seq=frame["seq"]: m["type"] == "telemetry" and m["step"] == seq)
        assert answer["clock_s"] == pytest.approx(k * 0.1)
        assert answer["behaviour"] is not None
    answers = [m for m in scripted.received if m["type"] == "telemetry" and m.get("run_id") == "lock"]
    steps = [m["step"] for m in answers if m["behaviour"] is not None]
    assert len(steps) == len(set(steps))          # never two steps for one frame


def test_a_lockstep_agent_waits_out_a_slow_hub_without_stopping_or_reconnecting(scripted, agent_process):
    """In lockstep the hub is silent while it waits for a slower agent. After 0.25 s the agent's watchdog sent a
    wheel stop, which landed in the step the hub was waiting on; after 2 s it reopened its socket and lost the
    next frame. Simulated wheels move only when the hub steps, so the agent waits."""
    start_run(scripted, {**RUN, "run_id": "lock", "lockstep": True, "clock": "hub"})
    first = scripted.frame(clock_s=0.0, neighbours=FAR_NEIGHBOUR)
    scripted.wait_for(lambda m: m["type"] == "telemetry" and m["step"] == first["seq"])
    connection, silent_from = scripted.routing, time.monotonic()
    time.sleep(2.6)
    second = scripted.frame(clock_s=0.1, neighbours=FAR_NEIGHBOUR)
    answer = scripted.wait_for(lambda m: m["type"] == "telemetry" and m["step"] == second["seq"])
    assert answer["frames_lost"] == 0 and answer["mode"] == "run" and answer["loop"]["steps"] == 2
    assert scripted.routing == connection                   # the same connection: not reopened
    during = [m for m in scripted.received if silent_from < m["_at"] < silent_from + 2.6]
    assert not [m for m in during if m["type"] == "wheels"], during


class Explode(Behaviour):
    def step(self) -> None:
        self.robot.wheels.set_speeds(0.2, 0.2)
        if self.robot.clock.now() > 0.3:
            raise RuntimeError("behaviour bug: " + "a long account " * 100)


@pytest.fixture
def explode():
    """"test-explode", known only to the test that asks for it: registered as this module was imported, it was
    among the known behaviours of every test the session ran after collecting this file."""
    register("test-explode")(Explode)
    yield "test-explode"
    _REGISTRY.pop("test-explode", None)


def test_an_exception_in_the_behaviour_stops_the_wheels_and_ends_the_agent(scripted, explode):
    link = HubLink(0, scripted.endpoint)
    agent = Agent(0, link, lambda a: SimDriver(link.send, lambda: a.state.sim), log=lambda line: None)
    failure = []

    def serve():
        try:
            agent.serve()
        except RuntimeError as err:
            failure.append(err)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    scripted.wait_for(lambda m: m["type"] == "hello")
    start_run(scripted, {**RUN, "behaviour": explode})
    deadline = time.monotonic() + 5.0
    while thread.is_alive() and time.monotonic() < deadline:
        scripted.frame()
        scripted.pump(0.05)
    thread.join(timeout=1.0)
    link.close()
    assert failure and "behaviour bug" in str(failure[0])
    assert failure[0].traceback_logged           # the agent logged it: khepri's last line does not repeat it
    scripted.pump(0.2)
    wheels = [m for m in scripted.received if m["type"] == "wheels"]
    assert any(m["left"] == 0.2 for m in wheels), "the behaviour never drove"
    assert (wheels[-1]["left"], wheels[-1]["right"]) == (0.0, 0.0)
    # The hub hears why, cut in the middle: the end says where and when (a cut at 200 characters lost it).
    said = [m["error"] for m in scripted.received if m["type"] == "telemetry" and m.get("error")]
    assert said and said[-1].startswith("behaviour crashed: robot 0, step(): RuntimeError: behaviour bug: ")
    assert re.search(r" \.\.\. .* at test_agent\.py:\d+ \(at t = 0\.\d s\)$", said[-1]), said[-1]
    assert len(said[-1]) <= 200


NEIGHBOURS = [[3, 0.5, -1.25], [7, 2.9999, 3.1416], [12, 0.0, 0.0], [999_999, 1.0, -3.1415]]


def encoded_frame(neighbours=NEIGHBOURS):
    return encode({"type": "frame", "seq": 4, "mode": "run", "hub_t": 12.5, "pose": [1.0, 2.0, 0.5],
                   "pose_age_s": 0.002, "neighbours": neighbours, "messages": [[3, 1.0, {"k": 1}]]})


def test_the_agents_decoder_gives_the_neighbours_as_columns_of_the_same_values():
    rows = decode_message(encoded_frame(), "hub", accept=DOWNLINK_TYPES)
    columns = decode_message(encoded_frame(), "hub", accept=DOWNLINK_TYPES, neighbour_columns=True)
    ids, ranges, bearings = columns.pop("neighbours")
    assert ids.dtype == np.int64 and ranges.dtype == np.float64 and bearings.dtype == np.float64
    assert [[i, r, b] for i, r, b in zip(ids.tolist(), ranges.tolist(), bearings.tolist())] == rows.pop("neighbours")
    assert columns == rows                      # everything else as before
    empty = decode_message(encoded_frame([]), "hub", neighbour_columns=True)["neighbours"]
    assert [len(column) for column in empty] == [0, 0, 0]
    hello = encode({"type": "hello", "id": 3, "driver": "kh4"})
    assert decode_message(hello, "robot 3", neighbour_columns=True) == decode_message(hello, "robot 3")


@pytest.mark.parametrize("column, value", [(0, 1_000_000), (1, -0.5), (1, float("nan")), (2, float("inf"))])
def test_the_columns_decoder_rejects_what_the_rows_decoder_rejects(column, value):
    data = bytearray(encoded_frame())
    record = np.frombuffer(data, dtype=[("id", "<u4"), ("range", "<f8"), ("bearing", "<f8")], count=1, offset=72)
    record[0][column] = value
    errors = []
    for columns in (False, True):
        with pytest.raises(ProtocolError) as err:
            decode_message(bytes(data), "hub", neighbour_columns=columns)
        errors.append(str(err.value))
    assert errors[0] == errors[1] and f"frame.neighbours[0][{column}]" in errors[0]


def test_the_devices_see_the_same_neighbours_from_columns_and_from_rows():
    tables = []
    for columns in (False, True):
        state = HubState()
        apply_frame(state, decode_message(encoded_frame(), "hub", neighbour_columns=columns), AgentClock(state), 1.0)
        tables.append(state.neighbours)
    rows, columns = tables
    assert list(columns) == list(rows) and len(columns) == len(NEIGHBOURS)
    np.testing.assert_array_equal(columns.ids, rows.ids)
    np.testing.assert_array_equal(columns.xy, rows.xy)
    assert [n.id for n in columns] == [3, 7, 12, 999_999]


def test_the_link_hands_frames_over_with_neighbour_columns(scripted):
    link = HubLink(0, scripted.endpoint)
    try:
        deadline = time.monotonic() + 10.0
        while scripted.routing is None and time.monotonic() < deadline:   # nothing is queued until connected
            link.send({"type": "hello", "driver": "test"})
            scripted.pump(0.1)
        scripted.frame(neighbours=NEIGHBOURS)
        deadline = time.monotonic() + 5.0
        frames = []
        while not frames and time.monotonic() < deadline:
            frames = [m for m in link.receive(0.1) if m["type"] == "frame"]
    finally:
        link.close()
    ids, ranges, bearings = frames[0]["neighbours"]
    assert ids.tolist() == [n[0] for n in NEIGHBOURS] and ranges.tolist() == [n[1] for n in NEIGHBOURS]
    assert bearings.tolist() == [n[2] for n in NEIGHBOURS]


def test_sends_before_the_hub_answered_are_not_counted_as_unsent_but_later_ones_are(scripted):
    """Every clean SIL run reported a few messages the agents could not send: the first hello (and idle
    telemetry) leave before the connection is up, which loses nothing. A send refused after the hub has spoken
    (here: the hub gone) is a loss, and still counted."""
    link = HubLink(0, "tcp://127.0.0.1:9")             # nothing listens: nothing can leave, nothing is lost
    try:
        assert [link.send({"type": "hello", "driver": "test"}) for _ in range(3)] == [False] * 3
        assert link.unsent == 0
    finally:
        link.close()
    link = HubLink(0, scripted.endpoint)
    try:
        link.send({"type": "hello", "driver": "test"})      # at once, as the agent does: usually not up yet
        deadline = time.monotonic() + 10.0
        while scripted.routing is None and time.monotonic() < deadline:
            link.send({"type": "hello", "driver": "test"})
            scripted.pump(0.1)
        scripted.frame()
        while not link.receive(0.1) and time.monotonic() < deadline:
            pass
        assert link.unsent == 0
        scripted.close()                                     # the hub goes away mid-run
        deadline = time.monotonic() + 5.0
        while link.send({"type": "hello", "driver": "test"}) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert link.unsent >= 1
    finally:
        link.close()


def test_an_agent_with_no_hub_says_so_and_a_bad_address_is_refused(first_waiting_line):
    """Nothing listens on the port: the agent keeps trying and says what to check, instead of sitting quiet.
    An address ZeroMQ refuses is a one-line error naming --hub."""
    import socket as sockets

    from onboard.agent.cli import add_agent_arguments, run_agent
    from onboard.config import ConfigError

    with sockets.socket() as probe:          # a free port, closed again: nothing listens there
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    started = time.monotonic()
    waiting = first_waiting_line(HubLink(0, f"tcp://127.0.0.1:{port}"))
    # The connection was refused: that is what it says, not every question it might ask (docs/lab.md).
    assert waiting.startswith(f"agent 0: no frame from the hub at tcp://127.0.0.1:{port} yet; still trying: "
                              f"nothing accepts a connection at tcp://127.0.0.1:{port} (refused or unreachable): is "
                              "the hub running, and are --hub and --port the host and robots port it printed when "
                              "it started? A hub listening on ::1 only"), waiting     # and the family's hint
    assert time.monotonic() - started < 5.0
    public, secret = zmq.curve_keypair()        # keys change nothing when no hub is there
    keyed = HubLink(0, f"tcp://127.0.0.1:{port}", keys={"public": public, "secret": secret, "server": public})
    assert "nothing accepts a connection at" in first_waiting_line(keyed)

    parser = argparse.ArgumentParser()
    add_agent_arguments(parser)      # every option with its default, as the command line gives them
    args = parser.parse_args(["--id", "0", "--hub", "tcp://bad host", "--driver", "sim", "--quiet"])
    with pytest.raises(ConfigError, match=r"--hub: 'tcp://bad host' has no port"):
        run_agent(args)
    args = parser.parse_args(["--id", "0", "--hub", "udp://bad host", "--driver", "sim", "--quiet"])
    with pytest.raises(ConfigError, match=r"--hub: cannot connect to 'udp://bad host'"):
        run_agent(args)


@pytest.mark.parametrize("option", ["--calibration", "--library"])
def test_kh4_options_with_the_sim_driver_are_refused_rather_than_ignored(option, capsys):
    """The notice that said they were ignored was dropped with --quiet: the file went unused without a word."""
    from onboard.agent.cli import add_agent_arguments, run_agent
    from onboard.config import ConfigError

    parser = argparse.ArgumentParser()
    add_agent_arguments(parser)
    # a bad --hub: without the check, the agent stopped there (and the test did not wait for a hub)
    args = parser.parse_args(["--id", "0", "--hub", "tcp://bad host", "--driver", "sim", "--quiet", option, "c.yaml"])
    with pytest.raises(ConfigError) as info:
        run_agent(args)
    assert info.value.field == option
    assert info.value.problem.startswith("is only for --driver kh4: the sim driver's readings come from the hub")


@pytest.mark.parametrize("value", ["0", "-0.1", "0.31", "60", "nan", "inf"])
def test_a_watchdog_longer_than_0_3_s_or_not_a_duration_is_refused(value):
    """The agent's watchdog stops the wheels once the hub is silent for --watchdog: a longer one (or nan, which
    compares false with every time) would leave a robot driving blind. No test gave the option at all."""
    from onboard.agent.cli import add_agent_arguments, run_agent
    from onboard.config import ConfigError

    parser = argparse.ArgumentParser()
    add_agent_arguments(parser)
    args = parser.parse_args(["--id", "0", "--hub", "tcp://bad host", "--driver", "sim", "--quiet",
                              "--watchdog", value])
    with pytest.raises(ConfigError) as info:
        run_agent(args)
    assert info.value.field == "--watchdog" and info.value.problem.startswith("must be in (0, 0.3] seconds")
    args = parser.parse_args(["--id", "0", "--hub", "tcp://bad host", "--driver", "sim", "--quiet",
                              "--watchdog", "0.3"])
    with pytest.raises(ConfigError, match="--hub"):          # 0.3 s passes: the bad --hub stops it next
        run_agent(args)


class BrokenIRDriver(SimDriver):
    """A robot whose IR bus has given up: the hardware fails, not the behaviour's code."""

    def proximity(self):
        from onboard.drivers import DriverError

        raise DriverError("kh4_proximity_ir failed with code -4")


def test_a_driver_failing_inside_step_is_reported_as_the_drivers_fault_not_the_behaviours():
    from onboard.behaviour import BehaviourError

    link = HubLink(0, "tcp://127.0.0.1:9")            # nothing there: the agent only ticks here
    agent = Agent(0, link, lambda a: BrokenIRDriver(link.send, lambda: a.state.sim), log=lambda line: None)
    try:
        agent.start_run({"run_id": "r1", "behaviour": "aggregate", "params": {}, "control_hz": 10.0})
        agent.state.mode = "run"
        with pytest.raises(BehaviourError):
            agent.tick(time.monotonic())
        assert agent.error.startswith("driver failed: robot 0, step(): DriverError: kh4_proximity_ir failed")
    finally:
        link.close()


def test_the_sim_driver_counts_the_encoders_from_the_agents_first_frame_as_the_kh4_driver_does():
    """An agent that joins (or restarts) mid-run: its odometry starts at 0 on a robot, so in SIL too, and from
    the agent's first frame, not from whenever its behaviour first reads it."""
    state = HubState()
    apply_frame(state, frame_with_odometry(1, [1.5, 1.25]), AgentClock(state), 1.0)
    driver = SimDriver(lambda message: True, lambda: state.sim, lambda: state.sim_first)
    apply_frame(state, frame_with_odometry(2, [1.75, 1.0]), AgentClock(state), 1.0)
    assert driver.encoders() == WheelOdometry(0.25, -0.25)
    apply_frame(state, frame_with_odometry(3, [2.0, 1.0]), AgentClock(state), 1.0)
    assert driver.encoders() == WheelOdometry(0.5, -0.25)


def frame_with_odometry(seq, odometry):
    return {"seq": seq, "pose": None, "neighbours": [], "messages": [], "sim": {"ir": [0.0] * 8, "odo": odometry}}


def test_an_empty_library_or_calibration_path_is_refused_not_taken_as_the_default():
    from onboard.agent.cli import add_agent_arguments, run_agent
    from onboard.config import ConfigError

    parser = argparse.ArgumentParser()
    add_agent_arguments(parser)
    for option in ("--library", "--calibration"):
        args = parser.parse_args(["--id", "0", "--driver", "kh4", option, ""])
        with pytest.raises(ConfigError, match=f"^{option}: an empty path"):
            run_agent(args)


def test_a_bad_calibration_file_is_named_as_the_option_that_gave_it(tmp_path, monkeypatch):
    """It was said as `--driver: cannot open the KheperaIV: ...`, sending the user to the wrong option."""
    from onboard.agent.cli import add_agent_arguments, run_agent
    from onboard.config import ConfigError

    bad = tmp_path / "kh4-0.yaml"
    bad.write_text("proximity: [{ambient: 5, touch: 1}]\n")
    parser = argparse.ArgumentParser()
    add_agent_arguments(parser)
    args = parser.parse_args(["--id", "0", "--driver", "kh4", "--calibration", str(bad)])
    with pytest.raises(ConfigError) as info:
        run_agent(args)
    assert info.value.field == "--calibration" and info.value.problem.startswith(f"{bad}: proximity")
    monkeypatch.setenv("KHEPRI_KH4_CALIBRATION", str(bad))
    with pytest.raises(ConfigError) as info:
        run_agent(parser.parse_args(["--id", "0", "--driver", "kh4"]))
    assert info.value.field == "$KHEPRI_KH4_CALIBRATION"


def test_a_calibration_value_yaml_cannot_read_is_named_as_the_file_not_the_robot(tmp_path):
    """`robot: !!int "x"` was `--driver kh4: cannot open the KheperaIV: invalid literal for int()`."""
    from onboard.agent.cli import add_agent_arguments, run_agent
    from onboard.config import ConfigError

    bad = tmp_path / "kh4-0.yaml"
    bad.write_text('robot: !!int "x"\nproximity: []\n')
    parser = argparse.ArgumentParser()
    add_agent_arguments(parser)
    with pytest.raises(ConfigError) as info:
        run_agent(parser.parse_args(["--id", "0", "--driver", "kh4", "--calibration", str(bad)]))
    assert str(info.value) == f"--calibration: {bad}:1: cannot read 'x' as an integer"


def test_a_library_that_will_not_load_is_named_as_the_option_that_gave_it(tmp_path, monkeypatch):
    """`--library /nope/libkhepera.so` said `--driver kh4: ... pass --library PATH or set KHEPRI_LIBKHEPERA`: the
    wrong option, and advice to pass what was passed."""
    from onboard.agent.cli import add_agent_arguments, run_agent
    from onboard.config import ConfigError

    monkeypatch.delenv("KHEPRI_LIBKHEPERA", raising=False)
    monkeypatch.chdir(tmp_path)
    parser = argparse.ArgumentParser()
    add_agent_arguments(parser)
    missing = str(tmp_path / "nope" / "libkhepera.so")
    with pytest.raises(ConfigError) as info:
        run_agent(parser.parse_args(["--id", "0", "--driver", "kh4", "--library", missing]))
    assert info.value.field == "--library" and "--library PATH" not in info.value.problem
    assert f"cannot load libkhepera from {missing!r}" in info.value.problem
    with pytest.raises(ConfigError) as info:       # the default name, found nowhere: where to give the path
        run_agent(parser.parse_args(["--id", "0", "--driver", "kh4"]))
    assert info.value.field == "--driver kh4" and info.value.problem.endswith("pass --library PATH or set "
                                                                              "KHEPRI_LIBKHEPERA")
    monkeypatch.setenv("KHEPRI_LIBKHEPERA", missing)
    with pytest.raises(ConfigError) as info:
        run_agent(parser.parse_args(["--id", "0", "--driver", "kh4"]))
    assert info.value.field == "$KHEPRI_LIBKHEPERA"


def test_the_agents_neighbour_columns_are_read_only_as_in_the_simulator():
    """Writing into them raised in simulation but not on the agent, so such a bug showed up only in sim."""
    state = HubState()
    apply_frame(state, {"seq": 1, "pose": [0.0, 0.0, 0.0], "neighbours": [[1, 2.0, 0.5]], "messages": []},
                AgentClock(state), 0.0)
    table = state.neighbours
    for column in (table.ids, table.ranges_m, table.bearings_rad, table.xy):
        with pytest.raises(ValueError, match="read-only"):
            column[...] = 0


def test_a_pose_from_before_a_new_run_keeps_its_age():
    """The clock restarts at 0 with each run, and the last frame's pose kept its stamp on the old run's clock:
    in the new run's future, its age read 0, and a pose minutes old (motion capture lost the robot before the
    run, so no frame since carried one) passed the behaviour's staleness checks as fresh."""
    from onboard.agent.devices import HubPositioning, HubRangeAndBearing

    state = HubState()
    clock = AgentClock(state)
    clock.started -= 300.0                                   # run 1 has gone for 300 s
    apply_frame(state, {"seq": 1, "pose": [1.0, 2.0, 0.0], "neighbours": [[1, 2.0, 0.5]], "messages": []},
                clock, 0.0)
    clock.started -= 5.0                                     # 5 s later: frames without a pose since
    clock.restart(False)                                     # run 2
    pose = HubPositioning(state, clock).pose()
    assert pose is not None and pose.age_s == pytest.approx(5.0, abs=0.05)
    assert HubRangeAndBearing(state, clock).neighbours().age_s == pytest.approx(5.0, abs=0.05)


def test_frames_the_agent_never_got_are_counted_by_their_sequence_numbers():
    """telemetry.frames_lost (summed in SIL's `frames lost on the way to the agents`) was only ever checked to be 0,
    which an agent that never counted passed."""
    state = HubState()
    for seq in (1, 2, 5, 6, 10):         # 3 and 4 lost, then 7, 8 and 9
        apply_frame(state, {"seq": seq, "pose": None, "neighbours": [], "messages": []}, AgentClock(state), 0.0)
    assert (state.seq, state.frames_lost) == (10, 5)


def test_a_flooded_agent_keeps_the_newest_messages_and_counts_the_others():
    """A robot keeps Radio.INBOX_LIMIT messages between two steps, as the simulator does; the rest is counted,
    not lost without a trace."""
    from onboard.hal import Radio

    state = HubState()
    flood = [[1, 0.5, {"n": n}] for n in range(Radio.INBOX_LIMIT + 44)]
    apply_frame(state, {"seq": 1, "pose": None, "neighbours": [], "messages": flood}, AgentClock(state), 0.0)
    assert len(state.inbox) == Radio.INBOX_LIMIT and state.inbox_dropped == 44
    assert state.inbox[0].payload == {"n": 44} and state.inbox[-1].payload == {"n": Radio.INBOX_LIMIT + 43}


def test_a_run_the_agent_cannot_start_is_said_once_though_the_hub_repeats_it(scripted, agent_process, tmp_path):
    """Without --import for the user's behaviour the agent said 'cannot start the run' twice a second."""
    unknown = dict(RUN, run_id="r-unknown", behaviour="not-imported-here")
    for _ in range(5):
        start_run(scripted, unknown)
        feed(scripted, 0.1)
    telemetry = scripted.wait_for(lambda m: m["type"] == "telemetry" and m.get("error"))
    assert "unknown behaviour 'not-imported-here'" in telemetry["error"]
    start_run(scripted, dict(unknown, run_id="r-unknown-2"))       # a new run is tried, and said, again
    feed(scripted, 0.2)
    said = [line for line in (tmp_path / "agent.log").read_text().splitlines() if "cannot start the run" in line]
    assert len(said) == 2, said
    start_run(scripted)                                            # a run it can start still starts
    t0 = time.monotonic()
    feed(scripted, 0.6, neighbours=FAR_NEIGHBOUR)
    scripted.wait_for(wheels_after(scripted, t0, moving=True))


def test_a_whole_hub_address_and_a_port_are_refused_together():
    """`--hub tcp://10.0.0.1:5561 --port 5560`: the address's own port won, silently."""
    from onboard.agent.link import hub_endpoint
    from onboard.config import ConfigError

    assert hub_endpoint("tcp://10.0.0.1:5561", 5560) == "tcp://10.0.0.1:5561"
    assert hub_endpoint("10.0.0.1", 5560, port_given=True) == "tcp://10.0.0.1:5560"
    with pytest.raises(ConfigError, match="--port: 'tcp://10.0.0.1:5561' is a whole address with its own port"):
        hub_endpoint("tcp://10.0.0.1:5561", 5560, port_given=True)
    ctl = subprocess.run([sys.executable, "-m", "khepri_cli.main", "ctl", "status", "--hub", "tcp://127.0.0.1:1",
                          "--port", "5561"], capture_output=True, text=True, timeout=60)
    assert ctl.returncode == 2 and "--port: 'tcp://127.0.0.1:1' is a whole address" in ctl.stderr


def test_a_whole_tcp_address_without_a_port_says_so():
    """`--hub tcp://127.0.0.1` said only "cannot connect to 'tcp://127.0.0.1': Invalid argument"."""
    from onboard.agent.link import hub_endpoint
    from onboard.config import ConfigError

    for address, host in (("tcp://127.0.0.1", "127.0.0.1"), ("tcp://[::1]", "::1"), ("tcp://hub.lab", "hub.lab")):
        with pytest.raises(ConfigError) as info:
            hub_endpoint(address, 5560)
        assert str(info.value) == (f"--hub: {address!r} has no port: a whole address ends with one ({address}:5560), "
                                   f"or give the host alone (--hub {host}) and the port with --port")
    assert hub_endpoint("tcp://[::1]:5560", 5561) == "tcp://[::1]:5560"
    assert hub_endpoint("ipc:///tmp/hub", 5560) == "ipc:///tmp/hub"      # no port to have


def test_an_ipv6_address_is_written_in_brackets_and_a_port_beside_it_refused():
    from onboard.agent.link import hub_endpoint
    from onboard.config import ConfigError

    assert hub_endpoint("::1", 5560) == hub_endpoint("[::1]", 5560) == "tcp://[::1]:5560"
    assert hub_endpoint("fd00::0:7", 5560) == "tcp://[fd00::7]:5560"
    with pytest.raises(ConfigError, match=r"--hub \[::1\] --port 5000\), or a whole address \(--hub tcp://\[::1\]:5000"):
        hub_endpoint("[::1]:5000", 5560)


@pytest.mark.ipv6_loopback
def test_a_hub_on_an_ipv6_address_serves_a_real_agent_and_ctl(tmp_path, make_scenario):
    """A lab on IPv6: ZeroMQ needs its IPV6 option on both ends, and without it the hub could not bind ::1
    ("No such device") and an agent given --hub ::1 made tcp://::1:5560, which never connects."""
    from hub.config import parse_config
    from hub.control import request
    from hub.harness import HubThread, spawn_agent, stop_processes

    config = parse_config({"source": {"type": "sim"}, "security": {"insecure": True},
                           "network": {"bind": "::1", "robot_port": 0, "control_port": 0}})
    scenario = make_scenario(robots={"count": 2}, arena={"walls": [-2.0, -2.0, 2.0, 2.0]})
    with HubThread(config, scenario=scenario) as hub:
        assert hub.endpoints["robots"].startswith("tcp://[::1]:")
        port = hub.endpoints["robots"].rsplit(":", 1)[1]
        agent = spawn_agent(hub.endpoints["robots"], 0, tmp_path / "agent.log")
        host_agent = spawn_agent("::1", 1, tmp_path / "agent1.log", extra=["--port", port])   # --hub ::1
        try:
            hub.wait_until(lambda s: s["robots"][0]["connected"] and s["robots"][1]["connected"])
        finally:
            stop_processes([agent, host_agent])
        control_port = hub.endpoints["control"].rsplit(":", 1)[1]
        ctl = subprocess.run([sys.executable, "-m", "khepri_cli.main", "ctl", "status", "--hub", "::1",
                              "--port", control_port], capture_output=True, text=True, timeout=60)
        assert ctl.returncode == 0 and "robot  connected" in ctl.stdout, ctl.stderr
        assert request(hub.endpoints["control"], "status")["ok"]


def start_ipv6_lab(bind, robots, make_scenario):
    from hub.config import parse_config
    from hub.harness import HubThread

    config = parse_config({"source": {"type": "sim"}, "security": {"insecure": True},
                           "network": {"bind": bind, "robot_port": 0, "control_port": 0}})
    return HubThread(config, scenario=make_scenario(robots={"count": robots}, arena={"walls": [-2.0, -2.0, 2.0, 2.0]}))


def ctl_status(host, control_endpoint, *options):
    port = control_endpoint.rsplit(":", 1)[1]
    return subprocess.run([sys.executable, "-m", "khepri_cli.main", "ctl", "status", "--hub", host, "--port", port,
                           *options], capture_output=True, text=True, timeout=60)


def test_localhost_stands_for_both_loopbacks_and_every_other_address_for_itself():
    from onboard.agent.link import endpoint_candidates

    both = ["tcp://127.0.0.1:5560", "tcp://[::1]:5560"]
    assert endpoint_candidates("tcp://localhost:5560") == endpoint_candidates("tcp://LocalHost.:5560") == both
    assert endpoint_candidates("tcp://localhost:*") == ["tcp://127.0.0.1:*", "tcp://[::1]:*"]    # the hub's bind
    for alone in ("tcp://127.0.0.1:5560", "tcp://[::1]:5560", "tcp://labpc:5560", "tcp://eth0;localhost:5560",
                  "ipc:///tmp/hub"):
        assert endpoint_candidates(alone) == [alone]


@pytest.mark.ipv6_loopback
@pytest.mark.parametrize("bind, hosts", [("::1", ["localhost"]), ("localhost", ["::1", "127.0.0.1", "localhost"])])
def test_localhost_and_either_loopback_reach_the_hub_whichever_family_it_listens_on(tmp_path, make_scenario,
                                                                                    bind, hosts):
    """ZeroMQ resolves `localhost` to IPv4 only: a hub on ::1 was never reached by an agent or ctl given --hub
    localhost, and a hub given bind: localhost listened on 127.0.0.1 alone, never reached as ::1."""
    from hub.harness import spawn_agent, stop_processes

    with start_ipv6_lab(bind, len(hosts), make_scenario) as hub:
        if bind == "localhost":
            port = hub.endpoints["robots"].rsplit(":", 1)[1]
            listening = [line for line in hub.lines if line.startswith("listening ")]
            assert listening[0] == f"listening robots tcp://127.0.0.1:{port} and tcp://[::1]:{port}"
        port = hub.endpoints["robots"].rsplit(":", 1)[1]
        agents = [spawn_agent(host, i, tmp_path / f"agent{i}.log", extra=["--port", port])
                  for i, host in enumerate(hosts)]
        try:
            hub.wait_until(lambda s: all(robot["connected"] for robot in s["robots"]))
            time.sleep(0.5)       # an agent on two connections at once would flip between them: it is on one
            status = hub.wait_until(lambda s: all(robot["connected"] for robot in s["robots"]))
            assert "duplicate robot" not in status["drops"]
        finally:
            stop_processes(agents)
        for host in hosts:
            ctl = ctl_status(host, hub.endpoints["control"])
            assert ctl.returncode == 0 and "robot  connected" in ctl.stdout, (host, ctl.stderr)


@pytest.mark.ipv6_loopback
def test_ctl_at_the_other_family_than_the_hub_says_why_nothing_answers(make_scenario):
    """A hub on 127.0.0.1 cannot be reached at ::1: the timeout's message says so, and what tries both."""
    with start_ipv6_lab("127.0.0.1", 1, make_scenario) as hub:
        ctl = ctl_status("::1", hub.endpoints["control"], "--timeout", "0.5")
    assert ctl.returncode == 1
    assert "nothing accepts a connection there (refused or unreachable)" in ctl.stderr, ctl.stderr
    assert ctl.stderr.rstrip().endswith("? A hub listening on IPv4 only (network.bind * or an IPv4 "
                                        "address such as 127.0.0.1) is never reached at an IPv6 address (--hub "
                                        "localhost tries 127.0.0.1 and ::1).")


def in_hosts_namespace(hosts_file, *command: str) -> list:
    """``command`` to run in a mount namespace of its own whose /etc/hosts is ``hosts_file``: a host name with
    exactly the records a test needs, without touching this machine's. Skips where namespaces are not allowed."""
    bind = f"mount --bind {hosts_file} /etc/hosts"
    probe = subprocess.run(["unshare", "-m", "sh", "-c", bind], capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(f"cannot bind a hosts file in a mount namespace here: {probe.stderr.strip()}")
    return ["unshare", "-m", "sh", "-c", f'{bind} && exec "$@"', "sh", *command]


@pytest.mark.ipv6_loopback
def test_a_hub_pc_name_with_an_ipv6_address_alone_is_reached(tmp_path, make_scenario):
    """ZeroMQ looks a name up for IPv4 only unless its IPV6 option is on: a hub PC known by an AAAA record alone
    was never reached (here glibc even maps the name's ::1 to 127.0.0.1 for IPv4, where no hub listens), and ctl
    timed out as if no hub ran. Both ctl and an agent now reach it."""
    hosts = tmp_path / "hosts"
    hosts.write_text("::1 hubpc.lab\n")
    khepri = [sys.executable, "-m", "khepri_cli.main"]
    with start_ipv6_lab("::1", 1, make_scenario) as hub:
        port = hub.endpoints["control"].rsplit(":", 1)[1]
        ctl = subprocess.run(in_hosts_namespace(hosts, *khepri, "ctl", "status", "--hub", "hubpc.lab", "--port", port,
                                                "--timeout", "3"), capture_output=True, text=True, timeout=60)
        assert ctl.returncode == 0 and "robot  connected" in ctl.stdout, ctl.stderr
        robot_port = hub.endpoints["robots"].rsplit(":", 1)[1]
        agent = subprocess.Popen(in_hosts_namespace(hosts, *khepri, "agent", "--id", "0", "--driver", "sim", "--hub",
                                                    "hubpc.lab", "--port", robot_port),
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            hub.wait_until(lambda status: status["robots"][0]["connected"])
        finally:
            agent.send_signal(signal.SIGINT)
            agent.wait(timeout=15)


@pytest.mark.parametrize("answer, lookups", [("ipv6", 1), ("ipv4", 1), ("no dns", 1)])
def test_the_agent_looks_its_hub_name_up_once_not_at_every_reset(monkeypatch, answer, lookups):
    """The IPv6-only check resolves the hub's name in the agent's loop: at every reset (2 s of silence) a DNS
    server that does not answer would have held the loop for its whole timeout. An unanswered lookup is tried
    again after IPV6_LOOKUP_RETRY_S, not before."""
    import socket as sockets

    from onboard.agent import link as link_module

    calls = []

    def resolve(host, *args, **kwargs):
        calls.append(host)
        if answer == "no dns":
            raise sockets.gaierror(sockets.EAI_AGAIN, "Temporary failure in name resolution")
        family, address = (sockets.AF_INET6, ("::1", 0, 0, 0)) if answer == "ipv6" else (sockets.AF_INET,
                                                                                           ("127.0.0.1", 0))
        return [(family, sockets.SOCK_STREAM, 6, "", address)]

    monkeypatch.setattr(link_module.socket, "getaddrinfo", resolve)
    link = link_module.HubLink(0, "tcp://hubpc.lab:5560", None, log=lambda line: None)
    try:
        for _ in range(5):
            link.reset()
        assert (calls.count("hubpc.lab"), link.socket.ipv6) == (lookups, answer == "ipv6")
        if answer == "no dns":
            monkeypatch.setattr(link_module.time, "monotonic", lambda: link._ipv6_lookup_after + 1.0)
            link.reset()
            assert calls.count("hubpc.lab") == 2
    finally:
        link.close()


def test_a_robot_without_the_agents_packages_is_told_which_in_one_line():
    """`python3 -m onboard.agent` on a robot without pyzmq ended in a ModuleNotFoundError traceback."""
    blocked = "import sys, runpy; sys.modules['zmq'] = None; sys.argv = ['agent', '--id', '0', '--driver', 'sim']; " \
              "runpy.run_module('onboard.agent', run_name='__main__')"
    done = subprocess.run([sys.executable, "-c", blocked], capture_output=True, text=True, timeout=60)
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert done.stderr.startswith("agent: error: import of zmq halted; None in sys.modules: the agent needs Python")


@pytest.mark.parametrize("field, value, problem", [
    ("spec", [1], "run.spec: must be a mapping"),
    ("spec", {"max_wheel_speed_m_s": 0}, "run.spec.max_wheel_speed_m_s: must be a number > 0"),
    ("control_hz", -10, "run.control_hz: must be a number > 0"),
    ("control_hz", 1e9, "run.control_hz: must be <= 100"),
    ("params", [1, 2], "run.params: must be a mapping"),
    ("run_id", ["r1"], "run.run_id: must be a string"),
    ("lockstep", "yes", "run.lockstep: must be true or false (got 'yes')"),
    ("lockstep", "false", "run.lockstep: must be true or false (got 'false')"),
    ("lockstep", 1, "run.lockstep: must be true or false (got 1)"),
    ("clock", "Hub", "run.clock: must be local or hub (got 'Hub')"),
    ("clock", True, "run.clock: must be local or hub (got True)"),
])
def test_a_start_with_malformed_run_settings_is_refused_not_crashed(scripted, field, value, problem):
    """The hub's `start` is input like any frame: a list for `spec` raised AttributeError out of the agent's loop,
    and a control_hz <= 0 or huge had the behaviour stepped as fast as the loop went, every step a miss. A
    lockstep of "yes", "false" or 1 was taken as true: the agent waited for frames to step, on a hub pacing by
    the wall clock."""
    said = []
    link = HubLink(0, scripted.endpoint)
    try:
        agent = Agent(0, link, lambda a: SimDriver(link.send, lambda: a.state.sim), log=said.append)
        agent.on_command({"type": "command", "cmd": "start", "run": {**RUN, field: value}})
    finally:
        link.close()
    assert agent.run is None and agent.behaviour is None
    assert agent.error.startswith(f"cannot start the run: {problem}"), agent.error
    assert agent.refused_run_id == ("r1" if field != "run_id" else None)


LISTENER = '''
from onboard.behaviour import Behaviour, register


@register("test-listener")
class Listener(Behaviour):
    def __init__(self, robot, params=None):
        super().__init__(robot, params)
        self.heard = []

    def step(self):
        self.heard += [m.payload["tag"] for m in self.robot.radio.receive()]

    def telemetry(self):
        return {"state": "listening", "heard": self.heard}
'''


def test_a_new_run_does_not_hear_what_was_relayed_after_the_last_one_ended(scripted, tmp_path):
    """The hub delivers its relay queue in the frames after `stop`; the agent kept those messages and the next
    run's behaviour took them as its own: in a lab, transport read the last run's closed cage and never caged."""
    module = tmp_path / "listener.py"
    module.write_text(LISTENER)
    process = spawn_agent(scripted.endpoint, 0, tmp_path / "agent.log", extra=["--import", str(module)])
    try:
        scripted.wait_for(lambda m: m["type"] == "hello")
        start_run(scripted, dict(RUN, run_id="r1", behaviour="test-listener"))
        feed(scripted, 0.3, messages=[[1, 0.0, {"tag": "run 1"}]])
        scripted.send({"type": "command", "cmd": "stop"})
        scripted.wait_for(lambda m: m["type"] == "ack" and m["cmd"] == "stop")
        feed(scripted, 0.2, mode="idle", messages=[[1, 0.0, {"tag": "after run 1"}]])
        start_run(scripted, dict(RUN, run_id="r2", behaviour="test-listener"))
        t0 = time.monotonic()
        feed(scripted, 0.4)
        telemetry = scripted.wait_for(lambda m: m["type"] == "telemetry" and m["_at"] > t0
                                      and m["run_id"] == "r2" and m["loop"]["steps"] >= 1)
        assert telemetry["behaviour"]["heard"] == []
    finally:
        stop_processes([process])


def test_loop_figures_count_the_current_run_only(scripted, tmp_path):
    """`ctl status` showed a second run's loop steps and deadline misses added to the first run's: an operator
    could not tell whether this run missed any."""
    process = spawn_agent(scripted.endpoint, 0, tmp_path / "agent.log")
    try:
        scripted.wait_for(lambda m: m["type"] == "hello")
        start_run(scripted, dict(RUN, run_id="r1"))
        feed(scripted, 1.0)
        first = [m for m in scripted.received if m["type"] == "telemetry" and m["run_id"] == "r1"][-1]
        assert first["loop"]["steps"] >= 5, first["loop"]
        scripted.send({"type": "command", "cmd": "stop"})
        scripted.wait_for(lambda m: m["type"] == "ack" and m["cmd"] == "stop")
        start_run(scripted, dict(RUN, run_id="r2"))
        t0 = time.monotonic()
        feed(scripted, 0.3)
        second = scripted.wait_for(lambda m: m["type"] == "telemetry" and m["_at"] > t0 and m["run_id"] == "r2"
                                   and m["loop"]["steps"] >= 1)
        assert second["loop"]["steps"] < first["loop"]["steps"], (first["loop"], second["loop"])
    finally:
        stop_processes([process])


def test_an_agent_given_the_control_port_is_told_so_while_it_waits(make_scenario, first_waiting_line):
    """Its bad-message line said the control port had answered, and its waiting line, every 10 s, that it was
    connected to a hub that sends robot 0 nothing: is robot 0 in the hub's lab? Both now name the port."""
    with start_ipv6_lab("127.0.0.1", 2, make_scenario) as hub:
        control = hub.endpoints["control"]
        waiting = first_waiting_line(HubLink(0, control))
    assert f"what answers at {control} is not a hub's robots port" in waiting, waiting
    assert "the hub's control port answered; agents connect to its robots port" in waiting, waiting
    assert "sends robot 0 nothing" not in waiting


def test_a_keyed_agent_the_hub_ignores_is_asked_whether_its_key_is_its_own():
    """robots/robot-3.key_secret held robot 2's key: the hub said `robot 2 claimed to be robot 3`, the agent only
    whether robot 3 was in the lab or another agent had its id."""
    from onboard.agent.connection import ConnectionWatch

    watch = ConnectionWatch.__new__(ConnectionWatch)
    watch.read = lambda: None
    watch.connected, watch.refused, watch.handshake_ok, watch.dropped = True, False, True, False
    watch.handshake_failed, watch.protocol_error = None, None
    keyed = watch.likely_cause(3, "tcp://hub:5560", keyed=True)
    assert "and is robots/robot-3.key_secret robot 3's own key (not another robot's)?" in keyed, keyed
    assert watch.likely_cause(3, "tcp://hub:5560", keyed=False).endswith(
        "is robot 3 in the hub's lab, and is no other agent connected as robot 3? The hub's console says which")


def test_khepri_agent_does_not_print_a_logged_traceback_twice(monkeypatch, capsys):
    """`khepri agent` printed the crash's traceback in the agent's lines and again after `khepri: error:`."""
    import khepri_cli.lab_commands as lab
    from khepri_cli.main import main
    from onboard.behaviour import BehaviourError

    def crash(args):
        try:
            [][1]
        except IndexError as exc:
            err = BehaviourError(0, "step()", exc)
        err.traceback_logged = True
        raise err

    monkeypatch.setattr(lab, "cmd_agent", crash)
    assert main(["agent", "--id", "0", "--driver", "sim"]) == 1
    said = capsys.readouterr().err
    assert said.startswith("khepri: error: the behaviour failed: robot 0, step(): IndexError") and \
        said.count("\n") == 1, said


def test_an_agent_says_when_its_run_goes_on_after_a_hold():
    """Its log said `estop: operator e-stop`, then `hold: e-stop cleared`, and nothing when the run went on:
    it read as a robot that never moved again."""
    from onboard.agent.loop import Agent
    from onboard.drivers.sim import SimDriver

    lines = []
    link = HubLink(3, "tcp://127.0.0.1:9")
    try:
        agent = Agent(3, link, lambda a: SimDriver(link.send, lambda: a.state.sim), log=lines.append)
        agent.run = {"run_id": "r1"}
        agent.state.mode = "run"
        for mode, reason in (("estop", "operator e-stop"), ("hold", "e-stop cleared"), ("run", "")):
            agent.apply_mode(mode, reason)
    finally:
        link.close()
    assert lines[-3:] == ["agent 3: estop: operator e-stop", "agent 3: hold: e-stop cleared",
                          "agent 3: run r1 goes on (was hold)"], lines
