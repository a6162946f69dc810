"""What the hub says about its robots' connections: a robot that goes silent and comes back, an agent that
reconnects, a second agent that claims a robot already taken. Real agent processes on loopback."""
import signal
import time

import pytest
import zmq

from hub.config import parse_config
from hub.harness import HubThread, spawn_agent, stop_processes
from onboard.agent.link import HubLink
from onboard.protocol import DOWNLINK_TYPES, decode, encode

LAB = {"source": {"type": "sim"}, "network": {"bind": "127.0.0.1", "robot_port": 0, "control_port": 0},
       "security": {"insecure": True}}


def lines_with(hub: HubThread, fragment: str):
    return [line for line in list(hub.lines) if fragment in line]


def test_a_robot_that_goes_silent_and_comes_back_is_said_once_each_way(tmp_path):
    """The hub's console said nothing when a connected robot stopped talking (agent dead, Wi-Fi gone): only
    `ctl status` showed it. Now one line when it goes silent, one when it is back, none per frame between."""
    with HubThread(parse_config(LAB)) as hub:
        agent = spawn_agent(hub.endpoints["robots"], 0, tmp_path / "agent.log")
        try:
            hub.wait_until(lambda s: s["robots"][0]["connected"])
            agent.send_signal(signal.SIGSTOP)     # frozen: its connection stays open, nothing comes through it
            silent = hub.wait_for_lines("robot 0 went silent")
            agent.send_signal(signal.SIGCONT)     # before its own 2 s reconnect: back on the same connection
            back = hub.wait_for_lines("robot 0 is back after")
            agent.kill()                          # dies without a word
            agent.wait()
            hub.wait_for_lines("robot 0 went silent", count=2)
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
        assert hub.wait_for_lines("has exited")[-1] == "hub: robot 1's agent has exited (its last message said so)"


def dealer(endpoint: str) -> zmq.Socket:
    sock = zmq.Context.instance().socket(zmq.DEALER)
    sock.linger = 0
    sock.connect(endpoint)
    return sock


def say(sock: zmq.Socket, agent: str, times: int = 1) -> None:
    """An agent's hellos, from robot 0, with its process token."""
    for _ in range(times):
        sock.send(encode({"type": "hello", "id": 0, "driver": "sim", "agent": agent}))
        time.sleep(0.05)


def gets_frames(sock: zmq.Socket, within_s: float = 1.0) -> bool:
    deadline = time.monotonic() + within_s
    while sock.poll(max(0.0, deadline - time.monotonic()) * 1000.0):
        if decode(sock.recv(), "hub", accept=DOWNLINK_TYPES)["type"] == "frame":
            return True
    return False


def test_an_agents_own_reconnect_takes_the_robot_over_quietly_and_a_second_agent_is_still_refused():
    """An agent that reopens its socket while its old connection still looks alive to the hub (it stopped
    getting frames, but its own messages got through) had its new connection's messages dropped as `duplicate
    robot` until the old one had been silent for watchdog_s. Its token says it is the same agent: it takes the
    robot over at once, in one line; a second agent (another token) is still kept out and counted. (watchdog_s 2 s:
    at 0.3 s a loaded machine that stalls this thread that long hands the robot to the second agent.)"""
    with HubThread(parse_config(dict(LAB, watchdog_s=2.0))) as hub:
        old, new, other = (dealer(hub.endpoints["robots"]) for _ in range(3))
        try:
            say(old, "agent-a")
            hub.wait_until(lambda s: s["robots"][0]["connected"])
            say(old, "agent-a", times=2)           # alive: it spoke just now
            say(new, "agent-a")                    # the same agent on a new socket
            hub.wait_for_lines("reconnected")
            say(old, "agent-a")                    # a message still in flight on the replaced connection
            assert gets_frames(new)                # the new connection holds the robot
            assert "duplicate robot" not in hub.status()["drops"]
            for _ in range(10):                    # another agent with --id 0, while this one is alive
                say(other, "agent-b")
                say(new, "agent-a")
            assert hub.status()["drops"]["duplicate robot"] >= 10
            hub.wait_for_lines("claimed by two connections")
        finally:
            for sock in (old, new, other):
                sock.close(0)
    assert lines_with(hub, "robot 0")[:2] == ["hub: robot 0 connected from 127.0.0.1",
                                              "hub: robot 0's agent reconnected from 127.0.0.1"], hub.lines
    assert len(lines_with(hub, "connected from")) == 2, hub.lines       # no hand-over back to the old socket


def test_an_agent_names_itself_with_one_token_on_every_connection():
    link, another = HubLink(3, "tcp://127.0.0.1:9"), HubLink(3, "tcp://127.0.0.1:9")
    try:
        before = decode(link.encode({"type": "wheels", "left": 0.0, "right": 0.0}), "agent")
        link.reset()                               # what the agent does after 2 s without a frame
        after = decode(link.encode({"type": "hello", "driver": "sim"}), "agent")
    finally:
        link.close()
        another.close()
    assert before["agent"] == after["agent"] and len(after["agent"]) == 16
    assert another.instance != link.instance       # another agent with the same --id: another token


def test_the_mocap_rate_falls_to_zero_soon_after_the_frames_stop():
    """A 200 Hz replay that had ended showed `mocap: 203.5 Hz` for 2 s beside `replay: ended`."""
    from hub.links import RateMeter

    fast, slow = RateMeter(), RateMeter()
    for k in range(401):
        fast.tick(k / 200.0)
    for k in range(4):
        slow.tick(float(k))
    assert fast.current(2.0 + 0.1) == pytest.approx(200.0, rel=0.05) and fast.current(2.0 + 0.6) == 0.0
    assert slow.current(3.0 + 1.5) == pytest.approx(1.0, rel=0.05)     # 1 Hz: a 1.5 s gap is not silence yet
    assert slow.current(3.0 + 2.1) == 0.0


def next_command(sock: zmq.Socket, within_s: float = 1.0):
    """The next command the hub sends on ``sock`` within ``within_s``, or None."""
    deadline = time.monotonic() + within_s
    while sock.poll(max(0.0, deadline - time.monotonic()) * 1000.0):
        message = decode(sock.recv(), "hub", accept=DOWNLINK_TYPES)
        if message["type"] == "command":
            return message
    return None


def test_a_start_an_agent_left_unacknowledged_is_not_sent_to_the_next_one_once_the_run_ended():
    """An agent got `start`, went away without acknowledging it, and the run was stopped while it was away:
    the next agent for that robot was sent the ended run's `start`, again every 0.25 s."""
    with HubThread(parse_config(LAB)) as hub:
        first = dealer(hub.endpoints["robots"])
        say(first, "agent-a")
        hub.wait_until(lambda s: s["robots"][0]["connected"])
        hub.request("start")
        assert next_command(first)["cmd"] == "start"          # and never acknowledged
        first.close(0)
        deadline = time.monotonic() + 5.0                       # the hub finds the connection gone when it sends
        while hub.hub.robots[0].routing is not None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert hub.hub.robots[0].routing is None
        hub.request("stop")
        second = dealer(hub.endpoints["robots"])
        try:
            say(second, "agent-b")
            command = next_command(second, within_s=1.0)
            assert command is None or command["cmd"] != "start", command
        finally:
            second.close(0)


def test_stopping_a_run_drops_the_radio_messages_it_left_queued():
    """A robot that connected after a run had been stopped got that run's queued broadcasts at once, and nothing
    told it which run they came from (their sent_s start from 0 each run)."""
    from hub.factory import build_hub

    hub = build_hub(parse_config(LAB), log=lambda line: None)
    try:
        hub.control.execute("start")
        hub.relay.submit(1, 2.0, {"hello": 1}, 20, [0])
        assert hub.relay.pending(0)
        hub.control.execute("stop")
        assert not hub.relay.pending(0)
    finally:
        hub.close()


def test_an_agent_that_joins_a_run_is_said_to_start_it_afresh(tmp_path):
    """A restarted agent rejoined the running run with only `robot 0 connected from ...`, and the robot drove
    again with a behaviour that knew nothing of the run: the operator had no word of either."""
    with HubThread(parse_config(LAB)) as hub:
        first = spawn_agent(hub.endpoints["robots"], 1, tmp_path / "first.log")
        late = None
        try:
            hub.wait_until(lambda s: s["robots"][1]["connected"])
            hub.request("start")
            run_id = hub.status()["run_id"]
            late = spawn_agent(hub.endpoints["robots"], 0, tmp_path / "late.log")
            (joined,) = hub.wait_for_lines("robot 0 connected from")
        finally:
            stop_processes([p for p in (first, late) if p is not None])
    assert joined == (f"hub: robot 0 connected from 127.0.0.1: it joins run {run_id} with a new behaviour (it knows "
                      "nothing of the run so far)"), joined
    assert lines_with(hub, "robot 1 connected from") == ["hub: robot 1 connected from 127.0.0.1"]


def test_an_estop_the_agent_does_not_acknowledge_is_sent_again_until_it_is():
    """A send never blocks, so a command can be lost (a full queue, a reconnecting agent): the hub sends it again
    every COMMAND_RETRY_S until the agent acknowledges it. On loopback nothing is lost, so no test needed the
    retry, and a hub that sent each command once passed them all."""
    with HubThread(parse_config(LAB)) as hub:
        sock = dealer(hub.endpoints["robots"])
        try:
            say(sock, "agent-a")
            hub.wait_until(lambda s: s["robots"][0]["connected"])
            hub.request("estop")
            assert next_command(sock)["cmd"] == "estop"
            again = next_command(sock)                       # not acknowledged: sent again
            assert again is not None and again["cmd"] == "estop", again
            sock.send(encode({"type": "ack", "id": 0, "cmd": "estop", "seq": 0, "agent": "agent-a"}))
            next_command(sock, within_s=0.3)                 # one may have crossed the acknowledgement
            assert next_command(sock, within_s=1.0) is None   # acknowledged: no more
        finally:
            sock.close(0)
