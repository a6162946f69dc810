"""The agent's HAL: devices fed by hub frames (pose, neighbours, radio, clock) and by the driver (IR, wheels,
encoders). A behaviour gets the same :class:`onboard.hal.Robot` bundle as in the simulator.
"""
from __future__ import annotations

import dataclasses
import json
import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Deque, Dict, List, Mapping, Optional

from onboard import hal
from onboard.drivers import Driver
from onboard.hal import Message, Neighbours, Pose, ProximityReading, RobotSpec, WheelOdometry, commanded_wheel_speeds
from onboard.hal.payload import plain_payload

INBOX_LIMIT = hal.Radio.INBOX_LIMIT    # relayed messages kept between two behaviour steps; the oldest go first


@dataclass
class HubState:
    """The latest hub frame, as the devices read it. Times are the robot's clock (``AgentClock``)."""

    seq: int = 0
    mode: str = "idle"
    reason: str = ""
    received_at: float = -math.inf          # local monotonic time of the last frame
    pose: Optional[Pose] = None
    neighbours: Neighbours = field(default_factory=lambda: Neighbours([], [], []))
    neighbours_at: float = 0.0              # robot-clock time the neighbours were measured
    hub_clock_s: Optional[float] = None
    sim: Optional[Dict[str, Any]] = None    # IR and odometry from the hub's sim source
    sim_first: Optional[Dict[str, Any]] = None   # the first frame's: where the sim driver's encoders count from
    inbox: Deque[Message] = field(default_factory=lambda: deque(maxlen=INBOX_LIMIT))
    frames_lost: int = 0
    inbox_dropped: int = 0                  # relayed messages pushed out of a full inbox before a step read them


class AgentClock(hal.Clock):
    """Seconds since the run started: local monotonic time, or the hub's simulated time in lockstep."""

    def __init__(self, state: HubState):
        self.state = state
        self.use_hub_clock = False
        self.started = time.monotonic()

    def restart(self, use_hub_clock: bool) -> None:
        """A new run's clock, from 0. The pose and neighbours of the last frame keep their age: stamped on the old
        run's clock they lay in the new one's future, where an age clamped to 0 made a pose minutes old (the
        motion capture lost the robot before the run) read as fresh."""
        before = self.now()
        self.use_hub_clock = use_hub_clock
        self.started = time.monotonic()
        shift = self.now() - before
        state = self.state
        if state.pose is not None:
            state.pose = dataclasses.replace(state.pose, stamp_s=state.pose.stamp_s + shift)
        state.neighbours_at += shift

    def now(self) -> float:
        if self.use_hub_clock:
            return self.state.hub_clock_s if self.state.hub_clock_s is not None else 0.0
        return time.monotonic() - self.started


def apply_frame(state: HubState, frame: Dict[str, Any], clock: AgentClock, received_at: float) -> None:
    """Fold one downlink frame into the state (messages accumulate; everything else is latest-only).
    The frame's mode is applied by the agent, which must act on a change (stop the wheels). ``neighbours`` is
    either the decoder's columns ``(ids, ranges_m, bearings_rad)``, used as they are, or a list of rows."""
    if state.seq and frame["seq"] > state.seq + 1:
        state.frames_lost += frame["seq"] - state.seq - 1
    state.seq = frame["seq"]
    state.received_at = received_at
    state.hub_clock_s = frame.get("clock_s", state.hub_clock_s)
    state.sim = frame.get("sim", state.sim)
    if state.sim_first is None:
        state.sim_first = state.sim
    now = clock.now()
    # In lockstep the pose belongs to the frame's simulated instant; in real time it is age_s old on arrival.
    measured = now if clock.use_hub_clock else now - frame.get("pose_age_s", 0.0)
    pose = frame.get("pose")
    if pose is not None:
        state.pose = Pose(pose[0], pose[1], pose[2], measured)
    neighbours = frame["neighbours"]
    if isinstance(neighbours, tuple):        # the decoder's columns (HubLink decodes with neighbour_columns)
        state.neighbours = Neighbours(*neighbours)
    else:                                    # [[id, range_m, bearing_rad], ...]
        state.neighbours = Neighbours([n[0] for n in neighbours], [n[1] for n in neighbours],
                                      [n[2] for n in neighbours])
    for column in (state.neighbours.ids, state.neighbours.ranges_m, state.neighbours.bearings_rad):
        column.flags.writeable = False       # as in the simulator: a behaviour writing into them gets an error
    state.neighbours_at = measured
    inbox = state.inbox
    for sender, sent_s, payload in frame["messages"]:
        if len(inbox) == INBOX_LIMIT:
            state.inbox_dropped += 1            # the deque drops the oldest itself; count it
        inbox.append(Message(sender, payload, sent_s))


class HubPositioning(hal.Positioning):
    def __init__(self, state: HubState, clock: AgentClock):
        self.state, self.clock = state, clock

    def pose(self) -> Optional[Pose]:
        p = self.state.pose
        if p is None:
            return None
        return Pose(p.x, p.y, p.yaw_rad, p.stamp_s, max(0.0, self.clock.now() - p.stamp_s))


class HubRangeAndBearing(hal.RangeAndBearingSensor):
    def __init__(self, state: HubState, clock: AgentClock):
        self.state, self.clock = state, clock

    def neighbours(self) -> Neighbours:
        age = max(0.0, self.clock.now() - self.state.neighbours_at)
        table = self.state.neighbours        # the frame's columns, shared: records are made only if asked for
        return Neighbours(table.ids, table.ranges_m, table.bearings_rad, age, table.xy)


class HubRadio(hal.Radio):
    """Broadcasts go to the hub at once; the hub relays them to the robots within d_C."""

    def __init__(self, state: HubState, clock: AgentClock, send: Callable[[Dict[str, Any]], bool], robot_id: int):
        self.state, self.clock, self.send, self.robot_id = state, clock, send, robot_id

    def broadcast(self, payload: Mapping[str, Any]) -> None:
        # The same checks as the simulator's radio, so a behaviour fails the same way in both.
        if not isinstance(payload, Mapping):
            raise TypeError(f"radio payload must be a mapping, got {type(payload).__name__}")
        plain = plain_payload(payload)            # names a field JSON cannot carry, as the simulator does
        size = len(json.dumps(plain, separators=(",", ":")))
        if size > self.MAX_PAYLOAD_BYTES:
            raise ValueError(f"radio payload of {size} bytes exceeds {self.MAX_PAYLOAD_BYTES}")
        self.send({"type": "broadcast", "payload": plain, "sent_s": round(self.clock.now(), 6)})

    def receive(self) -> List[Message]:
        messages = list(self.state.inbox)
        self.state.inbox.clear()
        return messages


class DriverWheels(hal.DifferentialSteering):
    def __init__(self, driver: Driver, spec: RobotSpec):
        self.driver, self.spec = driver, spec
        self.left = self.right = 0.0

    def set_speeds(self, left_m_s: float, right_m_s: float) -> None:
        self.left, self.right = commanded_wheel_speeds(left_m_s, right_m_s, self.spec.max_wheel_speed_m_s)
        self.driver.set_wheel_speeds(self.left, self.right)


class DriverProximity(hal.ProximitySensor):
    def __init__(self, driver: Driver):
        self.driver = driver

    def read(self) -> ProximityReading:
        return ProximityReading(values=tuple(float(v) for v in self.driver.proximity()))


class DriverOdometry(hal.Odometry):
    def __init__(self, driver: Driver):
        self.driver = driver

    def read(self) -> WheelOdometry:
        return self.driver.encoders()


def make_robot(robot_id: int, state: HubState, clock: AgentClock, driver: Driver,
               send: Callable[[Dict[str, Any]], bool], spec: RobotSpec) -> hal.Robot:
    return hal.Robot(
        id=robot_id,
        proximity=DriverProximity(driver),
        range_and_bearing=HubRangeAndBearing(state, clock),
        radio=HubRadio(state, clock, send, robot_id),
        wheels=DriverWheels(driver, spec),
        odometry=DriverOdometry(driver),
        positioning=HubPositioning(state, clock),
        clock=clock,
        spec=spec,
    )
