"""The hub's downlink: sensor frames and commands out to the robots' agents (docs/protocol.md).

A mixin of :class:`~.server.Hub`, split out so that ``server.py`` reads as the loop and what it reacts to;
these methods read the hub's state (poses, sensors, relay, modes) and never change it beyond the robots'
send bookkeeping (``seq``, ``next_due``, ``pending``).
"""
from __future__ import annotations

import time
from typing import Any, Dict, List, Optional

import numpy as np
import zmq

from onboard.protocol import (
    FRAME_HEADER,
    MAX_MESSAGE_BYTES,
    MODE_CODES,
    NEIGHBOUR_DTYPE,
    ProtocolError,
    encode,
    frame_tail,
    pack_frame,
)

from .links import RobotLink
from .log_format import robot_topic
from .sensors import FrameBatch

COMMAND_RETRY_S = 0.25    # an unacknowledged command is sent again this often
TAIL_SLACK_BYTES = 1024   # room kept in a frame for reason and sim beside the relayed messages
_SEND_MORE = int(zmq.NOBLOCK | zmq.SNDMORE)   # plain ints: combining the flag enums costs a microsecond a send
_SEND_LAST = int(zmq.NOBLOCK)


class Downlink:
    def send_due(self, now: float, fresh: bool) -> None:
        """Frames to robots whose turn has come: right after a fresh pose frame, or as a heartbeat when
        motion capture is late by half a period (so agents' watchdogs see a live hub either way). With motion
        capture slower than the downlink, every robot's turn comes with every pose frame."""
        downlink_hz = self.config.network.downlink_hz
        period = 1.0 / downlink_hz
        if fresh and self.mocap_rate.hz < downlink_hz:
            # Motion capture slower than the downlink: each pose frame goes to every robot at once. Spread over
            # the robots' turns (which keeps the bursts of a 120 Hz system small) its pose would reach some
            # robots up to one and a half downlink periods late.
            due = [r for r in self.robots.values() if r.routing is not None]
        else:
            slack = 0.0 if fresh else period / 2.0
            due = [r for r in self.robots.values() if r.routing is not None and now >= r.next_due + slack]
        if not due:
            return
        self.send_frames(due, now)
        for robot in due:
            robot.next_due += period
            if robot.next_due <= now:
                robot.next_due = now + period

    def send_frame(self, robot: RobotLink, now: float) -> None:
        self.send_frames([robot], now)

    def send_frames(self, robots: List[RobotLink], now: float) -> None:
        """One frame to each of ``robots``, in that order. The sensor part of all of them is built in one
        vectorised pass (:meth:`VirtualSensors.frames`); each frame is then a header pack, a slice of the
        neighbour records and, only when it carries messages, a reason or sim readings, a small JSON tail
        (docs/protocol.md). Nothing per neighbour happens in Python, and recording waits until all are sent."""
        batch = self.sensors.frames([robot.id for robot in robots])
        clock_s, stamp = self.clock_s, self.last_frame_stamp
        ages = np.maximum(now - self.seen_at.take(batch.rows), 0.0).tolist()
        recording = self.recorder is not None
        for k, robot in enumerate(robots):
            mode, reason = self.mode_for(robot)
            tail: Dict[str, Any] = {}
            if self.relay.pending(robot.id):
                budget = MAX_MESSAGE_BYTES - FRAME_HEADER.size - TAIL_SLACK_BYTES \
                    - NEIGHBOUR_DTYPE.itemsize * batch.count(k)
                messages = self.relay.take(robot.id, budget)
                if messages:
                    tail["messages"] = messages
            if reason:
                tail["reason"] = reason
            extra = self.extras.get(robot.id)
            if extra is not None:
                tail["sim"] = extra
            robot.seq += 1
            present = batch.present[k]
            hub_t = stamp if present else now
            age = ages[k] if present else 0.0
            try:
                data = pack_frame(robot.seq, MODE_CODES[mode], hub_t, age, batch.poses[k], batch.block(k),
                                  frame_tail(tail) if tail else b"", clock_s)
            except ProtocolError as err:
                self.drops.drop("unencodable downlink", f"robot {robot.id}", str(err))
                continue
            if self._send(robot, data) and recording:
                self.recorder.write_later(robot_topic(robot.id, "frame"), frame_record,
                                          (robot.seq, mode, hub_t, age, batch, k, tail, clock_s))
        if recording:
            self.recorder.kick()    # encode and write them now, in the recorder's thread
        self.sensors.refill()       # the next burst's noise, drawn now that this one is out

    def send_to(self, robot: RobotLink, message: Dict[str, Any], topic: str) -> bool:
        try:
            data = encode(message)
        except ProtocolError as err:
            self.drops.drop("unencodable downlink", f"robot {robot.id}", str(err))
            return False
        if not self._send(robot, data):
            return False
        if self.recorder is not None:
            self.recorder.write(robot_topic(robot.id, topic), message)
        return True

    def _send(self, robot: RobotLink, data: bytes) -> bool:
        sock = self.robot_socket
        try:
            sock.send(robot.routing, _SEND_MORE)
            sock.send(data, _SEND_LAST)
        except zmq.Again:
            robot.frames_dropped += 1      # the agent is not reading: drop rather than queue stale data
            self.drops.count("downlink queue full", f"robot {robot.id}")     # in status and /hub/drops
            return False
        except zmq.ZMQError:               # EHOSTUNREACH: the agent's connection is gone
            robot.routing = None
            return False
        return True

    def send_command_to_all(self, cmd: str, reason: str = "") -> None:
        for robot in self.robots.values():
            if robot.routing is not None:
                self.send_command(robot, cmd, reason)
            else:   # an older command waiting for a robot away (a run's start) is stale now: its hello gets
                robot.pending = None    # what holds then (a start of an ended run was re-sent to a new agent)

    def send_command(self, robot: RobotLink, cmd: str, reason: str = "") -> None:
        message: Dict[str, Any] = {"type": "command", "cmd": cmd}
        if cmd == "start":
            message["run"] = self.run.message(self.run_id or "")
        if reason:
            message["reason"] = reason
        robot.pending = message
        robot.pending_sent_at = time.monotonic()
        self.send_to(robot, message, topic="command")

    def resend_unacknowledged(self, now: float) -> None:
        """A send never blocks, so a command can be dropped (a full queue, a reconnecting agent): one the agent
        has not acknowledged goes again every COMMAND_RETRY_S until it is."""
        for robot in self.robots.values():
            if robot.pending is not None and robot.routing is not None \
                    and now - robot.pending_sent_at > COMMAND_RETRY_S:
                robot.pending_sent_at = now
                self.send_to(robot, robot.pending, topic="command")


def frame_record(seq: int, mode: str, hub_t: float, age: float, batch: FrameBatch, k: int, tail: Dict[str, Any],
                 clock_s: Optional[float]) -> Dict[str, Any]:
    """``/robot/<id>/frame``: the frame as the agent decodes it (docs/recording.md), without ``v``."""
    pose = batch.poses[k]
    record: Dict[str, Any] = {"type": "frame", "seq": seq, "mode": mode, "hub_t": hub_t,
                              "pose": None if pose is None else list(pose), "pose_age_s": age,
                              "neighbours": batch.neighbours(k), "messages": []}
    if clock_s is not None:
        record["clock_s"] = clock_s
    record.update(tail)
    return record
