"""Lockstep steps (``hub/lockstep.py``) against light agents: one frame per connected robot and step, all of
the same simulated instant, and a step ends as soon as every expected agent answered its frame."""
import threading
import time

import pytest
import zmq

from hub.config import parse_config
from hub.factory import build_hub
from hub.lockstep import Lockstep
from onboard.protocol import DOWNLINK_TYPES, decode, encode

CONNECTED = [0, 2, 5]            # of lab-6's robots 0..5; the others never say hello


class LightAgents(threading.Thread):
    """DEALERs for some robots, in a thread of their own: hello, then answer every frame with telemetry for its
    seq (``answer``) or keep quiet; every frame received is kept, decoded."""

    def __init__(self, endpoint, ids, answer=True):
        super().__init__(daemon=True)
        self.endpoint, self.ids, self.answer = endpoint, ids, answer
        self.frames = {rid: [] for rid in ids}
        self.ready = threading.Event()
        self.stop = threading.Event()

    def run(self):
        context = zmq.Context.instance()
        sockets = {}
        for rid in self.ids:
            sock = context.socket(zmq.DEALER)
            sock.linger = 0
            sock.connect(self.endpoint)
            sock.send(encode({"type": "hello", "id": rid, "driver": "test"}))
            sockets[rid] = sock
        self.ready.set()
        poller = zmq.Poller()
        for sock in sockets.values():
            poller.register(sock, zmq.POLLIN)
        by_socket = {sock: rid for rid, sock in sockets.items()}
        try:
            while not self.stop.is_set():
                for sock, _ in poller.poll(20):
                    rid = by_socket[sock]
                    message = decode(sock.recv(), "hub", accept=DOWNLINK_TYPES)
                    if message["type"] != "frame":
                        continue
                    self.frames[rid].append(message)
                    if self.answer:
                        sock.send(encode({"type": "telemetry", "id": rid, "step": message["seq"], "mode": "idle"}))
        finally:
            for sock in sockets.values():
                sock.close(0)


@pytest.fixture
def hub():
    config = parse_config({"source": {"type": "sim", "scenario": "lab-6", "lockstep": True},
                           "network": {"bind": "127.0.0.1", "robot_port": 0, "control_port": 0},
                           "security": {"insecure": True}})
    hub = build_hub(config, log=lambda line: None)
    hub.bind()
    yield hub
    hub.close()


def connect(hub, lockstep, agents):
    agents.start()
    assert agents.ready.wait(10.0)
    problem = lockstep.wait_for(lambda: sum(r.routing is not None for r in hub.robots.values()) == len(agents.ids),
                                10.0, "hellos")
    assert problem is None


def test_each_step_sends_one_frame_of_one_instant_to_every_connected_robot(hub):
    steps = 3
    lockstep = Lockstep(hub, timeout_s=5.0)
    agents = LightAgents(hub.endpoints["robots"], CONNECTED)
    connect(hub, lockstep, agents)
    try:
        reports, took = [], []
        for _ in range(steps):
            began = time.monotonic()
            reports.append(lockstep.step())
            took.append(time.monotonic() - began)
            lockstep.advance()
        deadline = time.monotonic() + 5.0
        while any(len(frames) < steps for frames in agents.frames.values()) and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        agents.stop.set()
        agents.join(5.0)
    for report, step_s in zip(reports, took):
        assert sorted(report.answered) == CONNECTED and report.missing == []
        # Each a real round trip, frame out to answer in, inside the step that waited for it.
        assert len(report.round_trip_s) == len(CONNECTED) and all(0.0 < t <= step_s for t in report.round_trip_s)
    assert lockstep.timeouts == 0
    # Answered by all: the step ends then, not at its 5 s timeout (a loop that waited it out passed the rest).
    assert max(took) < 2.5, took
    for rid in CONNECTED:
        frames = agents.frames[rid]
        assert [f["seq"] for f in frames] == list(range(1, steps + 1))       # one frame per step, no more
        assert frames[0]["pose"] is not None
    for k in range(steps):           # every robot's frame of a step holds the same simulated instant
        clocks = {agents.frames[rid][k]["clock_s"] for rid in CONNECTED}
        assert len(clocks) == 1
    times = [report.time_s for report in reports]
    assert all(a < b for a, b in zip(times, times[1:]))                  # physics advanced between steps
    for rid in set(range(6)) - set(CONNECTED):
        assert hub.robots[rid].seq == 0                                    # never connected: nothing sent


def test_a_silent_agent_is_reported_missing_and_then_no_longer_waited_for(hub):
    lockstep = Lockstep(hub, timeout_s=0.2)
    agents = LightAgents(hub.endpoints["robots"], [1], answer=False)
    connect(hub, lockstep, agents)
    try:
        reports = [lockstep.step() for _ in range(4)]
    finally:
        agents.stop.set()
        agents.join(5.0)
    assert [r.missing for r in reports] == [[1], [1], [1], []]
    assert lockstep.timeouts == 3 and hub.robots[1].seq == 4               # still sent every step


def test_an_agent_that_reopens_its_connection_gets_the_step_it_missed(hub):
    """An agent reopens its socket after a long silence. The hub's frame of the next step went to the old
    connection and was lost; the step went on without that robot's answer (its wheel command for the step
    missing), or timed out. The frame now goes again on the new connection, and the step is answered."""
    lockstep = Lockstep(hub, timeout_s=5.0)
    endpoint = hub.endpoints["robots"]
    context = zmq.Context.instance()
    hello = {"type": "hello", "id": 1, "driver": "test", "agent": "one-process"}
    old = context.socket(zmq.DEALER)
    old.linger = 0
    old.connect(endpoint)
    old.send(encode(hello))
    assert lockstep.wait_for(lambda: hub.robots[1].routing is not None, 10.0, "hello") is None
    reopened, received = threading.Event(), []

    def agent():
        frame = decode(old.recv(), "hub", accept=DOWNLINK_TYPES)         # step 1, answered on the old socket
        old.send(encode({"type": "telemetry", "id": 1, "step": frame["seq"], "mode": "idle", "agent": "one-process"}))
        time.sleep(0.3)
        old.close(0)
        reopened.set()
        time.sleep(0.3)              # the hub sends step 2's frame meanwhile, to the connection just closed
        new = context.socket(zmq.DEALER)
        new.linger = 0
        new.connect(endpoint)
        new.send(encode(hello))
        while new.poll(5000):
            message = decode(new.recv(), "hub", accept=DOWNLINK_TYPES)
            if message["type"] == "frame":
                received.append(message["seq"])
                new.send(encode({"type": "telemetry", "id": 1, "step": message["seq"], "mode": "idle",
                                 "agent": "one-process"}))
                break
        new.close(0)

    thread = threading.Thread(target=agent, daemon=True)
    thread.start()
    first = lockstep.step()
    lockstep.advance()
    assert reopened.wait(5.0)
    second = lockstep.step()
    thread.join(10.0)
    assert first.answered == [1] and second.answered == [1] and second.missing == []
    assert lockstep.timeouts == 0
    assert received == [3]             # step 2's first frame (seq 2) was lost with the old connection
