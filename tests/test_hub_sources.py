"""Pose sources: the motioncapture library (its mock backend stands in for the cameras) and replay of a log."""
import json
import math
import os
import re
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zmq

from hub.config import parse_config
from hub.control import status_table
from hub.factory import build_hub
from hub.harness import HubThread
from hub.recording import Recorder, read_log
from hub.server import UPLINK_SLICE, poses_record
from hub.sources import MotionCaptureSource, PoseFrame, ReadFailures, pose_from_mocap
from onboard.config import ConfigError
from onboard.protocol import decode, encode

NETWORK = {"bind": "127.0.0.1", "robot_port": 0, "control_port": 0}


def mock_config(rigid_bodies, up_axis="z", **extra):
    return parse_config({"source": {"type": "motioncapture", "system": "mock", "up_axis": up_axis,
                                    "options": {"frequency": 100, "rigid_bodies": rigid_bodies},
                                    "bodies": {"kh0": 0, "kh1": 1}},
                         "network": NETWORK, "security": {"insecure": True}, "run": {"behaviour": "aggregate"},
                         **extra})


def first_frame_for(endpoint, robot_id, timeout_s=5.0):
    """Join as a light robot and return the first downlink frame that carries a pose."""
    sock = zmq.Context.instance().socket(zmq.DEALER)
    sock.linger = 0
    sock.connect(endpoint)
    sock.send(encode({"type": "hello", "id": robot_id, "driver": "test"}))
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline:
            if sock.poll(100):
                message = decode(sock.recv(), "hub")
                if message["type"] == "frame" and message.get("pose") is not None:
                    return message
        raise TimeoutError("no frame with a pose")
    finally:
        sock.close(0)


@pytest.mark.parametrize("up_axis, bodies", [
    # kh0 turned a quarter turn left (about +z)
    ("z", "kh0(1.0,2.0,0.05,0.70710678,0,0,0.70710678);kh1(1.5,2.0,0.05,1,0,0,0);stray(0,0,0,1,0,0,0)"),
    # Y-up: the floor is x-z and world y = -z; a quarter turn about +y is a quarter turn of yaw.
    ("y", "kh0(1.0,0.05,-2.0,0.70710678,0,0.70710678,0);kh1(1.5,0.05,-2.0,1,0,0,0);stray(0,0,0,1,0,0,0)"),
])
def test_motioncapture_bodies_become_robot_poses_and_neighbours(up_axis, bodies):
    with HubThread(mock_config(bodies, up_axis)) as hub:
        frame = first_frame_for(hub.endpoints["robots"], 0)
        assert frame["pose"] == pytest.approx([1.0, 2.0, math.pi / 2], abs=1e-4)
        (neighbour,) = frame["neighbours"]
        assert neighbour[0] == 1 and neighbour[1] == pytest.approx(0.5, abs=0.05)
        assert neighbour[2] == pytest.approx(-math.pi / 2, abs=0.1)       # kh1 is to the right of kh0's heading
        status = hub.wait_until(lambda s: s["mocap_hz"] > 0)
        # The mock's 100 Hz as measured on arrival: a loaded machine delivers fewer (39.9 Hz was seen with a
        # study on both cores), so only the order of magnitude is checked, not the machine's speed.
        assert 10 < status["mocap_hz"] < 130
        assert any("ignoring rigid body 'stray'" in line for line in hub.lines)


class FakeQuaternion:
    def __init__(self, w, x, y, z):
        self.w, self.x, self.y, self.z = w, x, y, z


class FakeBody:
    """What the motioncapture SDK hands out per rigid body: a float32 position and a quaternion object."""

    def __init__(self, position, quaternion_wxyz):
        self.position = np.asarray(position, dtype=np.float32)
        self.rotation = FakeQuaternion(*quaternion_wxyz)


class FakeMocap:
    rigidBodies: dict = {}

    def waitForNextFrame(self):
        time.sleep(0.01)


def fake_source(bodies, up_axis, lines):
    return MotionCaptureSource(zmq.Context.instance(), "fake", {}, bodies, up_axis, log=lines.append,
                               connect=lambda system, options: FakeMocap())


class Unreachable:
    """An SDK whose system has gone: every read raises."""
    rigidBodies: dict = {}

    def waitForNextFrame(self):
        raise RuntimeError("recv failed: Connection refused")


def test_a_library_that_keeps_failing_is_said_at_growing_intervals_not_ten_times_a_second():
    lines = []
    source = MotionCaptureSource(zmq.Context.instance(), "fake", {}, {"kh0": 0}, "z", log=lines.append,
                                 connect=lambda system, options: Unreachable())
    time.sleep(1.5)
    source.close()
    lines = [line for line in lines if "motion capture" in line]        # not "connecting to fake"
    assert lines[0] == "hub: motion capture read failed: recv failed: Connection refused (trying again every 0.1 s)"
    assert 2 <= len(lines) <= 3, lines        # the first, and a count after 1 s (one line per try: 15)
    assert re.fullmatch(r"hub: motion capture read failed 1\d times in 1 s, the last with: recv failed: "
                        r"Connection refused; no frames meanwhile, so the robots are held", lines[1]), lines
    # Over an hour off, on the clock the reader thread passes: 1, 3, 9, 27, 81 s, then a line a minute.
    said = []
    failures = ReadFailures(said.append)
    for k in range(36000):
        failures.failed(RuntimeError("gone"), 1000.0 + k * 0.1)
    failures.read(4600.0)
    assert len(said) == 65 and said[-1] == "hub: motion capture frames again, after 36000 failed reads " \
        "over 3600.0 s", said[-3:]


def test_an_option_the_sdk_cannot_parse_is_one_line_naming_source_options():
    def refuse(system, options):
        raise ValueError("stoi")                       # what the C++ bindings raise for a non-number
    with pytest.raises(ConfigError) as info:
        MotionCaptureSource(zmq.Context.instance(), "fake", {"port": "x"}, {"kh0": 0}, "z", log=lambda line: None,
                            connect=refuse)
    assert info.value.field == "source.options" and "'fake' refused an option" in info.value.problem


def test_an_option_a_real_system_does_not_read_is_warned_with_the_key_it_reads():
    """motioncapture's connect() ignores unknown keys: `host:` for a Vicon connected to localhost, unsaid."""
    lines: list = []
    source = MotionCaptureSource(zmq.Context.instance(), "vicon", {"host": "10.0.0.5"}, {"kh0": 0}, "z",
                                 log=lines.append, connect=lambda system, options: FakeMocap())
    source.close()
    assert lines[1] == ("hub: warning: source.options.host: motioncapture 1.x's vicon backend does not read it; "
                        "passed on all the same (it reads hostname, enable_objects, enable_pointclout); did you "
                        "mean hostname?")
    lines.clear()
    MotionCaptureSource(zmq.Context.instance(), "vicon", {"hostname": "10.0.0.5"}, {"kh0": 0}, "z",
                        log=lines.append, connect=lambda system, options: FakeMocap()).close()
    assert not [line for line in lines if "warning" in line]


def test_an_unknown_system_lists_the_ones_the_library_knows():
    """It said only "cannot connect to 'vicn': Unknown motion capture type!"."""
    def unknown(system, options):
        raise RuntimeError("Unknown motion capture type!")
    with pytest.raises(ConfigError) as info:
        MotionCaptureSource(zmq.Context.instance(), "vicn", {}, {"kh0": 0}, "z", log=lambda line: None,
                            connect=unknown)
    assert info.value.field == "source.system"
    assert "Unknown motion capture type! (motioncapture 1.x knows mock, vicon, optitrack" in info.value.problem


def reference_convert(bodies, names_to_ids, up_axis):
    """The conversion body by body: listed names only, world pose per body, non-finite poses dropped."""
    ids, poses = [], []
    for name, body in bodies.items():
        if name in names_to_ids:
            q = body.rotation
            pose = pose_from_mocap(body.position.tolist(), (q.w, q.x, q.y, q.z), up_axis)
            if all(math.isfinite(v) for v in pose):
                ids.append(names_to_ids[name])
                poses.append(pose)
    return ids, np.asarray(poses, dtype=float).reshape(-1, 3)


def random_bodies(rng, names, occluded=(), unoriented=()):
    """``unoriented`` bodies come with a quaternion of all zeros (as some systems give for a body they lost)."""
    bodies = {}
    for name in names:
        q = rng.normal(size=4)
        position = rng.uniform(-3.0, 3.0, 3)
        if name in occluded:
            position = np.full(3, np.nan)
        bodies[name] = FakeBody(position, np.zeros(4) if name in unoriented else q / np.linalg.norm(q))
    return bodies


@pytest.mark.parametrize("up_axis", ["z", "y"])
def test_converting_rigid_bodies_matches_the_body_by_body_conversion(up_axis):
    listed = {f"kh{i}": 10 + i for i in range(6)}
    lines = []
    source = fake_source(listed, up_axis, lines)
    try:
        rng = np.random.default_rng(4)
        frames = [
            random_bodies(rng, ["kh0", "kh1", "stray", "kh2", "kh3", "kh4", "kh5"]),
            random_bodies(rng, ["kh0", "kh1", "stray", "kh2", "kh3", "kh4", "kh5"], occluded={"kh2"}),
            random_bodies(rng, ["kh0", "kh1", "kh2", "kh3", "kh4", "kh5"], unoriented={"kh1", "kh4"}),
            random_bodies(rng, ["kh5", "kh4", "kh0"]),                 # bodies left and changed order
            random_bodies(rng, ["kh0", "kh1", "kh2", "kh3", "kh4", "kh5", "other"]),
            random_bodies(rng, ["kh0", "kh1", "kh2", "kh3", "kh4", "kh5"]),
            {},
        ]
        for k, bodies in enumerate(frames):
            frame = source._convert(100.0 + k, bodies)
            ids, poses = reference_convert(bodies, listed, up_axis)
            assert frame.stamp == 100.0 + k
            assert frame.ids == ids
            assert frame.poses.shape == (len(ids), 3)
            np.testing.assert_allclose(frame.poses, poses, rtol=0, atol=1e-12)
    finally:
        source.close()
    ignored = [line for line in lines if "ignoring rigid body" in line]
    assert ignored == ["hub: ignoring rigid body 'stray' (not listed in source.bodies)",
                       "hub: ignoring rigid body 'other' (not listed in source.bodies)"]   # once per name


def test_a_y_up_body_is_placed_on_the_z_up_floor():
    source = fake_source({"kh0": 0}, "y", [])
    try:
        quarter = (math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0)    # a quarter turn about +y
        frame = source._convert(1.0, {"kh0": FakeBody((1.0, 0.05, -2.0), quarter)})
    finally:
        source.close()
    assert frame.ids == [0]
    np.testing.assert_allclose(frame.poses, [[1.0, 2.0, math.pi / 2]], atol=1e-6)
    # A body at z = 0 is at y = 0, not -0.0, which the geofence line and the log showed as -0.00.
    source = fake_source({"kh0": 0}, "y", [])
    try:
        frame = source._convert(1.0, {"kh0": FakeBody((1.0, 0.05, 0.0), quarter)})
    finally:
        source.close()
    assert math.copysign(1.0, frame.poses[0, 1]) == 1.0
    assert math.copysign(1.0, pose_from_mocap((1.0, 0.05, 0.0), quarter, "y")[1]) == 1.0


def quarter_turns(k):
    return (math.cos(k * math.pi / 4), 0.0, 0.0, math.sin(k * math.pi / 4))     # k quarter turns about +z


class RewrittenInPlace:
    """The SDK as it is: ``rigidBodies`` hands out the same body objects every frame (views into its own
    storage, which Vicon and Qualisys rebuild on each read), so a field read after the next frame is that
    frame's."""

    def __init__(self, names):
        self.rigidBodies = {name: FakeBody((0.0, 0.0, 0.0), quarter_turns(0)) for name in names}

    def next_frame(self, poses):
        for name, (x, turns) in poses.items():
            self.rigidBodies[name].position[:] = (x, 0.0, 0.0)
            self.rigidBodies[name].rotation = FakeQuaternion(*quarter_turns(turns))


def test_a_frame_keeps_its_own_yaws_when_the_sdk_rewrites_its_bodies_for_the_next():
    """The yaws were read from the SDK's objects when a row was sent or recorded, after the reader thread had
    moved on: frame N's positions went out and into the log with frame N+1's yaw (or, for a body frame N+1
    lacked, with whatever its freed storage held)."""
    hub = build_hub(mock_config("kh0(0,0,0,1,0,0,0);kh1(0.5,0,0,1,0,0,0)"), log=lambda line: None)
    source = fake_source({"kh0": 0, "kh1": 1}, "z", [])
    sdk = RewrittenInPlace(["kh0", "kh1"])
    try:
        sdk.next_frame({"kh0": (1.0, 1), "kh1": (2.0, 0)})
        frame_n = source._convert(100.0, sdk.rigidBodies)
        sdk.next_frame({"kh0": (1.1, -1), "kh1": (2.0, 2)})            # the reader thread is at frame N+1
        hub.on_pose_frame(frame_n)
        assert hub.sensors.frames([0, 1]).poses == [pytest.approx((1.0, 0.0, math.pi / 2), abs=1e-4),
                                                    pytest.approx((2.0, 0.0, 0.0), abs=1e-4)]
        x, _, _, _, _, qz, qw = poses_record(frame_n)["bodies"]["0"]
        assert (x, 2.0 * math.atan2(qz, qw)) == pytest.approx((1.0, math.pi / 2), abs=1e-5)
    finally:
        source.close()
        hub.source.close()


def test_a_body_without_an_orientation_is_held_like_an_occluded_one():
    """A body whose orientation is not finite or not a rotation (all zeros, as some systems give for a body they
    lost) was sent without a pose, but its robot ran on in `run`, blind, and the others still heard it. It is
    now left out of the frame: it keeps its last pose for stale_s, and is then held, as an occluded one is."""
    hub = build_hub(mock_config("kh0(0,0,0,1,0,0,0);kh1(0.5,0,0,1,0,0,0)"), log=lambda line: None)
    source = fake_source({"kh0": 0, "kh1": 1}, "z", [])
    try:
        hub.mode = "run"
        hub.on_pose_frame(source._convert(100.0, {"kh0": FakeBody((0, 0, 0), quarter_turns(1)),
                                                  "kh1": FakeBody((0.5, 0, 0), quarter_turns(2))}))
        assert hub.sensors.frames([0]).poses[0] == pytest.approx((0.0, 0.0, math.pi / 2), abs=1e-4)
        for k, broken in enumerate([(0.0,) * 4, (math.nan,) * 4, (1.0, 0.0, 0.0, math.inf)]):
            frame = source._convert(101.0 + k, {"kh0": FakeBody((0.2, 0, 0), broken),
                                                 "kh1": FakeBody((0.5, 0, 0), quarter_turns(0))})
            assert frame.ids == [1] and list(poses_record(frame)["bodies"]) == ["1"], broken
            hub.on_pose_frame(frame)            # a second after the last frame that had kh0: stale
            assert hub.sensors.pose_of(0) is None and hub.sensors.receivers_of(1) == []
            assert hub.mode_for(hub.robots[0]) == ("hold", "not tracked by motion capture")
            assert hub.mode_for(hub.robots[1]) == ("run", "")
        assert math.isnan(pose_from_mocap((0.3, 0, 0), (0.0,) * 4, "z")[2])
        assert math.isnan(pose_from_mocap((0.3, 0, 0), (1.0, 0.0, 0.0, math.inf), "z")[2])   # was 135 degrees
    finally:
        source.close()
        hub.source.close()


def test_stale_bodies_lose_their_pose_and_are_held():
    hub = build_hub(mock_config("kh0(0,0,0,1,0,0,0);kh1(0.5,0,0,1,0,0,0)"), log=lambda line: None)
    try:
        hub.mode = "run"
        both = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]])
        hub.on_pose_frame(PoseFrame(100.0, [0, 1], both))
        assert hub.sensors.pose_of(1) is not None and hub.mode_for(hub.robots[1]) == ("run", "")
        hub.on_pose_frame(PoseFrame(100.05, [0], both[:1]))          # robot 1 missing, but within stale_s
        assert hub.sensors.pose_of(1) is not None
        hub.on_pose_frame(PoseFrame(100.2, [0], both[:1]))           # now older than stale_s = 0.1 s
        assert hub.sensors.pose_of(1) is None and hub.sensors.receivers_of(0) == []
        assert hub.mode_for(hub.robots[1]) == ("hold", "not tracked by motion capture")
    finally:
        hub.source.close()


def test_a_fault_killing_a_robot_this_lab_does_not_serve_is_ignored():
    """A sim-source hub may serve some of the scenario's robots (`robots: [0, 1]` of lab-6); a scenario fault
    that killed robot 5 raised KeyError in the hub's loop, which ended the hub."""
    hub = build_hub(mock_config("kh0(0,0,0,1,0,0,0);kh1(0.5,0,0,1,0,0,0)"), log=lambda line: None)
    try:
        hub.mode = "run"
        poses = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]])
        hub.on_pose_frame(PoseFrame(100.0, [0, 1], poses, killed=(5, 1)))
        assert hub.mode_for(hub.robots[0]) == ("run", "")
        assert hub.mode_for(hub.robots[1]) == ("hold", "killed by a scenario fault")
    finally:
        hub.source.close()


def test_robots_are_held_when_motion_capture_stops_sending_altogether():
    """No frame at all (the cameras stopped, a replay ended): the robots' poses still go stale and they are
    held. Presence used to be recomputed only when a frame arrived, so they ran on, on their last pose."""
    hub = build_hub(mock_config("kh0(0,0,0,1,0,0,0);kh1(0.5,0,0,1,0,0,0)"), log=lambda line: None)
    try:
        hub.mode = "run"
        now = time.monotonic()
        hub.on_pose_frame(PoseFrame(now, [0, 1], np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]])))
        hub.housekeeping(now + 0.05)
        assert hub.mode_for(hub.robots[1]) == ("run", "") and hub.sensors.pose_of(0) is not None
        hub.housekeeping(now + 0.2)                                   # no frame since: older than stale_s
        assert hub.mode_for(hub.robots[0]) == ("hold", "not tracked by motion capture")
        assert hub.mode_for(hub.robots[1]) == ("hold", "not tracked by motion capture")
        assert hub.sensors.pose_of(0) is None and hub.sensors.frames([0]).poses == [None]
    finally:
        hub.source.close()


def test_a_waiting_pose_frame_interrupts_uplink_reading():
    hub = build_hub(mock_config("kh0(0,0,0,1,0,0,0);kh1(0.5,0,0,1,0,0,0)"), log=lambda line: None)
    sock = zmq.Context.instance().socket(zmq.DEALER)
    try:
        hub.bind()
        sock.connect(hub.endpoints["robots"])
        for step in range(1, 101):
            sock.send(encode({"type": "telemetry", "id": 0, "step": step, "mode": "idle"}))
        deadline = time.monotonic() + 5.0
        while hub.robot_socket.getsockopt(zmq.EVENTS) & zmq.POLLIN == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.2)                       # all 100 queued at the hub
        hub.source.wake.poke()                # a pose frame waits
        hub.handle_uplink_events({hub.robot_socket: zmq.POLLIN})
        assert hub.robots[0].step_answered == UPLINK_SLICE - 1
        hub.source.running = False            # no more pose frames: the rest is read in one go
        hub.source.thread.join()
        hub.source.wake.drain()
        hub.handle_uplink_events({hub.robot_socket: zmq.POLLIN})
        assert hub.robots[0].step_answered == 100
    finally:
        sock.close(0)
        hub.close()


def test_the_log_holds_each_frame_as_the_agent_decoded_it(tmp_path):
    log = tmp_path / "hub.mcap"
    with HubThread(mock_config("kh0(1.0,2.0,0.05,1,0,0,0);kh1(1.5,2.0,0.05,1,0,0,0)", record=str(log))) as hub:
        frame = first_frame_for(hub.endpoints["robots"], 0)
    records = list(read_log(log))
    recorded = next(r.payload for r in records if r.topic == "/robot/0/frame" and r.payload["seq"] == frame["seq"])
    assert {**recorded, "v": frame["v"]} == frame
    poses = next(r for r in records if r.topic == "/mocap/poses")
    assert set(poses.payload["bodies"]) == {"0", "1"}


def test_replay_serves_recorded_poses(tmp_path):
    log = tmp_path / "run.mcap"
    with Recorder(log) as recorder:
        for k in range(20):
            poses = np.array([[0.1 * k, 0.0, math.pi / 4], [0.1 * k, 1.0, 0.0]])
            recorder.write("/mocap/poses", poses_record(PoseFrame(0.0, [0, 1], poses)), stamp_s=1.7e9 + 0.05 * k)
    config = parse_config({"source": {"type": "replay", "file": str(log)}, "robots": [0, 1], "network": NETWORK,
                           "security": {"insecure": True}, "run": {"behaviour": "aggregate"}})
    with HubThread(config) as hub:
        frame = first_frame_for(hub.endpoints["robots"], 0)
        x, y, yaw = frame["pose"]
        assert y == pytest.approx(0.0, abs=1e-4) and yaw == pytest.approx(math.pi / 4, abs=1e-4)
        assert 0.0 <= x <= 1.9 + 1e-6
        assert frame["neighbours"][0][:2] == [1, pytest.approx(1.0, abs=0.05)]


def test_replay_warns_at_start_of_lab_robots_the_log_never_places(tmp_path):
    """robots: [0, 1, 2, 5] with a log of robots 0 and 1 (robot 1 only late): robots 2 and 5 were held all
    along, and nothing said why."""
    log = tmp_path / "run.mcap"
    with Recorder(log) as recorder:
        for k in range(20):
            ids = [0, 1] if k >= 15 else [0]
            poses = np.array([[0.1 * k, float(i), 0.0] for i in ids])
            recorder.write("/mocap/poses", poses_record(PoseFrame(0.0, ids, poses)), stamp_s=1.7e9 + 0.05 * k)
    lines = []

    def started(robots):
        lines.clear()
        config = parse_config({"source": {"type": "replay", "file": str(log)}, "robots": robots, "network": NETWORK,
                               "security": {"insecure": True}, "run": {"behaviour": "aggregate"}})
        build_hub(config, log=lines.append).close()
        return [line for line in lines if "no pose" in line]

    # ... and which robots the log does place: finding that out took a script.
    assert started([0, 1, 2, 5]) == [f"hub: warning: robots 2, 5 of this lab (robots) have no pose in {log} "
                                      "(source.file): the replay never places them, so they stay held; the log "
                                      "places 0, 1"]
    assert started([1, 3]) == [f"hub: warning: robot 3 of this lab (robots) has no pose in {log} (source.file): "
                               "the replay never places it, so it stays held; the log places 0, 1"]
    assert started([0, 1]) == []


def walking_log(path, frames, period_s=0.05):
    """A hub log of robots 0 and 1 walking along x, 1 m apart, one /mocap/poses record every ``period_s``."""
    with Recorder(path) as recorder:
        for k in range(frames):
            poses = np.array([[0.01 * k, 0.0, 0.0], [0.01 * k, 1.0, 0.0]])
            recorder.write("/mocap/poses", poses_record(PoseFrame(0.0, [0, 1], poses)), stamp_s=1.7e9 + period_s * k)
    return path


def replay_config(log, rate):
    return parse_config({"source": {"type": "replay", "file": str(log), "rate": rate}, "robots": [0, 1],
                         "network": NETWORK, "security": {"insecure": True}, "run": {"behaviour": "aggregate"}})


def test_a_slowed_replay_keeps_the_robots_tracked_between_its_frames(tmp_path):
    """At rate 0.1 a 20 Hz log gives a frame every 0.5 s, five times source.stale_s: every robot was held as
    'not tracked by motion capture' between two frames."""
    config = replay_config(walking_log(tmp_path / "run.mcap", frames=40), rate=0.1)
    hub = build_hub(config, log=lambda line: None)
    try:
        hub.bind()
        held = []
        deadline = time.monotonic() + 2.5      # about five replayed frames
        while time.monotonic() < deadline:
            for frame in hub.source.poll(time.monotonic()):
                hub.on_pose_frame(frame)
            hub.housekeeping(time.monotonic())
            if hub.last_frame_stamp > -math.inf:
                held.append(not hub.sensors.present.all())
            time.sleep(0.02)
        assert held and not any(held)
    finally:
        hub.close()


def test_each_run_replays_the_log_from_its_start(tmp_path):
    """The replay started with the hub: agents that had to connect first saw it only from where it was by then
    (0.6-0.8 s into a sil log, although started before the hub). Like the sim source's world, each run now begins
    at the log's first record; `reset_each_run: false` keeps the replay going."""
    for reset in (True, False):
        config = replay_config(walking_log(tmp_path / f"run-{reset}.mcap", frames=40), rate=1.0)
        config.source.reset_each_run = reset
        lines = []
        hub = build_hub(config, log=lines.append)
        try:
            hub.bind()
            deadline = time.monotonic() + 0.5                # 10 records played before the operator's start
            while time.monotonic() < deadline:
                for frame in hub.source.poll(time.monotonic()):
                    hub.on_pose_frame(frame)
                time.sleep(0.02)
            assert hub.source.progress()["played_s"] >= 0.3 and hub.poses[hub.row[0], 0] >= 0.06
            assert hub.control.execute("start")[0]
            if reset:
                assert hub.source.progress()["played_s"] == 0.0 and hub.poses[hub.row[0], 0] == 0.0
                assert lines[-1].endswith(": aggregate; the replay is back at the log's start"), lines
            else:
                assert hub.source.progress()["played_s"] >= 0.3 and hub.poses[hub.row[0], 0] >= 0.06
            if reset:                                         # the log gone since: the replay goes on, said
                assert hub.control.execute("stop")[0]
                (tmp_path / f"run-{reset}.mcap").unlink()
                assert hub.control.execute("start")[0]
                assert "cannot start" in lines[-2] and lines[-2].endswith("; it goes on from where it was"), lines
                assert lines[-1].endswith(": aggregate"), lines      # not "back at the log's start"
        finally:
            hub.close()


def test_a_slowed_replay_does_not_say_motion_capture_stopped_between_its_frames(tmp_path):
    """At rate 0.04 a 20 Hz log gives a frame every 1.25 s: the hub said `no motion-capture frame for 1 s` and
    `motion capture is back` with every frame. The silence it speaks of is stretched by 1/rate too."""
    config = replay_config(walking_log(tmp_path / "run.mcap", frames=40), rate=0.04)
    lines = []
    hub = build_hub(config, log=lines.append)
    try:
        hub.bind()
        frames, deadline = 0, time.monotonic() + 2.8      # three replayed frames, 1.25 s apart
        while time.monotonic() < deadline:
            for frame in hub.source.poll(time.monotonic()):
                hub.on_pose_frame(frame)
                frames += 1
            hub.housekeeping(time.monotonic())
            time.sleep(0.02)
        assert frames >= 2 and hub.silent_s == 25.0
        assert not [line for line in lines if "motion-capture frame" in line or "motion capture is back" in line]
    finally:
        hub.close()


def test_ctl_status_shows_how_far_the_replay_has_got(tmp_path):
    """With the replay source `ctl status` said nothing of where in the log the replay was, or that it had ended:
    only the hub's console did, at the end."""
    log, cut = tmp_path / "run.mcap", tmp_path / "cut.mcap"
    with Recorder(log) as recorder:
        for k in range(21):
            poses = np.array([[0.01 * k, 0.0, 0.0], [0.01 * k, 1.0, 0.0]])
            recorder.write("/mocap/poses", poses_record(PoseFrame(0.0, [0, 1], poses)), stamp_s=1.7e9 + 0.1 * k)
        recorder.flush()
        cut.write_bytes(log.read_bytes())       # what a killed hub leaves: no index, no footer

    def replay(path):
        config = parse_config({"source": {"type": "replay", "file": str(path)}, "robots": [0, 1], "network": NETWORK,
                               "security": {"insecure": True}, "run": {"behaviour": "aggregate"}})
        with HubThread(config) as hub:
            early = hub.status()
            return early, hub.wait_until(lambda status: status["replay"]["ended"], timeout_s=15.0)

    early, ended = replay(log)
    assert early["object"] is None
    going = early["replay"]
    assert going["total_s"] == 2.0 and going["played_s"] < 2.0 and not going["ended"] and going["rate"] == 1.0
    assert status_table(early).splitlines()[-1] == \
        f"replay: {going['played_s']:.1f} s of 2.0 s played ({going['percent']:.0f} %) at 1x"
    assert ended["replay"] == {"played_s": 2.0, "total_s": 2.0, "percent": 100.0, "rate": 1.0, "ended": True,
                               "passed_over": 0}
    assert status_table(ended).splitlines()[-1] == "replay: ended: 2.0 s of 2.0 s played (100 %) at 1x"

    early, ended = replay(cut)              # its length is not known without reading it all: the file's share
    assert early["replay"]["total_s"] is None and 0 < early["replay"]["percent"] <= 100
    assert status_table(early).splitlines()[-1].endswith("% of the file (a log cut short: its length is not known)")
    assert ended["replay"]["played_s"] == 2.0 and ended["replay"]["percent"] == 100.0


def test_an_unknown_sim_scenario_names_the_lab_configs_field():
    """The lab config's field is source.scenario."""
    for scenario, field in (("no-such-scenario", "source.scenario"), ("lab-6", None)):
        config = parse_config({"source": {"type": "sim", "scenario": scenario}, "network": NETWORK,
                               "security": {"insecure": True}})
        if field is None:
            build_hub(config, log=lambda line: None).close()
            continue
        with pytest.raises(ConfigError) as info:
            build_hub(config, log=lambda line: None)
        assert info.value.field == field and "not built in" in str(info.value)


@pytest.mark.parametrize("scenario, said", [
    # A scenario beside the config, named without its folder, read as gone: the hub looks from its own folder.
    ("beside-the-config.yaml", r"^source.scenario: no such file: beside-the-config.yaml \(a lab config's paths are "
                               r"relative to the folder the hub is started in, "),
    # `source: {scenario: ./lab-6}` with no file ./lab-6 served the built-in lab-6 without a word.
    ("./lab-6", r"^source.scenario: no such file: ./lab-6 \(the built-in scenario is lab-6, without a folder\) \(a "
                r"lab config's paths are relative to the folder"),
])
def test_a_sim_scenario_file_that_is_not_there_is_an_error_naming_where_the_hub_looked(tmp_path, monkeypatch,
                                                                                        scenario, said):
    monkeypatch.chdir(tmp_path)
    config = parse_config({"source": {"type": "sim", "scenario": scenario}, "network": NETWORK,
                           "security": {"insecure": True}})
    with pytest.raises(ConfigError, match=said):
        build_hub(config, log=lambda line: None)


def test_a_bad_field_inside_the_sim_scenario_file_names_the_file_and_the_field(tmp_path):
    """It said only "behaviour: unknown behaviour 'goto'", which reads as a key of the lab config."""
    (tmp_path / "goto.yaml").write_text("behaviour: goto\nrobots: {count: 2}\n")
    config = parse_config({"source": {"type": "sim", "scenario": str(tmp_path / "goto.yaml")}, "network": NETWORK,
                           "security": {"insecure": True}})
    with pytest.raises(ConfigError, match=r"^source.scenario: .*goto.yaml: behaviour: unknown behaviour 'goto'"):
        build_hub(config, log=lambda line: None)


def test_an_agent_still_in_a_run_this_hub_ended_is_not_said_to_be_in_a_run_it_never_started():
    """Hub and agents stopped together (SIGTERM to all): an agent reconnecting as the hub ended its run was said
    to be `in run ..., which this hub did not start (was the hub restarted during it?)`."""
    lines = []
    hub = build_hub(parse_config({"source": {"type": "sim"}, "network": NETWORK, "security": {"insecure": True}}),
                    log=lines.append)
    try:
        hub.bind()
        hub.control.execute("start")
        ended = hub.run_id
        hub.control.execute("stop")
        for robot in hub.robots.values():
            robot.routing = b"\x00gone"           # a connection ZeroMQ no longer has: what is sent there is dropped
        hub._on_hello(hub.robots[0], {"driver": "sim", "run_id": ended}, time.monotonic())
        assert not [line for line in lines if "did not start" in line], lines
        hub._on_hello(hub.robots[1], {"driver": "sim", "run_id": "0123456789ab"}, time.monotonic())
        (unknown,) = [line for line in lines if "did not start" in line]
        assert unknown.startswith("hub: robot 1 was in run 0123456789ab, which this hub did not start")
    finally:
        hub.close()


def test_a_real_robots_agent_joining_a_sim_hub_is_told_about_once():
    lines = []
    hub = build_hub(parse_config({"source": {"type": "sim"}, "network": NETWORK, "security": {"insecure": True}}),
                    log=lines.append)
    try:
        robot = hub.robots[0]
        for message in ({"driver": "kh4"}, {"driver": "kh4"}):
            hub._on_hello(robot, message, time.monotonic())
        hub._on_hello(hub.robots[1], {"driver": "sim"}, time.monotonic())
        said = [line for line in lines if "driver, but this hub simulates" in line]
        assert said == [said[0]] and said[0].startswith("hub: robot 0's agent uses the kh4 driver")
        assert robot.driver == "kh4"
    finally:
        hub.close()


def real_wheels_source(kind, tmp_path):
    if kind == "sim":
        return {"type": "sim"}
    if kind == "mock":
        return {"type": "motioncapture", "system": "mock", "up_axis": "z", "bodies": {"kh0": 0, "kh1": 1},
                "options": {"frequency": "50", "rigid_bodies": "kh0(0,0,0,1,0,0,0);kh1(0.5,0,0,1,0,0,0)"}}
    log = tmp_path / "run.mcap"
    with Recorder(log) as recorder:
        recorder.write("/mocap/poses", poses_record(PoseFrame(0.0, [0, 1], np.array([[0.0, 0, 0], [0.5, 0, 0]]))),
                       stamp_s=1.7e9)
    return {"type": "replay", "file": str(log)}


@pytest.mark.parametrize("kind, why", [("sim", "this hub simulates the robots"),
                                       ("mock", "the mock motion capture's poses do not follow real robots"),
                                       ("replay", "a replay's poses come from a recording")])
def test_a_robot_with_real_wheels_is_held_when_the_poses_are_not_the_rooms(tmp_path, kind, why):
    """A kh4 agent drove its wheels through a whole replay (and against the mock motion capture, whose poses
    never move), steering by poses that did not follow it; lab.md says the wheels move nothing there."""
    source = real_wheels_source(kind, tmp_path)
    hub = build_hub(parse_config({"source": source, "network": NETWORK, "security": {"insecure": True},
                                  "robots": [0, 1], "run": {"behaviour": "aggregate"}}), log=lambda line: None)
    try:
        real, simulated = hub.robots[0], hub.robots[1]
        hub._on_hello(real, {"driver": "kh4"}, time.monotonic())
        hub._on_hello(simulated, {"driver": "sim"}, time.monotonic())
        hub.mode = "run"
        assert hub.mode_for(real) == ("hold", f"{why}: a robot with real wheels (kh4) is held")
        assert hub.mode_for(simulated)[1] != hub.mode_for(real)[1]
    finally:
        hub.close()


def test_a_recorded_pose_holds_no_negative_zero():
    record = poses_record(PoseFrame(0.0, [4], np.array([[-1e-7, -2e-6, -1e-8]])))
    assert json.dumps(record["bodies"]) == '{"4": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]}'


@pytest.mark.parametrize("mocap_hz, served", [(5.0, [0, 1]), (120.0, [])])
def test_motion_capture_slower_than_the_downlink_reaches_every_robot_with_each_frame(mocap_hz, served):
    """At 5 Hz a pose frame waited for each robot's downlink turn, up to 75 ms; at 120 Hz the turns spread the
    bursts, and the next frame is at most 8 ms away."""
    hub = build_hub(mock_config("kh0(0,0,0,1,0,0,0);kh1(0.5,0,0,1,0,0,0)"), log=lambda line: None)
    hub.source.running = False              # only the pose frame below
    hub.source.thread.join()
    sockets = []
    try:
        hub.bind()
        for rid in (0, 1):
            sock = zmq.Context.instance().socket(zmq.DEALER)
            sock.linger = 0
            sock.connect(hub.endpoints["robots"])
            sock.send(encode({"type": "hello", "id": rid, "driver": "test"}))
            sockets.append(sock)
        deadline = time.monotonic() + 5.0
        while any(r.routing is None for r in hub.robots.values()) and time.monotonic() < deadline:
            if hub.robot_socket.poll(50):
                hub.handle_uplink_events({hub.robot_socket: zmq.POLLIN})
        for sock in sockets:                # the welcome frames the hellos brought
            while sock.poll(200):
                sock.recv()
        now = time.monotonic()
        for robot in hub.robots.values():
            robot.next_due = now + 0.04     # each had its frame 10 ms ago
        hub.mocap_rate.hz = mocap_hz
        hub.on_pose_frame(PoseFrame(now, [0, 1], np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]])))
        hub.send_due(now, fresh=True)
        got = [rid for rid, sock in zip((0, 1), sockets)
               if sock.poll(500) and decode(sock.recv(), "hub")["pose"] is not None]
        assert got == served
    finally:
        for sock in sockets:
            sock.close(0)
        hub.close()


def test_a_fast_replay_counts_and_says_the_frames_it_passed_over(tmp_path):
    """At rate 100 a 50 Hz log's frames fall due faster than the hub's loop: only the newest of each pass is fed
    (latest-only), and about one in ten was left out without a word."""
    from hub.control import replay_text
    from hub.replay_source import ReplaySource

    log = tmp_path / "run.mcap"
    with Recorder(log) as recorder:
        for k in range(50):
            recorder.write("/mocap/poses", poses_record(PoseFrame(0.0, [0], np.array([[0.01 * k, 0.0, 0.0]]))),
                           stamp_s=1.7e9 + 0.02 * k)
    lines = []
    source = ReplaySource(str(log), rate=100.0, log=lines.append)
    fed = [source.poll(1000.0)]                   # the first record starts the clock
    fed += [source.poll(1000.0 + 0.001 * k) for k in range(1, 12)]     # 1 ms passes: 5 records fall due in each
    assert sum(len(frames) for frames in fed) + source.passed_over == 50 and source.passed_over > 30
    assert lines == [f"hub: replay reached the end of the log ({source.passed_over} pose frames passed over: at "
                     "100x they came faster than the hub's loop, which sends only the newest (a smaller "
                     "source.rate feeds them all))"]
    assert replay_text(source.progress()).endswith(f", {source.passed_over} frames passed over to keep up")


def test_at_the_end_of_a_replay_the_robots_are_held_because_it_ended(tmp_path):
    """After the last frame every robot was 'not tracked by motion capture', and the hub said 'no motion-capture
    frame for 1 s', as if the cameras had stopped, right after 'replay reached the end of the log'."""
    config = replay_config(walking_log(tmp_path / "run.mcap", frames=5), rate=2.0)
    lines = []
    hub = build_hub(config, log=lines.append)
    try:
        hub.bind()
        hub.mode = "run"
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            for frame in hub.source.poll(time.monotonic()):
                hub.on_pose_frame(frame)
            hub.housekeeping(time.monotonic())
            time.sleep(0.02)
        assert hub.source.ended and hub.mode_for(hub.robots[0]) == ("hold", "the replay has ended")
    finally:
        hub.close()
    assert "hub: replay reached the end of the log" in lines
    assert not [line for line in lines if "no motion-capture frame" in line], lines


def test_a_long_log_is_looked_through_for_unplaced_robots_only_so_long(tmp_path):
    """With one lab robot never placed the hub read the whole log before it listened: about a minute, silent, for
    an hour of 100 robots. Past its scan time it says how far it looked instead."""
    from hub.factory import say_unplaced_replay_robots
    from hub.replay_source import ReplaySource

    log = tmp_path / "run.mcap"
    with Recorder(log) as recorder:
        for k in range(600):
            recorder.write("/mocap/poses", poses_record(PoseFrame(0.0, [0], np.array([[0.0, 0.0, 0.0]]))),
                           stamp_s=1.7e9 + 0.1 * k)
    source = ReplaySource(str(log), log=lambda line: None)
    assert source.never_placed([0, 7]) == ([7], None)                      # read to the end: never placed
    missing, scanned_s = source.never_placed([0, 7], scan_s=0.0)          # out of time at once
    assert missing == [7] and 25.0 <= scanned_s < 59.9

    class Cut:
        path = log
        placed_ids = [0]

        def never_placed(self, ids):
            return [7], 25.5
    said = []
    say_unplaced_replay_robots(Cut(), [0, 7], said.append)
    assert said == [f"hub: warning: robot 7 of this lab (robots) has no pose in the first 26 s of {log} "
                    "(source.file): it is held until the replay places it; so far the log places 0"]


def test_log_info_tells_each_e_stop_with_its_clear_and_the_start_that_resumed_the_run(tmp_path):
    """A run that stood still for a minute: the log's reader had to find why in /control by hand."""
    from hub.log_summary import summarise
    from hub.log_text import format_summary

    log = tmp_path / "hub.mcap"
    with HubThread(mock_config("kh0(1.0,2.0,0.05,1,0,0,0);kh1(1.5,2.0,0.05,1,0,0,0)", record=str(log))) as hub:
        for cmd in ("start", "estop", "estop", "clear", "start", "stop", "estop"):   # the second: while latched
            assert hub.request(cmd)["ok"], cmd
    summary = summarise(log)
    run = summary.runs[0]["run_id"]
    assert [(e["run_id"], e["cleared_s"] is not None, e["resumed_s"] is not None) for e in summary.estops] == [
        (run, True, True), (None, False, False)]
    first = summary.estops[0]
    assert summary.runs[0]["started_s"] <= first["at_s"] <= first["cleared_s"] <= first["resumed_s"] \
        <= summary.runs[0]["ended_s"]
    lines = [line for line in format_summary(summary).splitlines() if line.startswith("e-stop:")]
    clock = r"\d\d:\d\d:\d\d"
    assert len(lines) == 2 and re.fullmatch(
        rf"e-stop:    {clock} by (.+) in run {run}; cleared {clock} by \1; run resumed {clock} by \1", lines[0]), lines
    assert re.fullmatch(rf"e-stop:    {clock} by .+ \(no run going\); not cleared in the log", lines[1]), lines
    assert summarise(log, use_index=False).estops == summary.estops        # the walk, as for a killed hub's log
    # Each /control record carries the hub's mode and run after it: the resuming start keeps the run's id.
    control = [(r.payload["cmd"], r.payload["mode"], r.payload["run_id"]) for r in read_log(log, topics=["/control"])]
    assert control == [("start", "run", run), ("estop", "estop", run), ("estop", "estop", run),
                       ("clear", "hold", run), ("start", "run", run), ("stop", "idle", None),
                       ("estop", "estop", None)], control


def log_console(path):
    return subprocess.run([sys.executable, "-m", "khepri_cli.main", "log", "console", str(path)], capture_output=True,
                          text=True, env=dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1])))


def test_the_hubs_console_lines_are_in_its_log_and_log_console_prints_them(tmp_path):
    """A terminal's scrollback was the only record of an evening's connections, e-stops and refusals."""
    from mcap.reader import make_reader

    log = tmp_path / "hub.mcap"
    with HubThread(mock_config("kh0(1.0,2.0,0.05,1,0,0,0);kh1(1.5,2.0,0.05,1,0,0,0)", record=str(log))) as hub:
        hub.request("start")
        hub.request("estop")
        said = list(hub.lines)
    shown = log_console(log)
    assert shown.returncode == 0, shown.stderr
    printed = shown.stdout.splitlines()
    stamp = r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{3}  "
    assert all(re.match(stamp, line) for line in printed), printed
    # Every line the hub said up to the e-stop, in order, beginning with those said before its log was open.
    messages = [line[25:] for line in printed]
    assert messages[:len(said)] == said and any("E-STOP" in line for line in messages), (said, messages)
    # A killed hub's log (no summary at its end): the lines recovered, and a word that there may be more.
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(log.read_bytes()[:-100])
    shown_cut = log_console(cut)
    assert shown_cut.returncode == 0 and shown_cut.stdout.splitlines()[:3] == printed[:3], shown_cut
    assert f"khepri: {cut}: the log ends early (" in shown_cut.stderr, shown_cut.stderr
    assert "ends early" not in shown.stderr
    # A damaged chunk (bytes overwritten on disk) was skipped without a word, exit code 0, lines missing.
    damaged = tmp_path / "damaged.mcap"
    data = bytearray(log.read_bytes())
    data[200:232] = b"\xff" * 32
    damaged.write_bytes(bytes(data))
    shown_damaged = log_console(damaged)
    assert shown_damaged.returncode == 1 and f"khepri: {damaged}: damaged, " in shown_damaged.stderr, shown_damaged
    assert "console lines in them are missing" in shown_damaged.stderr
    # A record after the last chunk damaged in a file that ends closed: log info says DAMAGED (written to its
    # end, damaged since), and this said only that the log ends early, exit 0.
    bad_end = tmp_path / "bad-end.mcap"
    data = bytearray(log.read_bytes())
    summary_start = struct.unpack_from("<Q", data, len(data) - 8 - 20)[0]     # the footer's summary_start
    data[summary_start] = 0                                                  # opcode 0: not a record
    bad_end.write_bytes(bytes(data))
    shown_end = log_console(bad_end)
    assert shown_end.returncode == 1 and f"khepri: {bad_end}: the log is damaged at its end (" in shown_end.stderr, \
        shown_end
    with open(log, "rb") as file:       # Foxglove's Log panel reads foxglove.Log messages
        reader = make_reader(file)
        schema, channel, message = next(reader.iter_messages(topics=["/hub/log"]))
        assert schema.name == "foxglove.Log" and channel.message_encoding == "json"
        first = json.loads(message.data)
        assert set(first) == {"timestamp", "level", "message", "name", "file", "line"}
        assert abs(first["timestamp"]["sec"] + first["timestamp"]["nsec"] / 1e9 - message.log_time / 1e9) < 1e-6


def test_log_console_of_a_log_without_console_lines_says_so(tmp_path):
    from hub.recording import Recorder

    log = tmp_path / "old.mcap"
    with Recorder(log) as recorder:
        recorder.write("/hub/status", {"frames_per_s": 1.0})
    shown = log_console(log)
    assert shown.returncode == 1 and shown.stdout == ""
    assert shown.stderr.strip() == f"khepri: {log}: no console lines in this log (/hub/log: recorded by hubs since " \
                                   "2026-11-29)"
    empty = log_console(" ")            # as log info: refused naming the argument, not read as the folder "."
    assert empty.returncode == 2 and "FILE: an empty path: name the .mcap log" in empty.stderr, empty.stderr


def test_a_hub_console_with_no_log_keeps_no_lines_once_the_hub_is_built():
    """It kept up to 500 lines for a log that would never open."""
    from hub.console import HubConsole

    printed = []
    console = HubConsole(printed.append)
    console("hub: warning: said while building")
    assert console.early and console.early[0][1] == "hub: warning: said while building"
    console.record_to(None)
    for n in range(3):
        console(f"hub: line {n}")
    assert console.early is None and printed[-1] == "hub: line 2"


@pytest.mark.parametrize("up_axis, bodies, warned", [
    ("y", "kh0(0,0,0.05,1,0,0,0);kh1(0,0.4,0.05,1,0,0,0)", True),     # Z-up positions read as Y-up: one spot
    ("z", "kh0(0,0,0.05,1,0,0,0);kh1(0,0.4,0.05,1,0,0,0)", False)])
def test_two_robots_on_one_spot_make_the_hub_ask_about_up_axis(up_axis, bodies, warned):
    """A wrong up_axis put robots on top of each other and the hub served it without a word."""
    with HubThread(mock_config(bodies, up_axis=up_axis)) as hub:
        deadline = time.monotonic() + (5.0 if warned else 2.5)
        while time.monotonic() < deadline and not any("apart on the floor" in line for line in hub.lines):
            time.sleep(0.05)
        said = [line for line in hub.lines if "apart on the floor" in line]
    if warned:
        assert said == ["hub: warning: robots 0 and 1 are 0.00 m apart on the floor, closer than two robots can "
                        "be: is source.up_axis (y) right for this system (z: Vicon, Qualisys; y: OptiTrack "
                        "Motive's default), and is each body its own robot in source.bodies?"], hub.lines
    else:
        assert said == [], said
