"""The hub: poses in, virtual sensor frames and relayed radio out, operator control, safety.

Sockets (docs/protocol.md): a ROUTER for the robots' DEALERs (downlink frames and commands, uplink
telemetry, broadcasts, wheel commands) and a ROUTER for ``khepri ctl``. One thread runs everything here;
only a motion-capture reader runs beside it (``hub/sources.py``).

This module holds the :class:`Hub`'s state, sockets, loop, pose handling and safety modes; what it sends is in
``hub/downlink.py`` and what it receives from robots in ``hub/uplink.py`` (mixins of the same class), operator
requests in ``hub/control_service.py``, and what it checks and says periodically in ``hub/housekeeping.py``.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Dict, List, Optional, Tuple

import numpy as np
import zmq

from onboard.agent.link import tcp_host
from onboard.protocol import MAX_MESSAGE_BYTES

from .background_recorder import BackgroundRecorder
from .binding import bind_error, bind_every
from .config import LabConfig
from .console import as_console
from .control_service import ControlService
from .downlink import Downlink
from .housekeeping import MOCAP_SILENT_S, Housekeeping
from .keyfiles import KeyRing
from .links import VIRTUAL_DRIVERS, DropLog, RateMeter, RobotLink, SparseFrames
from .relay import RadioRelay
from .security import OPERATOR_DOMAIN, ROBOT_DOMAIN, HandshakeWatch, HubAuthenticator, make_curve_server
from .sensors import SensingModel, VirtualSensors
from .sources import PoseFrame, PoseSource
from .uplink import Uplink

if TYPE_CHECKING:
    from .progress import RunProgress

DOWNLINK_HWM = 8          # frames queued per robot; older data is useless, a full queue drops (latest-only)
UPLINK_SLICE = 16         # uplink messages read between two looks for a waiting pose frame and at the clock
# The longest the hub reads one socket before it sends the frames due: a flood of messages (a fuzzer, a
# misbehaving peer) must not hold back the frames the agents' 0.3 s watchdogs wait for.
READ_SLICE_S = 0.02
SHUTDOWN_ACK_WAIT_S = 0.3      # at shutdown, how long the hub waits for the agents to acknowledge its stop


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


class Hub(Downlink, Uplink, Housekeeping):
    def __init__(self, config: LabConfig, source: PoseSource, robot_ids: List[int], run: RunTemplate,
                 sensing: SensingModel, relay_drop: float, seed=None, keyring: Optional[KeyRing] = None,
                 recorder=None, log: Callable[[str], None] = print, context: Optional[zmq.Context] = None,
                 progress: Optional[RunProgress] = None):
        if recorder is not None and not isinstance(recorder, BackgroundRecorder):
            # The loop only queues; a thread of its own writes. A write that fails (a full disk) ends the
            # recording, not the lab run: the robots keep being served, and the operator is told.
            recorder = BackgroundRecorder(recorder, on_failure=self._recording_failed, on_skip=lambda error: log(
                f"hub: not recorded: {error} (left out of the log, counted in its drops; said once per topic)"),
                on_behind=lambda queued: log(f"hub: RECORDING FALLS BEHIND: {queued} messages wait for the disk; "
                                             "new ones are left out until it catches up (ctl status counts them)"))
        self.config, self.source, self.run, self.keyring, self.recorder = config, source, run, keyring, recorder
        self.log = as_console(log)            # every line it prints goes into the log too, as /hub/log
        self.log.record_to(recorder)
        self.context = context or zmq.Context.instance()
        self.noise_seed = seed            # the sim source's: each run that restarts its world restarts the noise too
        rng = np.random.default_rng(seed)
        self.ids = list(robot_ids)
        self.robots: Dict[int, RobotLink] = {rid: RobotLink(rid) for rid in self.ids}
        self.row = {rid: i for i, rid in enumerate(self.ids)}
        self.sensors = VirtualSensors(self.ids, sensing, rng)
        self.relay = RadioRelay(self.ids, relay_drop, config.relay.queue, config.relay.max_bytes, rng)
        self.drops = DropLog(self.log, on_drop=self._record_drop)
        self.poses = np.zeros((len(self.ids), 3))
        self.seen_at = np.full(len(self.ids), -math.inf)
        self.outside_fence = np.zeros(len(self.ids), dtype=bool)
        self.killed: set = set()
        self.unknown_runs_said: set = set()     # runs agents were in that this hub never started (uplink.py)
        self.runs_started: set = set()          # the runs this hub started (control_service.py)
        self.extras: Dict[int, Dict[str, Any]] = {}
        self.clock_s: Optional[float] = None
        self.last_frame_stamp = -math.inf
        self.mocap_rate = RateMeter()
        # A replay slower than real time spaces its frames out by 1/rate: a pose is stale only after as many
        # of them as at real time (or every robot flickers between run and hold at rate 0.1).
        slowed = min(1.0, getattr(source, "rate", 1.0))
        replay = config.source.type == "replay"
        self.stale_s = config.source.stale_s / slowed if replay else config.source.stale_s
        # Likewise the "no motion-capture frame" line: at rate 0.01 it came and went with every frame.
        self.silent_s = MOCAP_SILENT_S / slowed if replay else MOCAP_SILENT_S
        self.mocap_silent = False
        self.sparse_frames = SparseFrames(self.stale_s, self.silent_s, config.source.stale_s)
        self._finished_said: Optional[str] = None    # the run whose end was said
        self.progress = progress          # the sim source's object and waypoints (hub/progress.py), else None
        self.arrival_said: Optional[str] = None      # the run whose arrival at its last waypoint was said
        self.placed_a_robot = False       # some frame has held a pose for one of this lab's robots
        # When to look next for two robots on one spot (housekeeping); only real motion capture can put them there.
        self.overlap_check_at = 0.0 if config.source.type == "motioncapture" else math.inf
        self.mode = "idle"
        self.run_id: Optional[str] = None
        self.estop_at: Optional[float] = None
        self.started_at = time.monotonic()
        self.expect_frames_from(self.started_at)
        self.control = ControlService(self)
        self.authenticator: Optional[HubAuthenticator] = None
        self.handshake_watches: List[HandshakeWatch] = []
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
        self.robot_socket, robot_addresses = self._router(ROBOT_DOMAIN, net.robot_port, "robot_port")
        self.robot_socket.sndhwm = DOWNLINK_HWM
        self.control_socket, control_addresses = self._router(OPERATOR_DOMAIN, net.control_port, "control_port")
        if self.keyring is not None:      # peers dropped before ZAP (no keys, another hub's key): said, not silent
            self.handshake_watches = [HandshakeWatch(self.context, sock, domain, self.keyring, self.log)
                                      for sock, domain in ((self.robot_socket, ROBOT_DOMAIN),
                                                           (self.control_socket, OPERATOR_DOMAIN))]
        for role, addresses in (("robots", robot_addresses), ("control", control_addresses)):
            self.endpoints[role] = addresses[0]
            self.log(f"listening {role} {' and '.join(addresses)}")   # one line per role: tools count them
        if self.recorder is not None:      # said once bound: a hub that cannot bind removes the log it opened
            self.log(f"hub: recording to {self.recorder.path}")
        return self.endpoints

    def _router(self, domain: str, port: int, port_field: str) -> Tuple[zmq.Socket, List[str]]:
        sock = self.context.socket(zmq.ROUTER)
        sock.linger = 0
        sock.router_mandatory = 1      # a full or vanished peer raises instead of dropping silently
        sock.rcvhwm = 10_000
        sock.maxmsgsize = MAX_MESSAGE_BYTES + 1024   # ZeroMQ itself cuts off absurd frames before we read them
        if self.keyring is not None:
            make_curve_server(sock, self.keyring, domain)
        bind = self.config.network.bind
        try:
            return sock, bind_every(sock, f"tcp://{tcp_host(bind)}:{port if port else '*'}")
        except zmq.ZMQError as err:
            sock.close(0)          # nothing half-open: the caller closes the sockets bound before this one
            raise bind_error(err, bind, port, port_field) from None

    def close(self) -> None:
        if self.robot_socket is not None:
            self.send_command_to_all("stop", reason="hub shutting down")
            self._wait_for_acknowledgements(time.monotonic() + SHUTDOWN_ACK_WAIT_S)
        for watch in self.handshake_watches:
            watch.close()
        for sock in (self.robot_socket, self.control_socket):
            if sock is not None:
                sock.close(0)
        if self.authenticator is not None:
            self.authenticator.stop()
        self.source.close()
        if self.recorder is not None:
            self.recorder.close()

    def _wait_for_acknowledgements(self, deadline: float) -> None:
        """The shutdown stops are only queued: closing the socket at once dropped them, and every agent kept
        its run, held by nothing but its watchdog. Read the uplink until each connected agent acknowledged
        its stop, or the deadline passed."""
        while time.monotonic() < deadline:
            now = time.monotonic()
            waiting = [r for r in self.robots.values() if r.pending is not None and r.routing is not None
                       and r.connected(now, self.config.watchdog_s)]
            if not waiting:
                return
            if self.robot_socket.poll(20, zmq.POLLIN):
                self.handle_uplink_events({self.robot_socket: zmq.POLLIN})

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
            deadline = time.monotonic() + READ_SLICE_S
            for count in range(budget):
                if count % UPLINK_SLICE == UPLINK_SLICE - 1 and time.monotonic() > deadline:
                    break         # the rest next time round, after the frames due
                try:
                    parts = self.control_socket.recv_multipart(zmq.NOBLOCK, copy=False)
                except zmq.Again:
                    break
                self.control.handle(parts)

    def handle_uplink_events(self, events: Dict[Any, int], budget: int = 2000) -> None:
        if self.robot_socket not in events:
            return
        wake = self.source.wake_socket
        deadline = time.monotonic() + READ_SLICE_S
        for count in range(budget):
            if count % UPLINK_SLICE == UPLINK_SLICE - 1 and (time.monotonic() > deadline or (
                    wake is not None and wake.getsockopt(zmq.EVENTS) & zmq.POLLIN)):
                break             # frames are due or a pose frame waits: serve it first, the rest next time round
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
        sparse = None if self.run.lockstep else self.sparse_frames.tick(frame.stamp)   # lockstep: paced by agents
        if sparse:
            self.log(f"hub: {sparse}")
        present = frame.stamp - self.seen_at <= self.stale_s
        for rid in self.killed:
            if rid in self.row:     # a fault may kill a robot of the scenario that this lab does not serve
                present[self.row[rid]] = False
        self.sensors.update(self.poses, present)
        self._check_geofence(present)
        self._hold_sim_wheels(frame.stamp)
        if self.recorder is not None:      # encoded by the recorder's thread, after the frames went out
            self.recorder.write_later("/mocap/poses", poses_record, (frame,))

    def restart_noise(self) -> None:
        """The virtual sensors' noise and the relay's drops from the start of their streams, as in a hub just
        started: a new run in a world rebuilt for the scenario's seed then repeats the last one in lockstep."""
        rng = np.random.default_rng(self.noise_seed)
        self.sensors.restart(rng)
        self.relay.rng = rng

    def _check_geofence(self, present: np.ndarray) -> None:
        fence = self.config.geofence
        if fence is None:
            return
        xmin, ymin, xmax, ymax = fence
        x, y = self.poses[:, 0], self.poses[:, 1]
        outside = present & ((x < xmin) | (x > xmax) | (y < ymin) | (y > ymax))
        newly = np.nonzero(outside & ~self.outside_fence)[0]
        if len(newly) > 1 and outside.sum() == present.sum():    # one line, and the likely cause, not one each
            self.log(f"hub: every robot is outside the geofence {list(fence)} (robot {self.ids[newly[0]]} at "
                     f"({x[newly[0]]:.2f}, {y[newly[0]]:.2f})): stopped; is the geofence in the motion capture's "
                     "frame and metres?")
            newly = newly[:0]
        for row in newly:
            self.log(f"hub: robot {self.ids[row]} is outside the geofence at ({x[row]:.2f}, {y[row]:.2f}): stopped")
        self.outside_fence = outside

    def _hold_sim_wheels(self, now: float) -> None:
        """With the sim source the hub is the physics: robots that must not move do not, whatever agents send."""
        command = getattr(self.source, "command", None)
        if command is None:
            return
        for rid, robot in self.robots.items():
            if self.mode_for(robot)[0] != "run" or not self._answering(robot, now):
                command(rid, 0.0, 0.0)

    def _answering(self, robot: RobotLink, now: float) -> bool:
        """Whether a robot's agent is there to drive its simulated wheels. In lockstep that is whether it answered
        the last step: the wall clock said silent whenever the hub had waited longer than watchdog_s for a slower
        agent, and stopped this one's wheels, which its next step only restarted if it set them again."""
        if self.run.lockstep:
            return robot.routing is not None and robot.unresponsive_steps == 0
        return robot.connected(now, self.config.watchdog_s)

    def mode_for(self, robot: RobotLink) -> Tuple[str, str]:
        """What this robot must do now, and why when it is not the hub's mode."""
        if self.mode == "estop":
            return "estop", "operator e-stop"
        if robot.id in self.killed:
            return "hold", "killed by a scenario fault"
        if self.mode != "run":
            return self.mode, ""
        if robot.driver and robot.driver not in VIRTUAL_DRIVERS and self.source.not_the_real_robots is not None:
            return "hold", f"{self.source.not_the_real_robots}: a robot with real wheels ({robot.driver}) is held"
        row = self.row[robot.id]
        if not self.sensors.present[row]:
            return "hold", self.source.untracked
        if self.outside_fence[row]:
            return "hold", "outside the geofence"
        return "run", ""

    def _recording_failed(self, error: BaseException) -> None:
        self.log(f"hub: RECORDING STOPPED: {error}; the run goes on without a log (ctl status says so)")

    def _record_drop(self, reason: str, sender: str) -> None:
        if self.recorder is not None:
            self.recorder.count_drop(reason, sender)


def poses_record(frame: PoseFrame) -> Dict[str, Any]:
    """``/mocap/poses`` in the recorder's schema: robot id -> [x, y, z, qx, qy, qz, qw], world frame, z up."""
    bodies = {}
    for rid, (x, y, yaw) in zip(frame.ids, frame.poses.tolist()):
        if not math.isfinite(yaw):
            continue            # an orientation the system could not give: no pose, as with an occluded body
        # "+ 0.0": a value rounded to -0.0 is written as 0.0 (a log reader need not know of signed zeros).
        bodies[str(rid)] = [round(x, 5) + 0.0, round(y, 5) + 0.0, 0.0, 0.0, 0.0,
                            round(math.sin(yaw / 2.0), 6) + 0.0, round(math.cos(yaw / 2.0), 6) + 0.0]
    return {"bodies": bodies, "clock_s": frame.clock_s}
