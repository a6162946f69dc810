"""The agent keeps the wheels safe where its own loop cannot: a behaviour's step() that never returns, and wheel
commands from a thread of the behaviour's own during an e-stop. A real agent process with the kh4 driver
(against the compiled stand-in libkhepera, whose call log shows every speed command) and a scripted hub."""
import os
import re
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from hub.harness import ScriptedHub, stop_processes
from onboard.agent.safety import StepWatchdog

sys.path.insert(0, str(Path(__file__).parent))
from test_kh4_driver import compile_stub, speed_commands  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

STUCK = '''
import time
from onboard.behaviour import Behaviour, register

@register("stuck_after_three")
class StuckAfterThree(Behaviour):
    """Drives for three steps, then waits in step() for a message that never comes."""
    def step(self):
        self.steps = getattr(self, "steps", 0) + 1
        self.robot.wheels.set_speeds(0.1, 0.1)
        while self.steps > 3:
            time.sleep(0.01)
'''

DRIVES_FROM_A_THREAD = '''
import threading, time
from onboard.behaviour import Behaviour, register

@register("drives_from_a_thread")
class DrivesFromAThread(Behaviour):
    """Ramps the wheels from a thread of its own, whatever the agent's mode."""
    def __init__(self, robot, params):
        super().__init__(robot, params)
        threading.Thread(target=self.drive, daemon=True).start()
    def drive(self):
        while True:
            self.robot.wheels.set_speeds(0.1, 0.1)
            time.sleep(0.01)
    def step(self):
        pass
'''


@pytest.fixture(scope="module")
def stub_library(tmp_path_factory) -> Path:
    return compile_stub(tmp_path_factory.mktemp("stub"))


@pytest.fixture
def hub():
    scripted = ScriptedHub()
    yield scripted
    scripted.close()


def start_agent(tmp_path: Path, stub_library: Path, hub: ScriptedHub, module: str, name: str):
    (tmp_path / f"{name}.py").write_text(textwrap.dedent(module))
    log = tmp_path / "calls.log"
    env = dict(os.environ, PYTHONPATH=str(ROOT), KH4_STUB_LOG=str(log))
    agent = subprocess.Popen([sys.executable, "-m", "onboard.agent", "--id", "0", "--driver", "kh4", "--library",
                              str(stub_library), "--hub", hub.endpoint, "--import", name],
                             cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=open(tmp_path / "agent.log", "w"))
    hub.wait_for(lambda m: m["type"] == "hello")
    hub.send({"type": "command", "cmd": "start", "run": {"run_id": "r1", "behaviour": name, "params": {},
                                                          "control_hz": 10.0, "clock": "local"}})
    hub.wait_for(lambda m: m["type"] == "ack" and m["cmd"] == "start")
    return agent, log


def feed(hub: ScriptedHub, seconds: float, mode: str = "run") -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        hub.frame(mode=mode)
        hub.pump(0.05)


def test_a_step_that_never_returns_has_the_wheels_stopped_and_sigterm_still_ends_the_agent(
        tmp_path, stub_library, hub):
    agent, log = start_agent(tmp_path, stub_library, hub, STUCK, "stuck_after_three")
    try:
        feed(hub, 1.5)                       # three steps drive, the fourth never returns
        commands = speed_commands(log)
        assert (147, 147) in commands, commands                 # 0.1 m/s in hardware units: it drove
        assert commands[-1] == (0, 0), f"the wheels were left turning: {commands[-4:]}"
        agent.send_signal(signal.SIGTERM)
        assert agent.wait(timeout=5) == 1    # about a second after SIGTERM, without the step
    finally:
        stop_processes([agent])
    said = (tmp_path / "agent.log").read_text()
    assert "step() has run for" in said and "exiting without it" in said
    # Where it waits, for the behaviour's author: its own line that called time.sleep(), not the library's.
    assert re.search(r"step\(\) has run for .*; it is at stuck_after_three\.py:1[12], in step\(\)", said), said


def test_wheel_commands_from_a_behaviours_own_thread_do_not_pass_an_estop(tmp_path, stub_library, hub):
    agent, log = start_agent(tmp_path, stub_library, hub, DRIVES_FROM_A_THREAD, "drives_from_a_thread")
    try:
        feed(hub, 0.5)
        assert (147, 147) in speed_commands(log)                  # driving while the mode is run
        hub.send({"type": "command", "cmd": "estop", "reason": "test"})
        hub.wait_for(lambda m: m["type"] == "ack" and m["cmd"] == "estop")
        at_ack = len(speed_commands(log))
        feed(hub, 0.8, mode="estop")
        after = speed_commands(log)[at_ack:]
        assert all(command == (0, 0) for command in after), f"moved during the e-stop: {after[:5]}"
    finally:
        stop_processes([agent])


class PausingDriver:
    """A driver whose ``call_started`` (which the step watchdog reads between taking a step's start time and
    judging it) can hold the watchdog there once, to force the interleaving of a step that ends meanwhile."""
    stoppable_from_any_thread = True
    call_name = ""

    def __init__(self):
        self.stops = 0
        self.armed = False
        self.holding = threading.Event()
        self.released = threading.Event()

    @property
    def call_started(self):
        if self.armed:
            self.armed = False
            self.holding.set()
            self.released.wait()
        return None

    def close_gate_within(self, wait_s):
        self.stops += 1
        return True


def test_a_step_that_ends_as_the_watchdog_judges_it_does_not_spare_the_next_step():
    """The watchdog took a slow step's start time, the step returned, and the watchdog then tripped on it again:
    the wheels stopped once more, and its `tripped` flag, which only end() cleared, stayed set, so the next step
    could hang with the wheels on."""
    driver, said = PausingDriver(), []
    watchdog = StepWatchdog(driver, 0.25, lambda: False, said.append, 0)
    watchdog.start()
    try:
        watchdog.begin()                       # a slow step: 0.3 s, over the 0.25 s limit, so the wheels stop...
        time.sleep(0.3)
        assert driver.stops == 1, said
        driver.armed = True
        assert driver.holding.wait(2.0)        # ...and it returns while the watchdog holds its start time
        watchdog.end()
        driver.released.set()
        time.sleep(0.1)
        assert driver.stops == 1 and not watchdog.tripped, said
        watchdog.begin()                       # this one hangs: stopped after 0.25 s
        time.sleep(0.6)
        assert driver.stops == 2, said
    finally:
        watchdog.end()
        watchdog.stop()


@pytest.mark.parametrize("reading, sent", [(7.4, 7.4), (None, None), (float("nan"), None), ("7.4", None),
                                           (1e300, None), (-1.0, None), (True, None)])
def test_a_battery_reading_the_hub_would_drop_is_sent_as_no_reading(reading, sent):
    """The hub drops a telemetry whose battery_v is not a voltage (docs/protocol.md): one odd read of the driver
    would have had the robot's whole report dropped; it is no reading instead, `-` in `ctl status`."""
    from types import SimpleNamespace

    from onboard.agent.safety import GuardedDriver

    assert GuardedDriver(SimpleNamespace(name="reading", battery_v=lambda: reading)).battery_v() == sent
