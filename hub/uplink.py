"""The hub's uplink: what the robots' agents send (hello, telemetry, broadcasts, wheel commands, acks).

A mixin of :class:`~.server.Hub`, like :class:`~.downlink.Downlink`. :meth:`Uplink.handle_uplink` checks one
message (its framing, its claimed robot id against the connection's CURVE key, a rival connection for the
same robot) and hands it to the ``_on_<type>`` handler of its type.
"""
from __future__ import annotations

import math
import time
from typing import Any, Dict, List, Optional

import zmq

from onboard.protocol import UPLINK_TYPES, ProtocolError, check_payload_size, decode

from .links import VIRTUAL_DRIVERS, RobotLink, frame_property, frame_sender
from .log_format import robot_topic

DUPLICATE_WARNING_S = 30.0     # a robot id claimed by two live connections is said this often
# A robot whose agent said nothing for this long (or watchdog_s, if longer) is said to be silent. A shorter gap
# (a Wi-Fi hiccup) shows in `ctl status` only: a line for each would flood the console on a flaky network.
SILENT_LOG_S = 1.0
# The hub's loop turns at every pose frame (120 Hz and more): a second of silence needs no look at every robot
# each time round, and the look costs the loop about 0.02 ms at 100 robots.
SILENCE_CHECK_PERIOD_S = 0.1


class Uplink:
    silence_checked_at = -math.inf      # when say_silent_robots last looked

    def handle_uplink(self, parts: List[zmq.Frame]) -> None:
        now = time.monotonic()
        if len(parts) != 2:
            sender = frame_sender(parts[-1], "peer")
            self.drops.drop("malformed message", sender, f"{len(parts) - 1} frames from {sender}, expected 1")
            return
        routing, body = parts
        user, peer = frame_property(body, "User-Id"), frame_property(body, "Peer-Address")
        sender = frame_sender(body, "peer")
        try:
            message = decode(body.bytes, sender, accept=UPLINK_TYPES)
        except ProtocolError as err:
            self.drops.drop("bad message", sender, str(err))
            return
        rid = message["id"]
        if self.keyring is not None and user != f"robot:{rid}":
            self.drops.drop("id mismatch", sender, f"{sender} claimed to be robot {rid}")
            return
        robot = self.robots.get(rid)
        if robot is None:
            self.drops.drop("unknown robot", sender, f"{sender} claimed robot {rid}, which is not in this lab")
            return
        if self._speaks_for(robot, routing.bytes, peer, sender, message.get("agent"), now):
            robot.last_uplink = now
            getattr(self, f"_on_{message['type']}")(robot, message, now)

    def _speaks_for(self, robot: RobotLink, routing: bytes, peer: Optional[str], sender: str, agent: Optional[str],
                    now: float) -> bool:
        """Whether this connection holds the robot: the one that does, a new one once it is silent (or at once
        for its own agent's reconnect), not a rival while it is alive, nor the connection its agent replaced."""
        if robot.routing == routing:
            if robot.silence_said:
                self.log(f"hub: robot {robot.id} is back after {now - robot.last_uplink:.1f} s of silence")
                robot.silence_said = False
            return True
        if routing == robot.replaced_routing:
            return False          # still in flight on the connection its agent has just replaced: stale
        same_agent = agent is not None and agent == robot.agent
        if robot.connected(now, self.config.watchdog_s) and not same_agent:
            self._rival(robot, peer, sender, now)
            return False
        self._connected(robot, routing, peer, now, agent, same_agent)
        return True

    def _connected(self, robot: RobotLink, routing: bytes, peer: Optional[str], now: float, agent: Optional[str],
                   same_agent: bool) -> None:
        """A connection takes the robot: a new agent's, or the robot's own agent's new one (``same_agent``: it
        reopened its socket, or ZeroMQ reconnected it), which takes over at once even while the old one looks
        alive, and whose old connection is then ignored."""
        robot.replaced_routing = robot.routing if same_agent else None
        robot.routing, robot.peer, robot.agent = routing, peer or "", agent
        robot.silence_said = False          # this line says it is back
        index = self.ids.index(robot.id)
        robot.next_due = now + (index / max(1, len(self.ids))) / self.config.network.downlink_hz  # spread sends
        if same_agent:
            self.log(f"hub: robot {robot.id}'s agent reconnected from {robot.peer or '?'}")
        else:
            # A new agent during a run starts it afresh: a restarted one knows nothing of its old self (for the
            # transport, it stays a spare). The operator saw only "connected" and the robot driving again.
            joins = (f": it joins run {self.run_id} with a new behaviour (it knows nothing of the run so far)"
                     if self.mode == "run" and self.run_id is not None else "")
            self.log(f"hub: robot {robot.id} connected from {robot.peer or '?'}{joins}")

    def _rival(self, robot: RobotLink, peer: Optional[str], sender: str, now: float) -> None:
        """A second connection speaks for a robot whose connection is alive (two agents started with one --id,
        or one robot key copied twice). The first keeps the robot, frames and wheels, until it is silent for
        watchdog_s; the other's messages are dropped. Switching on every message instead would hand the frames
        back and forth, and the agents' wheels with them. Said once every DUPLICATE_WARNING_S, and only once the
        first connection spoke after the second appeared: an agent too old to send its token (``agent``) that
        reconnects leaves its old one silent."""
        self.drops.count("duplicate robot", sender)
        if now - robot.rival_seen > self.config.watchdog_s:
            robot.rival_since = now            # a new contest
        robot.rival_seen = now
        if robot.last_uplink <= robot.rival_since or now - robot.rival_warned < DUPLICATE_WARNING_S:
            return
        robot.rival_warned = now
        self.log(f"hub: robot {robot.id} is claimed by two connections: {robot.peer or '?'} (first, keeps the "
                 f"robot) and {peer or '?'} (ignored while the first is alive); is a second agent running with "
                 f"--id {robot.id}?")

    def say_silent_robots(self, now: float) -> None:
        """One line when a robot that was connected goes silent (its agent died, or its Wi-Fi dropped), and one
        when it speaks again (``handle_uplink``): `ctl status` showed it as not connected, but nobody watching the
        hub's console learnt that a robot had stopped."""
        if now - self.silence_checked_at < SILENCE_CHECK_PERIOD_S or self.run.lockstep:
            return      # lockstep: an agent is quiet while the hub waits for a slower one (sil names one stuck)
        self.silence_checked_at = now
        quiet_s = max(SILENT_LOG_S, self.config.watchdog_s)
        for robot in self.robots.values():
            heard = robot.last_uplink > -math.inf
            if heard and not robot.silence_said and now - robot.last_uplink > quiet_s:
                robot.silence_said = True
                self.log(silence_line(robot, quiet_s))

    def _note_driver(self, robot: RobotLink, driver: str) -> None:
        """A real robot's agent talking to a hub that simulates that robot drives real wheels the hub never
        sees, while the simulated robot stands still: almost surely a mistake, so say it when it starts."""
        if driver != robot.driver and driver not in VIRTUAL_DRIVERS and self.source.not_the_real_robots:
            self.log(f"hub: robot {robot.id}'s agent uses the {driver} driver, but {self.source.not_the_real_robots}"
                     f" ({self.source.description}): it is held, its wheels stopped, so that it does not drive by "
                     f"poses that do not follow it; for a simulated robot start the agent with --driver sim")
        robot.driver = driver

    def _on_hello(self, robot: RobotLink, message: Dict[str, Any], now: float) -> None:
        self._note_driver(robot, message["driver"])
        robot.run_id = message.get("run_id")
        if self.run_id is not None and robot.run_id != self.run_id and self.mode != "idle":
            self.send_command(robot, "start")          # a late or restarted agent joins the current run
        elif self.mode == "estop":
            self.send_command(robot, "estop", "operator e-stop")
        elif self.run_id is None and robot.run_id is not None:
            self._stop_unknown_run(robot)                   # e.g. the hub restarted mid-run

    def _stop_unknown_run(self, robot: RobotLink) -> None:
        """An agent in a run this hub never started (the hub was restarted mid-run): stopped, and said once per
        run. The new hub's console said only that robots connected, and its log had no trace of the run. An
        agent still in a run this hub has ended (it reconnected as the run ended) is only told to stop."""
        if robot.run_id not in self.unknown_runs_said and robot.run_id not in self.runs_started:
            self.unknown_runs_said.add(robot.run_id)
            self.log(f"hub: robot {robot.id} was in run {robot.run_id}, which this hub did not start (was the hub "
                     "restarted during it?): its robots are told to stop. With real robots the object is where "
                     "that run left it, not at the mission's start: check the run's params before `ctl start`")
        self.send_command(robot, "stop", "the hub has no run")

    def _on_telemetry(self, robot: RobotLink, message: Dict[str, Any], now: float) -> None:
        error = message.get("error")
        if error and error != (robot.telemetry or {}).get("error"):
            # Said once per new error at the operator's console (a crash, a run it cannot start), not only in
            # `ctl status`: the robot has stopped, and the operator should not have to poll to learn why.
            self.log(f"hub: robot {robot.id}: {error}")
        robot.telemetry = message
        robot.step_answered = message["step"]
        robot.run_id = message.get("run_id", robot.run_id)
        self._note_driver(robot, message.get("driver", robot.driver))
        if robot.run_id is not None and robot.run_id != self.run_id and robot.pending is None:
            # An agent that holds a run this hub did not start: the hub restarted while it was running. Its
            # hellos were lost while it reconnected, and a connected agent says no more hellos, so its
            # telemetry is where the hub learns it (a command already in flight is retried on its own).
            if self.run_id is None:
                self._stop_unknown_run(robot)
            elif self.mode != "idle":
                self.send_command(robot, "start")
        if self.recorder is not None:
            self.recorder.write(robot_topic(robot.id, "telemetry"), message)

    def _on_broadcast(self, robot: RobotLink, message: Dict[str, Any], now: float) -> None:
        payload = message["payload"]
        size = check_payload_size(payload)
        receivers = self.sensors.receivers_of(robot.id) if self.mode_for(robot)[0] == "run" else []
        if not self.relay.submit(robot.id, message["sent_s"], payload, size, receivers):
            # Its behaviour is not told (a broadcast has no answer): the line names the robot and the limit.
            self.drops.drop("refused broadcast", f"robot {robot.id}",
                            f"robot {robot.id}'s broadcast of {size} bytes, over relay.max_bytes "
                            f"({self.relay.max_bytes}); its behaviour is not told", key="over relay.max_bytes")
        elif self.recorder is not None:
            self.recorder.write(robot_topic(robot.id, "broadcast"), message)
            self.recorder.write(robot_topic(robot.id, "relay"), {"receivers": receivers})

    def _on_wheels(self, robot: RobotLink, message: Dict[str, Any], now: float) -> None:
        command = getattr(self.source, "command", None)
        if command is None:
            return
        allowed = self.mode_for(robot)[0] == "run"
        command(robot.id, message["left"] if allowed else 0.0, message["right"] if allowed else 0.0)
        if self.recorder is not None:
            self.recorder.write(robot_topic(robot.id, "wheels"), message)   # not /command: that is the operator's

    def _on_ack(self, robot: RobotLink, message: Dict[str, Any], now: float) -> None:
        if robot.pending is not None and robot.pending["cmd"] == message["cmd"]:
            robot.pending = None
        if message["cmd"] == "estop" and self.estop_at is not None and robot.estop_ack_s is None:
            robot.estop_ack_s = now - self.estop_at


def silence_line(robot: RobotLink, quiet_s: float) -> str:
    """Why a robot went quiet, as far as the hub knows: an agent that said goodbye (its last telemetry's mode is
    ``exiting``: stopped with Ctrl-C, SIGTERM or SIGHUP, or crashed) left; any other just stopped talking."""
    if (robot.telemetry or {}).get("mode") == "exiting":
        return f"hub: robot {robot.id}'s agent has exited (its last message said so)"
    return (f"hub: robot {robot.id} went silent: no message from its agent at {robot.peer or '?'} for {quiet_s:g} s "
            f"(did the agent stop, or its network drop?)")
