"""Lockstep pacing for the ``sim`` source: one control step of physics only after every live agent answered.

Each step: snapshot the world (faults, poses, IR, odometry) -> virtual sensors -> one frame to every agent,
all built and sent in one batch -> wait until each expected agent's telemetry answers that frame (wheel
commands and broadcasts arrive before it on the same socket) or the wall-clock timeout passes -> advance
physics by one control period. A dead or hung agent costs at most the timeout per step, and after three
silent steps it is no longer waited for (until it answers again). The agents run their normal loop; only
their pacing follows the frames.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Set, Tuple

import zmq

from .server import Hub
from .sim_source import SimSource

UNRESPONSIVE_AFTER_STEPS = 3


@dataclass
class StepReport:
    time_s: float
    answered: List[int] = field(default_factory=list)
    missing: List[int] = field(default_factory=list)
    round_trip_s: List[float] = field(default_factory=list)   # frame sent -> answer received, per agent


class Lockstep:
    def __init__(self, hub: Hub, timeout_s: float = 2.0):
        if not isinstance(hub.source, SimSource):
            raise TypeError("lockstep needs the sim source")
        self.hub, self.source, self.timeout_s = hub, hub.source, timeout_s
        self.poller = zmq.Poller()
        self.poller.register(hub.robot_socket, zmq.POLLIN)
        self.poller.register(hub.control_socket, zmq.POLLIN)
        self.steps = 0
        self.timeouts = 0

    def expected(self, now: float) -> List[int]:
        """Agents this step waits for: connected, alive in the world, not written off as unresponsive."""
        hub = self.hub
        return [r.id for r in hub.robots.values()
                if r.routing is not None and r.id not in hub.killed and r.unresponsive_steps < UNRESPONSIVE_AFTER_STEPS]

    def step(self) -> StepReport:
        hub, source = self.hub, self.source
        now = time.monotonic()
        frame = source.snapshot(now)
        hub.on_pose_frame(frame)
        report = StepReport(frame.clock_s or 0.0)
        # One batch: the sensor part of every frame in one vectorised pass (Hub.send_frames). A frame counts as
        # sent once the whole batch is out, so a round trip never includes time before its frame left.
        # Who must answer is settled before the send: an agent whose connection failed in it is waited for.
        waiting = set(self.expected(now))
        connected = [robot for robot in hub.robots.values() if robot.routing is not None]
        if connected:
            hub.send_frames(connected, time.monotonic())
        sent = time.monotonic()
        sent_at = {robot.id: (sent, robot.seq, robot.routing) for robot in connected}
        deadline = time.monotonic() + self.timeout_s
        while waiting and time.monotonic() < deadline:
            events = dict(self.poller.poll(max(0.0, deadline - time.monotonic()) * 1000.0))
            hub.handle_sockets(events)
            self._resend_to_reconnected(waiting, sent_at)
            for rid in list(waiting):
                robot = hub.robots[rid]
                if rid in sent_at and robot.step_answered >= sent_at[rid][1]:
                    waiting.discard(rid)
                    report.answered.append(rid)
                    report.round_trip_s.append(time.monotonic() - sent_at[rid][0])
                    robot.unresponsive_steps = 0
        for rid in waiting:
            robot = hub.robots[rid]
            if robot.unresponsive_steps == 0:    # the agent's step for this frame is the one that hangs
                robot.silent_since, robot.silent_since_clock_s = sent, report.time_s
            robot.unresponsive_steps += 1
            report.missing.append(rid)
        if waiting:
            self.timeouts += 1
        hub.housekeeping(time.monotonic())
        self.steps += 1
        return report

    def _resend_to_reconnected(self, waiting: Set[int], sent_at: Dict[int, Tuple[float, int, Any]]) -> None:
        """An agent that reopened its connection while its frame was on the way lost that frame (its agent counts
        it lost): it gets this step's frame again on the new connection, or it could not answer the step."""
        for rid in waiting:
            robot = self.hub.robots[rid]
            if robot.routing is not None and (rid not in sent_at or sent_at[rid][2] != robot.routing):
                self.hub.send_frames([robot], time.monotonic())
                sent_at[rid] = (time.monotonic(), robot.seq, robot.routing)

    def advance(self) -> None:
        self.source.advance(self.source.substeps_per_control)

    def wait_for(self, condition, timeout_s: float, what: str) -> Optional[str]:
        """Serve sockets until ``condition()``; None when met, else a one-line reason."""
        deadline = time.monotonic() + timeout_s
        while not condition():
            left = deadline - time.monotonic()
            if left <= 0:
                return f"timed out after {timeout_s:g} s waiting for {what}"
            events = dict(self.poller.poll(min(left, 0.05) * 1000.0))
            self.hub.handle_sockets(events)
            self.hub.housekeeping(time.monotonic())
        return None
