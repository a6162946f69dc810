"""The hub: poses in, virtual sensor frames and relayed radio out, operator control, safety.

Sockets (docs/protocol.md): a ROUTER for the robots' DEALERs (downlink frames and commands, uplink
telemetry, broadcasts, wheel commands) and a ROUTER for ``khepri ctl``. One thread runs everything here;
only a motion-capture reader runs beside it (``hub/sources.py``).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np
import zmq

from onboard.config import ConfigError
from onboard.protocol import MAX_MESSAGE_BYTES, UPLINK_TYPES, ProtocolError, check_payload_size, decode

from .config import LabConfig
from .control_service import ControlService
from .downlink import Downlink
from .links import DropLog, RateMeter, RobotLink
from .recording import BackgroundRecorder, robot_topic
from .relay import RadioRelay
from .security import OPERATOR_DOMAIN, ROBOT_DOMAIN, HubAuthenticator, KeyRing, make_curve_server
from .sensors import SensingModel, VirtualSensors
from .sources import PoseFrame, PoseSource

DOWNLINK_HWM = 8          # frames queued per robot; older data is useless, a full queue drops (latest-only)
UPLINK_SLICE = 16         # uplink messages read between two looks for a waiting pose frame
MOCAP_SILENT_S = 1.0      # warn when no pose frame arrived for this long
DUPLICATE_WARNING_S = 30.0     # a robot id claimed by two live connections is said this often
NO_POSE_YET_WARNING_S = 2.0    # warn when no frame has placed a robot this long after start...
NO_POSE_YET_REPEAT_S = 30.0    # ...and again this often while none does


@dataclass
class RunTemplate:
    """What ``start`` sends every agent: the behaviour, its parameters and how to pace it."""

    behaviour: str
    params: Dict[str, Any]
    control_hz: float = 10.0
    lockstep: bool = False
    spec: Dict[str, float] = field(default_factory=dict)
    seed: Optional[int] = None      # each agent seeds its `random` from it and its id (reproducible SIL runs)

    def message(self, run_id: str) -> Dict[str, Any]:
        message = {"run_id": run_id, "behaviour": self.behaviour, "params": self.params,
                   "control_hz": self.control_hz, "lockstep": self.lockstep,
                   "clock": "hub" if self.lockstep else "local", "spec": self.spec}
        if self.seed is not None:
            message["seed"] = self.seed
        return message


class Hub(Downlink):
    def __init__(self, config: LabConfig, source: PoseSource, robot_ids: List[int], run: RunTemplate,
                 sensing: SensingModel, relay_drop: float, seed=None, keyring: Optional[KeyRing] = None,
                 recorder=None, log: Callable[[str], None] = print, context: Optional[zmq.Context] = None):
        if recorder is not None and not isinstance(recorder, BackgroundRecorder):
            recorder = BackgroundRecorder(recorder)     # the loop only queues; a thread of its own writes
        self.config, self.source, self.run, self.keyring, self.recorder, self.log = \
            config, source, run, keyring, recorder, log
        self.context = context or zmq.Context.instance()
        rng = np.random.default_rng(seed)
        self.ids = list(robot_ids)
        self.robots: Dict[int, RobotLink] = {rid: RobotLink(rid) for rid in self.ids}
        self.row = {rid: i for i, rid in enumerate(self.ids)}
        self.sensors = VirtualSensors(self.ids, sensing, rng)
        self.relay = RadioRelay(self.ids, relay_drop, config.relay.queue, config.relay.max_bytes, rng)
        self.drops = DropLog(log, on_drop=self._record_drop)
        self.poses = np.zeros((len(self.ids), 3))
        self.seen_at = np.full(len(self.ids), -math.inf)
        self.outside_fence = np.zeros(len(self.ids), dtype=bool)
        self.killed: set = set()
        self.extras: Dict[int, Dict[str, Any]] = {}
        self.clock_s: Optional[float] = None
        self.last_frame_stamp = -math.inf
        self.mocap_rate = RateMeter()
        self.mocap_silent = False
        self.placed_a_robot = False       # some frame has held a pose for one of this lab's robots
        self.mode = "idle"
        self.run_id: Optional[str] = None
        self.estop_at: Optional[float] = None
        self.started_at = time.monotonic()
        self._next_no_pose_warning = self.started_at + NO_POSE_YET_WARNING_S
        self.control = ControlService(self)
        self.authenticator: Optional[HubAuthenticator] = None
        self.robot_socket: Optional[zmq.Socket] = None
        self.control_socket: Optional[zmq.Socket] = None
        self.endpoints: Dict[str, str] = {}
        self._next_status_record = 0.0
        self._frame_ids: Optional[List[int]] = None
        self._frame_rows: Tuple[np.ndarray, Optional[List[int]]] = (np.zeros(0, dtype=np.intp), None)

    # --- sockets --------------------------------------------------------------------------------------
    def bind(self) -> Dict[str, str]:
        """Bind both sockets and print ``listening <role> <endpoint>`` for each. Port 0 picks a free port."""
        net = self.config.network
        if self.keyring is not None:
            self.authenticator = HubAuthenticator(self.context, self.keyring, log=self.log)
            self.authenticator.start()
        self.robot_socket = self._router(ROBOT_DOMAIN, net.robot_port, "robot_port")
        self.robot_socket.sndhwm = DOWNLINK_HWM
        self.control_socket = self._router(OPERATOR_DOMAIN, net.control_port, "control_port")
        for role, sock in (("robots", self.robot_socket), ("control", self.control_socket)):
            self.endpoints[role] = sock.getsockopt_string(zmq.LAST_ENDPOINT)
            self.log(f"listening {role} {self.endpoints[role]}")
        return self.endpoints

    def _router(self, domain: str, port: int, port_field: str) -> zmq.Socket:
        sock = self.context.socket(zmq.ROUTER)
        sock.linger = 0
        sock.router_mandatory = 1      # a full or vanished peer raises instead of dropping silently
        sock.rcvhwm = 10_000
        sock.maxmsgsize = MAX_MESSAGE_BYTES + 1024   # ZeroMQ itself cuts off absurd frames before we read them
        if self.keyring is not None:
            make_curve_server(sock, self.keyring, domain)
        bind = self.config.network.bind
        try:
            sock.bind(f"tcp://{bind}:{port if port else '*'}")
        except zmq.ZMQError as err:
            sock.close(0)          # nothing half-open: the caller closes the sockets bound before this one
            raise bind_error(err, bind, port, port_field) from None
        return sock

    def close(self) -> None:
        self.send_command_to_all("stop", reason="hub shutting down")
        for sock in (self.robot_socket, self.control_socket):
            if sock is not None:
                sock.close(0)
        if self.authenticator is not None:
            self.authenticator.stop()
        self.source.close()
        if self.recorder is not None:
            self.recorder.close()

    # --- the real-time loop -----------------------------------------------------------------------------
    def serve(self, should_stop: Callable[[], bool] = lambda: False) -> None:
        """The loop. Control requests first (an e-stop must not wait). With a source whose frames arrive on their
        own (motion capture: it has a wake socket), a waiting pose frame then becomes downlink frames before the
        uplink is read, and uplink reading stops as soon as another pose frame waits. With a source the hub paces
        (sim, replay), uplink comes first, so wheel commands reach the physics before it steps. Recording
        happens after the sends."""
        poller = zmq.Poller()
        poller.register(self.robot_socket, zmq.POLLIN)
        poller.register(self.control_socket, zmq.POLLIN)
        pose_first = self.source.wake_socket is not None
        if pose_first:
            poller.register(self.source.wake_socket, zmq.POLLIN)
        period = 1.0 / self.config.network.downlink_hz
        while not should_stop():
            now = time.monotonic()
            timeout = min(self.source.next_due(now), period / 2.0, 0.05)
            events = dict(poller.poll(max(0.0, timeout) * 1000.0))
            self.handle_control(events)
            if not pose_first:
                self.handle_uplink_events(events)
            frames = self.source.poll(time.monotonic())
            for frame in frames:
                self.on_pose_frame(frame)
            self.send_due(time.monotonic(), fresh=bool(frames))
            if pose_first:
                self.handle_uplink_events(events)
            self.housekeeping(time.monotonic())

    def handle_sockets(self, events: Dict[Any, int], budget: int = 2000) -> None:
        self.handle_control(events, budget)
        self.handle_uplink_events(events, budget)

    def handle_control(self, events: Dict[Any, int], budget: int = 2000) -> None:
        if self.control_socket in events:
            for _ in range(budget):
                try:
                    parts = self.control_socket.recv_multipart(zmq.NOBLOCK, copy=False)
                except zmq.Again:
                    break
                self.control.handle(parts)

    def handle_uplink_events(self, events: Dict[Any, int], budget: int = 2000) -> None:
        if self.robot_socket not in events:
            return
        wake = self.source.wake_socket
        for count in range(budget):
            if wake is not None and count % UPLINK_SLICE == UPLINK_SLICE - 1 \
                    and wake.getsockopt(zmq.EVENTS) & zmq.POLLIN:
                break             # a pose frame waits: serve it first, the rest of the uplink next time round
            try:
                parts = self.robot_socket.recv_multipart(zmq.NOBLOCK, copy=False)
            except zmq.Again:
                break
            self.handle_uplink(parts)

    # --- poses -> sensors -------------------------------------------------------------------------------
    def on_pose_frame(self, frame: PoseFrame) -> None:
        if frame.ids != self._frame_ids:          # usually the same bodies as last time: reuse the row lookup
            self._frame_ids = list(frame.ids)
            rows = [self.row[rid] for rid in frame.ids if rid in self.row]
            keep = None if len(rows) == len(frame.ids) else [k for k, rid in enumerate(frame.ids) if rid in self.row]
            self._frame_rows = (np.asarray(rows, dtype=np.intp), keep)
        rows, keep = self._frame_rows
        self.placed_a_robot = self.placed_a_robot or len(rows) > 0
        self.poses[rows] = frame.poses if keep is None else frame.poses[keep]
        self.seen_at[rows] = frame.stamp
        self.killed = set(frame.killed)
        self.extras = frame.extras
        self.clock_s = frame.clock_s
        self.last_frame_stamp = frame.stamp
        self.mocap_rate.tick(frame.stamp)
        present = frame.stamp - self.seen_at <= self.config.source.stale_s
        for rid in self.killed:
            present[self.row[rid]] = False
        self.sensors.update(self.poses, present)
        self._check_geofence(present)
        self._hold_sim_wheels(frame.stamp)
        if self.recorder is not None:      # encoded by the recorder's thread, after the frames went out
            self.recorder.write_later("/mocap/poses", poses_record, (frame,))

    def _check_geofence(self, present: np.ndarray) -> None:
        fence = self.config.geofence
        if fence is None:
            return
        xmin, ymin, xmax, ymax = fence
        x, y = self.poses[:, 0], self.poses[:, 1]
        outside = present & ((x < xmin) | (x > xmax) | (y < ymin) | (y > ymax))
        for row in np.nonzero(outside & ~self.outside_fence)[0]:
            self.log(f"hub: robot {self.ids[row]} left the geofence at ({x[row]:.2f}, {y[row]:.2f}): stopped")
        self.outside_fence = outside

    def _hold_sim_wheels(self, now: float) -> None:
        """With the sim source the hub is the physics: robots that must not move do not, whatever agents send."""
        command = getattr(self.source, "command", None)
        if command is None:
            return
        for rid, robot in self.robots.items():
            if self.mode_for(robot)[0] != "run" or not robot.connected(now, self.config.watchdog_s):
                command(rid, 0.0, 0.0)

    def mode_for(self, robot: RobotLink) -> Tuple[str, str]:
        """What this robot must do now, and why when it is not the hub's mode."""
        if self.mode == "estop":
            return "estop", "operator e-stop"
        if robot.id in self.killed:
            return "hold", "killed by a scenario fault"
        if self.mode != "run":
            return self.mode, ""
        row = self.row[robot.id]
        if not self.sensors.present[row]:
            return "hold", "not tracked by motion capture"
        if self.outside_fence[row]:
            return "hold", "outside the geofence"
        return "run", ""

    # --- uplink -----------------------------------------------------------------------------------------
    def handle_uplink(self, parts: List[zmq.Frame]) -> None:
        now = time.monotonic()
        if len(parts) != 2:
            self.drops.drop("malformed message", "unknown peer", f"{len(parts) - 1} frames, expected 1")
            return
        routing, body = parts
        user, peer = _property(body, "User-Id"), _property(body, "Peer-Address")
        sender = f"{user or 'peer'} at {peer or '?'}"
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
        if robot.routing != routing.bytes:
            if robot.connected(now, self.config.watchdog_s):
                self._rival(robot, peer, sender, now)
                return
            self._connected(robot, routing.bytes, peer, now)
        robot.last_uplink = now
        getattr(self, f"_on_{message['type']}")(robot, message, now)

    def _connected(self, robot: RobotLink, routing: bytes, peer: Optional[str], now: float) -> None:
        robot.routing, robot.peer = routing, peer or ""
        index = self.ids.index(robot.id)
        robot.next_due = now + (index / max(1, len(self.ids))) / self.config.network.downlink_hz  # spread sends
        self.log(f"hub: robot {robot.id} connected from {robot.peer or '?'}")

    def _rival(self, robot: RobotLink, peer: Optional[str], sender: str, now: float) -> None:
        """A second connection speaks for a robot whose connection is alive (two agents started with one --id,
        or one robot key copied twice). The first keeps the robot, frames and wheels, until it is silent for
        watchdog_s; the other's messages are dropped. Switching on every message instead would hand the frames
        back and forth, and the agents' wheels with them. Said once every DUPLICATE_WARNING_S, and only once the
        first connection spoke after the second appeared: an agent that reconnects leaves its old one silent."""
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

    def _on_hello(self, robot: RobotLink, message: Dict[str, Any], now: float) -> None:
        robot.driver = message["driver"]
        robot.run_id = message.get("run_id")
        if self.run_id is not None and robot.run_id != self.run_id and self.mode != "idle":
            self.send_command(robot, "start")          # a late or restarted agent joins the current run
        elif self.mode == "estop":
            self.send_command(robot, "estop", "operator e-stop")
        elif self.run_id is None and robot.run_id is not None:
            self.send_command(robot, "stop", "the hub has no run")   # e.g. the hub restarted mid-run

    def _on_telemetry(self, robot: RobotLink, message: Dict[str, Any], now: float) -> None:
        robot.telemetry = message
        robot.step_answered = message["step"]
        robot.run_id = message.get("run_id", robot.run_id)
        if self.recorder is not None:
            self.recorder.write(robot_topic(robot.id, "telemetry"), message)

    def _on_broadcast(self, robot: RobotLink, message: Dict[str, Any], now: float) -> None:
        payload = message["payload"]
        size = check_payload_size(payload)
        receivers = self.sensors.receivers_of(robot.id) if self.mode_for(robot)[0] == "run" else []
        if not self.relay.submit(robot.id, message["sent_s"], payload, size, receivers):
            self.drops.drop("refused broadcast", f"robot {robot.id}", f"{size} bytes > relay.max_bytes")
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

    # --- periodic ---------------------------------------------------------------------------------------
    def housekeeping(self, now: float) -> None:
        self.resend_unacknowledged(now)
        self._warn_if_no_pose_yet(now)
        silent = now - self.last_frame_stamp > MOCAP_SILENT_S and self.last_frame_stamp > -math.inf
        if silent != self.mocap_silent:
            self.mocap_silent = silent
            self.log("hub: no motion-capture frame for 1 s: robots without a pose are held" if silent
                     else "hub: motion capture is back")
        if self.recorder is not None and now >= self._next_status_record:
            self._next_status_record = now + 1.0
            self.recorder.write("/hub/status", self.control.status(now))

    def _warn_if_no_pose_yet(self, now: float) -> None:
        """A source that never delivers (no server, wrong host, a log without poses) is said from the start,
        not only once frames stop after a first one. Lockstep frames wait for the agents: nothing to say."""
        if self.placed_a_robot or self.run.lockstep or now < self._next_no_pose_warning:
            return
        self._next_no_pose_warning = now + NO_POSE_YET_REPEAT_S
        after, source = f"{now - self.started_at:.0f} s", self.source.description
        if self.last_frame_stamp == -math.inf:
            self.log(f"hub: no motion-capture frame yet after {after} from {source}")
        else:
            self.log(f"hub: the frames from {source} hold none of this lab's robots yet after {after} "
                     f"(check source.bodies and robots; this lab's robots: {format_ids(self.ids)})")

    def _record_drop(self, reason: str, sender: str) -> None:
        if self.recorder is not None:
            self.recorder.count_drop(reason, sender)


def poses_record(frame: PoseFrame) -> Dict[str, Any]:
    """``/mocap/poses`` in the recorder's schema: robot id -> [x, y, z, qx, qy, qz, qw], world frame, z up."""
    bodies = {}
    for rid, (x, y, yaw) in zip(frame.ids, frame.poses.tolist()):
        bodies[str(rid)] = [round(x, 5), round(y, 5), 0.0, 0.0, 0.0, round(math.sin(yaw / 2.0), 6),
                            round(math.cos(yaw / 2.0), 6)]
    return {"bodies": bodies, "clock_s": frame.clock_s}


def format_ids(ids: List[int], limit: int = 10) -> str:
    shown = ", ".join(map(str, ids[:limit]))
    return shown + (f" and {len(ids) - limit} more" if len(ids) > limit else "")


def bind_error(err: zmq.ZMQError, bind: str, port: int, port_field: str) -> ConfigError:
    """A failed bind as the config field to fix: the port when it is taken, else the address."""
    if err.errno == zmq.EADDRINUSE:
        return ConfigError(f"network.{port_field}", f"port {port} on {bind} is already in use")
    reason = (err.strerror or str(err)).split(" (addr=")[0]     # pyzmq appends the endpoint; we name it ourselves
    return ConfigError("network.bind", f"cannot listen on {bind!r}: {reason} (give an address of this PC, "
                       "e.g. 127.0.0.1, or * for all interfaces)")


def _property(frame: zmq.Frame, name: str) -> Optional[str]:
    try:
        return frame.get(name)
    except zmq.ZMQError:      # no such property (e.g. no authentication: no User-Id)
        return None
