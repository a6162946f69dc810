"""What the hub says about odd peers and odd lab files: who sent it, why it was refused, nothing left unsaid."""
import json
import time

import pytest
import zmq

from hub.config import load_config, parse_config
from hub.harness import HubThread
from hub.links import DropLog
from onboard.config import ConfigError
from onboard.protocol import PROTOCOL_VERSION, decode, encode

NETWORK = {"bind": "127.0.0.1", "robot_port": 0, "control_port": 0}
SIM = {"source": {"type": "sim"}, "network": NETWORK, "security": {"insecure": True}}


def mocap_config(bodies, robots=None):
    data = {"source": {"type": "motioncapture", "system": "mock", "bodies": bodies,
                       "options": {"rigid_bodies": ";".join(f"{name}(0,0,0,1,0,0,0)" for name in bodies)}},
            "network": NETWORK, "security": {"insecure": True}, "run": {"behaviour": "aggregate"}}
    if robots is not None:
        data["robots"] = robots
    return data


def dealer(endpoint: str) -> zmq.Socket:
    sock = zmq.Context.instance().socket(zmq.DEALER)
    sock.linger = 0
    sock.connect(endpoint)
    return sock


def test_a_request_the_hub_cannot_take_is_answered_with_why():
    """A lab's own client asking for a command the hub does not know waited for its timeout, told nothing."""
    with HubThread(parse_config(SIM)) as hub:
        sock = dealer(hub.endpoints["control"])
        try:
            sock.send(json.dumps({"v": PROTOCOL_VERSION, "type": "request", "cmd": "pause", "nonce": 5}).encode())
            assert sock.poll(3000), "no reply to a request with an unknown command"
            reply = decode(sock.recv(), "hub", accept=("reply",))
            sock.send(b"\xff not json")
            assert sock.poll(3000), "no reply to a request that is not JSON"
            garbage = decode(sock.recv(), "hub", accept=("reply",))
        finally:
            sock.close(0)
        assert reply["ok"] is False and reply["nonce"] == 5
        assert reply["error"].startswith("refused: request.cmd: must be one of") and "'pause'" in reply["error"]
        assert garbage["ok"] is False and "nonce" not in garbage and "not a JSON message" in garbage["error"]
        assert hub.request("status")["ok"]          # and the hub serves on


def test_a_message_in_too_many_frames_names_its_sender():
    with HubThread(parse_config(SIM)) as hub:
        sock = dealer(hub.endpoints["robots"])
        try:
            sock.send_multipart([encode({"type": "hello", "id": 0, "driver": "test"}), b"extra"])
            line = hub.wait_for_lines("dropped malformed message", timeout_s=5.0)[0]
        finally:
            sock.close(0)
    assert line.startswith("hub: dropped malformed message: 2 frames from peer at 127.0.0.1, expected 1"), line


def test_a_message_nested_past_pythons_recursion_limit_is_counted_and_dropped_naming_its_sender():
    """json.loads raises RecursionError, not ValueError, for it: uncaught, it would end the hub's loop."""
    nested = b"[" * 30_000 + b"]" * 30_000          # within the hub's 64 kB message size limit
    with HubThread(parse_config(SIM)) as hub:
        robot, operator = dealer(hub.endpoints["robots"]), dealer(hub.endpoints["control"])
        try:
            robot.send(b'{"v": 2, "type": "hello", "id": 0, "driver": "test", "x": ' + nested + b"}")
            line = hub.wait_for_lines("dropped bad message", timeout_s=5.0)[0]
            operator.send(b'{"v": 2, "type": "request", "cmd": "status", "nonce": 4, "x": ' + nested + b"}")
            assert operator.poll(3000), "no reply to a request nested past the recursion limit"
            reply = decode(operator.recv(), "hub", accept=("reply",))
        finally:
            robot.close(0)
            operator.close(0)
        assert hub.status()["drops"] == {"bad message": 1, "bad control message": 1}     # and it serves on
    assert line.startswith("hub: dropped bad message: from peer at 127.0.0.1: not a JSON message or a binary frame")
    assert reply["ok"] is False and "not a JSON message" in reply["error"] and "nonce" not in reply


def test_drops_a_burst_hid_are_said_when_its_second_is_over():
    """'+N more' was said only with the sender's next drop, which may never come."""
    lines = []
    drops = DropLog(lines.append)
    for _ in range(4):
        drops.drop("bad message", "robot:3 at 10.0.0.3", "from robot:3 at 10.0.0.3: v: unsupported")
    start = time.monotonic()
    drops.flush(start)                              # the burst's second is not over: nothing yet
    assert len(lines) == 1
    drops.flush(start + 1.5)
    assert lines[1] == ("hub: dropped 3 more messages from robot:3 at 10.0.0.3 in the last second "
                        "(bad message 3; `khepri ctl status` counts drops by reason)")
    drops.flush(start + 3.0)                        # said once
    assert len(lines) == 2 and drops.counts == {"bad message": 4}


def test_a_new_mistake_from_a_sender_whose_repeats_are_muted_is_still_said():
    """The same bad message again and again makes its sender wait longer for a line (up to a minute); on
    loopback every agent is that one sender, so another agent's new mistake went unsaid, and the line after
    the quiet time gave no reason."""
    lines = []
    drops = DropLog(lines.append)
    sender, start = "peer at 127.0.0.1", time.monotonic()
    drops.drop("unknown robot", sender, "from peer at 127.0.0.1: robot 42 is not in this lab")
    # As after a few repeats: its last line 1.5 s ago, its quiet time grown to 8 s.
    drops._last_line[sender], drops._quiet_s[sender] = start - 1.5, 8.0
    drops.drop("unknown robot", sender, "from peer at 127.0.0.1: robot 42 is not in this lab")    # hidden
    assert len(lines) == 1
    drops.drop("bad message", sender, "from peer at 127.0.0.1: hello.driver: is required")
    assert lines[-1].startswith("hub: dropped bad message: from peer at 127.0.0.1: hello.driver: is required")
    drops.drop("bad message", sender, "from peer at 127.0.0.1: wheels.right: is required")   # within its second
    drops.flush(time.monotonic() + 1.5)
    assert lines[-1].endswith("(bad message 1; `khepri ctl status` counts drops by reason)"), lines
    assert drops.counts == {"unknown robot": 2, "bad message": 2}


def test_a_robot_without_a_rigid_body_is_refused():
    with pytest.raises(ConfigError) as info:
        parse_config(mocap_config({"kh0": 0, "kh1": 1}, robots=[0, 1, 2]))
    assert str(info.value) == ("robots[2]: robot 2 has no rigid body in source.bodies (add e.g. kh2: 2 there, "
                               "or take it off this list)")
    assert parse_config(mocap_config({"kh0": 0, "kh1": 1}, robots=[1])).robots == [1]


def test_bodies_of_robots_left_out_of_the_run_are_said():
    """Four of six robots out today is fine; a body the hub silently ignores may be a typo."""
    with HubThread(parse_config(mocap_config({"kh0": 0, "kh1": 1, "kh5": 5}, robots=[0]))) as hub:
        line = hub.wait_for_lines("source.bodies", timeout_s=5.0)[0]
    assert line == "hub: source.bodies kh1 (robot 1), kh5 (robot 5): not in robots, so not served (their poses " \
                   "are ignored)"


@pytest.mark.parametrize("content", ["", "# only a comment\n"])
def test_an_empty_lab_file_is_refused_not_taken_as_defaults(tmp_path, content):
    path = tmp_path / "lab.yaml"
    path.write_text(content)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert info.value.field == "--config" and info.value.problem.startswith(f"{path} is empty")
    path.write_text(json.dumps(SIM))
    assert load_config(path).source.type == "sim"


def test_a_mock_without_rigid_bodies_is_refused_rather_than_placing_no_robot():
    for options in (None, {}, {"frequency": "50"}):
        config = mocap_config({"kh0": 0})
        config["source"]["options"] = options
        with pytest.raises(ConfigError) as info:
            parse_config(config)
        assert info.value.field == "source.options.rigid_bodies" and "is required for the mock" in info.value.problem


@pytest.mark.parametrize("rigid_bodies, problem", [
    ("kh0(0,0,0)", "entry 1 ('kh0(0,0,0)') must be name(x,y,z,qw,qx,qy,qz)"),
    ("kh0(0,0,0,1,0,0,0),kh1(1,0,0,1,0,0,0)", "entry 1 ("),
    ("kh0(0,0,0,1,0,0,0);kh1(a,0,0,1,0,0,0)", "entry 2 ('kh1(a,0,0,1,0,0,0)')"),
    (" ; ", "has no body"),
    ("kh0(0,0,0.05,0,0,0,0)", "entry 1 ('kh0(0,0,0.05,0,0,0,0)'): its quaternion qw,qx,qy,qz is not a rotation"),
    ("kh0(0,0,0,1,0,0,0);kh0(1,0,0,1,0,0,0)", "entry 2 ('kh0(1,0,0,1,0,0,0)'): the body 'kh0' is given twice"),
])
def test_a_mock_body_the_mock_would_skip_is_refused(rigid_bodies, problem):
    """The mock skips an entry it cannot parse, and the robot was never placed, with no word of why."""
    config = mocap_config({"kh0": 0})
    config["source"]["options"]["rigid_bodies"] = rigid_bodies
    with pytest.raises(ConfigError) as info:
        parse_config(config)
    assert info.value.field == "source.options.rigid_bodies" and problem in info.value.problem


def test_a_body_the_mock_does_not_have_is_named_and_spaces_after_a_semicolon_do_not_count():
    config = mocap_config({"kh0": 0, "kh1": 1})
    config["source"]["options"]["rigid_bodies"] = "kh0(0,0,0,1,0,0,0)"
    with pytest.raises(ConfigError) as info:
        parse_config(config)
    assert str(info.value) == "source.bodies.kh1: the mock has no body 'kh1' (its rigid_bodies: 'kh0')"
    config["source"]["options"]["rigid_bodies"] = "kh0(0,0,0,1,0,0,0); kh1(0.5,0,0,1,0,0,0)"
    with HubThread(parse_config(config)) as hub:       # the mock names the second body " kh1" if given as is
        hub.request("start")
        hub.wait_until(lambda s: [(r["id"], r["mode"]) for r in s["robots"]] == [(0, "run"), (1, "run")],
                       timeout_s=5.0)


def test_a_sender_repeating_one_bad_message_is_said_less_and_less_often(monkeypatch):
    """An agent started with an id not in the lab says hello every second: the hub said so every second."""
    clock = [1000.0]
    monkeypatch.setattr("hub.links.time.monotonic", lambda: clock[0])
    lines = []
    drops = DropLog(lines.append)
    said_at = []
    for second in range(130):
        clock[0] = 1000.0 + second
        before = len(lines)
        drops.drop("unknown robot", "peer at 10.0.0.9", "peer at 10.0.0.9 claimed robot 9, which is not in this lab")
        drops.flush(clock[0])
        said_at += [second] * (len(lines) - before)
    assert said_at == [0, 1, 3, 7, 15, 31, 63, 123], said_at
    assert lines[-1].endswith("(+59 more from this sender in the last 60 s)")
    assert drops.counts == {"unknown robot": 130}
    # A different mistake is said at once, not after the repeated one's quiet time (up to a minute): on
    # loopback every agent is this one sender, and another agent's new mistake went unsaid.
    drops.drop("bad message", "peer at 10.0.0.9", "something else")
    assert lines[-1] == "hub: dropped bad message: something else (+6 more from this sender in the last 6 s)"
    drops.drop("bad message", "peer at 10.0.0.9", "something new")       # but not twice in one second
    assert lines[-1].endswith("something else (+6 more from this sender in the last 6 s)")
    clock[0] += 1
    drops.drop("bad message", "peer at 10.0.0.9", "something else again")   # a new detail: a second again
    assert lines[-1] == "hub: dropped bad message: something else again (+1 more from this sender in the last second)"


def test_problems_said_in_turn_are_repeats_too(monkeypatch):
    """Four stray agents on one PC (one sender: their address) claim robots 1, 3, 5 and 6 in turn, and an agent
    pointed at the control port sends hello and telemetry in turn: with only the last problem remembered, each
    was new, and the console got a line every second for as long as the hub ran. A refused broadcast's size
    changes from message to message: the same problem, said with the robot and the limit."""
    clock = [1000.0]
    monkeypatch.setattr("hub.links.time.monotonic", lambda: clock[0])
    lines = []
    drops = DropLog(lines.append)
    for second in range(64):
        clock[0] = 1000.0 + second
        for robot in (1, 3, 5, 6):
            drops.drop("unknown robot", "peer at 127.0.0.1", f"peer at 127.0.0.1 claimed robot {robot}, which is "
                       "not in this lab")
        drops.flush(clock[0])
    assert len(lines) <= 12, lines          # each one's first line, then 1, 2, 4, ... s apart: not 64
    lines.clear()
    for second in range(64):
        clock[0] = 2000.0 + second
        drops.drop("refused broadcast", "robot 2", f"robot 2's broadcast of {1000 + second} bytes, over "
                   "relay.max_bytes (500)", key="over relay.max_bytes")
        drops.flush(clock[0])
    assert len(lines) <= 8 and lines[0] == "hub: dropped refused broadcast: robot 2's broadcast of 1000 bytes, over " \
        "relay.max_bytes (500)", lines
