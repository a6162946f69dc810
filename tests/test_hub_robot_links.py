"""What the hub says about its robots' connections: a robot that goes silent and comes back, an agent that
reconnects, a second agent that claims a robot already taken. Real agent processes on loopback."""
import signal
import time

from hub.config import parse_config
from hub.harness import HubThread, spawn_agent, stop_processes

LAB = {"source": {"type": "sim"}, "network": {"bind": "127.0.0.1", "robot_port": 0, "control_port": 0},
       "security": {"insecure": True}}


def lines_with(hub: HubThread, fragment: str):
    return [line for line in list(hub.lines) if fragment in line]


def wait_for_lines(hub: HubThread, fragment: str, count: int = 1, timeout_s: float = 10.0):
    deadline = time.monotonic() + timeout_s
    while len(lines_with(hub, fragment)) < count:
        assert time.monotonic() < deadline, f"no {count} lines with {fragment!r}: {hub.lines}"
        time.sleep(0.05)
    return lines_with(hub, fragment)


def test_a_robot_that_goes_silent_and_comes_back_is_said_once_each_way(tmp_path):
    """The hub's console said nothing when a connected robot stopped talking (agent dead, Wi-Fi gone): only
    `ctl status` showed it. Now one line when it goes silent, one when it is back, none per frame between."""
    with HubThread(parse_config(LAB)) as hub:
        agent = spawn_agent(hub.endpoints["robots"], 0, tmp_path / "agent.log")
        try:
            hub.wait_until(lambda s: s["robots"][0]["connected"])
            agent.send_signal(signal.SIGSTOP)     # frozen: its connection stays open, nothing comes through it
            silent = wait_for_lines(hub, "robot 0 went silent")
            time.sleep(0.4)
            agent.send_signal(signal.SIGCONT)     # before its own 2 s reconnect: back on the same connection
            back = wait_for_lines(hub, "robot 0 is back after")
            agent.kill()                          # dies without a word
            agent.wait()
            wait_for_lines(hub, "robot 0 went silent", count=2)
            time.sleep(1.5)                       # and stays dead: nothing more is said
        finally:
            stop_processes([agent])
    assert silent[0] == "hub: robot 0 went silent: no message from its agent at 127.0.0.1 for 1 s (did the agent " \
                        "stop, or its network drop?)"
    assert len(back) == 1 and back[0].endswith(" s of silence"), back
    assert len(lines_with(hub, "robot 0 went silent")) == 2 and len(lines_with(hub, "is back")) == 1, hub.lines


def test_an_agent_that_exits_is_said_to_have_exited(tmp_path):
    with HubThread(parse_config(LAB)) as hub:
        agent = spawn_agent(hub.endpoints["robots"], 1, tmp_path / "agent.log")
        try:
            hub.wait_until(lambda s: s["robots"][1]["connected"])
        finally:
            assert stop_processes([agent]) == [0]       # SIGTERM: it says goodbye on its way out
        assert wait_for_lines(hub, "has exited")[-1] == "hub: robot 1's agent has exited (its last message said so)"
