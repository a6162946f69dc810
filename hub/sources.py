"""Pose sources for the hub: the ``motioncapture`` library, a recorded MCAP log (``hub/replay_source.py``),
and the simulator (``hub/sim_source.py``). Each hands the hub :class:`PoseFrame` records stamped on arrival with
the hub's monotonic clock, in the world frame (z up, yaw counter-clockwise from x).
"""
from __future__ import annotations

import math
import operator
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Deque, Dict, List, Optional, Tuple

import numpy as np

from hub.mocap_options import DEGENERATE_QUATERNION, known_systems_hint, unread_option_notes
from onboard.config import ConfigError, as_written


@dataclass
class PoseFrame:
    stamp: float                    # hub monotonic time when the frame arrived (s)
    ids: List[int]                  # robots seen in this frame
    poses: np.ndarray               # (len(ids), 3) x, y (m), yaw (rad), world frame, all finite
    clock_s: Optional[float] = None     # sim source: simulated time of the frame
    extras: Dict[int, Dict[str, Any]] = field(default_factory=dict)   # sim source: per-robot IR and odometry
    killed: Tuple[int, ...] = ()    # sim source: robots a scenario fault has killed


class SourceRestartError(RuntimeError):
    """A source could not start again for a new run (``restart``): the run starts where the source is."""


class PoseSource:
    """Base: a source is polled by the hub loop. ``wake_socket`` (optional) becomes readable when frames wait."""

    description = "source"
    wake_socket = None
    # Not None when the poses do not come from the robots in the room (a recording, a simulation, the mock
    # motion capture): why. A robot with real wheels is then held (Hub.mode_for): it would steer by poses that
    # do not follow it, and drive on where no geofence can see it.
    not_the_real_robots: Optional[str] = None

    @property
    def untracked(self) -> str:
        """Why a robot without a pose is held (``ctl status``), in this source's terms."""
        return "not tracked by motion capture"

    @property
    def ended(self) -> bool:
        """The source has no more frames to give, and has said so (a replay at the end of its log)."""
        return False

    def robot_ids(self) -> Optional[List[int]]:
        """The robots this source knows, or None when the config's list decides."""
        return None

    def poll(self, now: float) -> List[PoseFrame]:
        return []

    def next_due(self, now: float) -> float:
        """Seconds until the source wants to be polled again without a wake-up."""
        return 0.05

    def progress(self) -> Optional[Dict[str, Any]]:
        """How far a source that ends has got (a replay: ``ctl status``'s ``replay``); None for one that does not."""
        return None

    def close(self) -> None:
        pass


# --- axis conventions ---------------------------------------------------------------------------------------
def pose_from_mocap(position, quaternion_wxyz, up_axis: str) -> Tuple[float, float, float]:
    """World (x, y, yaw) from a rigid body's position and orientation in the mocap frame.

    Z-up systems (Vicon, Qualisys by default): the floor is x-y. Y-up systems (OptiTrack Motive's default):
    the floor is x-z, and the z-up world is (x, -z, y). Yaw is the heading of the body's x axis on the floor.
    """
    w, qx, qy, qz = quaternion_wxyz
    if not (w * w + qx * qx + qy * qy + qz * qz >= DEGENERATE_QUATERNION and math.isfinite(w + qx + qy + qz)):
        # All zeros (a body some systems lost), or a component that is not finite: no orientation.
        return float(position[0]), float(-position[2] if up_axis == "y" else position[1]), math.nan
    # The body's x axis expressed in the mocap frame: the first column of the rotation matrix.
    ax = 1.0 - 2.0 * (qy * qy + qz * qz)
    ay = 2.0 * (qx * qy + w * qz)
    az = 2.0 * (qx * qz - w * qy)
    if up_axis == "y":
        return float(position[0]), float(-position[2]) + 0.0, math.atan2(-az, ax)
    return float(position[0]), float(position[1]), math.atan2(ay, ax)


def floor_positions(positions: np.ndarray, up_axis: str) -> np.ndarray:
    """Many bodies' (K, 3) mocap positions as (K, 3) world x, y and a yaw left NaN (:func:`yaws_from_mocap`
    gives it), with :func:`pose_from_mocap`'s axis convention."""
    poses = np.empty((len(positions), 3))
    poses[:, :2] = positions[:, (0, 2) if up_axis == "y" else (0, 1)]
    if up_axis == "y":
        np.negative(poses[:, 1], out=poses[:, 1])
        poses[:, 1] += 0.0          # -0.0 (a body at z = 0) was said and recorded as y -0.00
    poses[:, 2] = np.nan
    return poses


def yaws_from_mocap(quaternions_wxyz: np.ndarray, up_axis: str) -> np.ndarray:
    """:func:`pose_from_mocap`'s yaw for many bodies at once: (K, 4) quaternions -> (K,).

    Few numpy calls (each costs microseconds when the caches are cold, as they are once per mocap frame): the
    heading is ``atan2(a, 0.5 - b)`` with both arguments half those of :func:`pose_from_mocap`, which halves
    them exactly and so gives the same angle."""
    w, qx, qy, qz = np.asarray(quaternions_wxyz, dtype=float).reshape(-1, 4).T
    across = qy * qy
    across += qz * qz                          # (1 - ax) / 2
    if up_axis == "y":
        along = w * qy
        along -= qx * qz                       # -az / 2
    else:
        along = qx * qy
        along += w * qz                        # ay / 2
    yaws = np.arctan2(along, 0.5 - across)
    # A quaternion far from unit length (all zeros: a body some systems lost) has no yaw: NaN, no pose. Nor has
    # one with a component that is not finite (arctan2 made 135 degrees of [1, 0, 0, inf]).
    yaws[(w * w + qx * qx + across < DEGENERATE_QUATERNION) | ~np.isfinite(w + qx + qy + qz)] = np.nan
    return yaws


class _WakeUp:
    """An inproc socket pair: a reader thread pokes, the hub's poller wakes."""

    def __init__(self, context, name: str):
        import zmq

        self.reader = context.socket(zmq.PAIR)
        self.reader.bind(f"inproc://wake-{name}-{id(self)}")
        self.writer = context.socket(zmq.PAIR)
        self.writer.connect(f"inproc://wake-{name}-{id(self)}")
        self.lock = threading.Lock()
        self.closed = False
        self.zmq = zmq

    def poke(self) -> None:
        with self.lock:
            if self.closed:       # a reader thread still in the SDK's wait when the source closed
                return
            try:
                self.writer.send(b"", self.zmq.NOBLOCK)
            except self.zmq.ZMQError:
                pass   # already poked and not yet drained

    def drain(self) -> None:
        while True:
            try:
                self.reader.recv(self.zmq.NOBLOCK)
            except self.zmq.Again:
                return

    def close(self) -> None:
        """Under the poke's lock: a ZeroMQ socket must not be closed while another thread sends on it."""
        with self.lock:
            self.closed = True
            self.reader.close(0)
            self.writer.close(0)


CONNECT_TIMEOUT_S = 10.0          # source.connect_timeout_s's default
IN_PROCESS_SYSTEMS = ("mock",)    # synthetic backends: nothing on the network to wait for
# Backends whose connect returns at once even when nothing answers: the probe waits for their first frame
# instead. Vicon's does so for an address no host answers (192.168.10.2 from a PC off that network), and its
# waitForNextFrame then spins a whole core for as long as the hub runs, frames never coming.
FIRST_FRAME_SYSTEMS = ("vicon",)
# Connects in a child process, which ends itself (SIGALRM's default action) should its parent die first.
_PROBE = """
import json, os, signal, sys
signal.alarm(int(sys.argv[3]) + 5)
import motioncapture
try:
    mocap = motioncapture.connect(sys.argv[1], json.loads(sys.argv[2]))
    if sys.argv[4] == "frame":
        mocap.waitForNextFrame()
except RuntimeError as err:
    print(err, file=sys.stderr, flush=True)
    os._exit(1)
os._exit(0)   # no destructors: some SDKs block or complain while disconnecting
"""


def describe_options(options: Dict[str, str], limit: int = 80) -> str:
    text = ", ".join(f"{k}={v}" for k, v in options.items()) or "no options"
    return text if len(text) <= limit else text[:limit - 3] + "..."


def probe_mocap(system: str, options: Dict[str, str], timeout_s: float) -> None:
    """Connect once in a child process (and, for FIRST_FRAME_SYSTEMS, read one frame) and wait for it at most
    ``timeout_s``, so that a system that never answers is an error instead of a hang. In this process it could
    not be timed out or interrupted: some backends (optitrack, with no server) block inside the SDK while
    holding Python's GIL, which freezes every thread, signal handlers included. The child dies with us on
    Ctrl-C (same process group) or is killed."""
    import json
    import subprocess
    import sys

    first_frame = system in FIRST_FRAME_SYSTEMS
    command = [sys.executable, "-c", _PROBE, system, json.dumps(options), str(int(math.ceil(timeout_s))),
               "frame" if first_frame else "connect"]
    try:
        probe = subprocess.run(command, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        where = f" at {options['hostname']}" if "hostname" in options else ""
        frame = " (not one frame: is that its address, and is it streaming?)" if first_frame else ""
        raise ConfigError("source.system", f"no answer from {system}{where} within {timeout_s:g} s{frame}") from None
    if probe.returncode != 0:
        reason = probe.stderr.strip().splitlines()[-1:] or [f"exit code {probe.returncode}"]
        raise ConfigError("source.system",
                          f"cannot connect to {as_written(system)}: {reason[0]}{known_systems_hint(reason[0])}")


_WXYZ = operator.attrgetter("w", "x", "y", "z")     # a motioncapture Quaternion's fields


READ_RETRY_S = 0.1           # a failed read is tried again this much later
FAILURE_LINE_MAX_S = 60.0    # while reads keep failing, a line at 1, 3, 9, 27, 81 s, then one a minute


class ReadFailures:
    """What the reader thread says while the motion-capture library fails: the first failure, then a count at
    growing intervals, and one line when frames come again. A line per try (10 a second) buried the console
    and the log of a hub whose motion capture was off for an hour."""

    def __init__(self, log: Callable[[str], None]):
        self.log = log
        self.count = 0
        self.since = 0.0
        self.next_line = 0.0

    def failed(self, err: Exception, now: float) -> None:
        self.count += 1
        if self.count == 1:
            self.since, self.next_line = now, now + 1.0
            self.log(f"hub: motion capture read failed: {err} (trying again every {READ_RETRY_S:g} s)")
        elif now >= self.next_line:
            self.log(f"hub: motion capture read failed {self.count} times in {now - self.since:.0f} s, the last "
                     f"with: {err}; no frames meanwhile, so the robots are held")
            self.next_line = now + min(2.0 * (now - self.since), FAILURE_LINE_MAX_S)

    def read(self, now: float) -> None:
        if self.count:
            self.log(f"hub: motion capture frames again, after {self.count} failed "
                     f"read{'' if self.count == 1 else 's'} over {now - self.since:.1f} s")
            self.count = 0


class MotionCaptureSource(PoseSource):
    """The ``motioncapture`` library in a reader thread (its ``waitForNextFrame`` blocks)."""

    def __init__(self, context, system: str, options: Dict[str, Any], bodies: Dict[str, int], up_axis: str,
                 log: Callable[[str], None] = print, connect: Optional[Callable] = None,
                 connect_timeout_s: float = CONNECT_TIMEOUT_S):
        import motioncapture

        options = {k: str(v) for k, v in options.items()}
        host = options.get("hostname")
        self.description = f"motioncapture {system}" + (f" at {host}" if host else "")
        if system == "mock":
            self.not_the_real_robots = "the mock motion capture's poses do not follow real robots"
        self.bodies, self.up_axis, self.log = dict(bodies), up_axis, log
        log(f"hub: connecting to {system} ({describe_options(options)})...")
        for note in unread_option_notes(system, options):
            log(f"hub: warning: {note}")
        if connect is None and system not in IN_PROCESS_SYSTEMS:
            probe_mocap(system, options, connect_timeout_s)
        try:
            self.mocap = (connect or motioncapture.connect)(system, options)
        except RuntimeError as err:
            raise ConfigError("source.system",
                              f"cannot connect to {as_written(system)}: {err}{known_systems_hint(str(err))}") from None
        except (ValueError, TypeError) as err:     # the SDK's own parsing of an option (std::stoi, ...)
            raise ConfigError("source.options", f"{as_written(system)} refused an option "
                                                f"({describe_options(options)}): {err}") from None
        self.frames: Deque[PoseFrame] = deque(maxlen=8)   # the hub wants the newest; old ones are useless
        self.wake = _WakeUp(context, "mocap")
        self.wake_socket = self.wake.reader
        self.unknown_names: set = set()
        self._names: Optional[Tuple[str, ...]] = None      # the body names of the last frame, and their lookup
        self._selection: Tuple[List[int], Optional[List[int]]] = ([], None)
        self.running = True
        self.thread = threading.Thread(target=self._read, name="mocap-reader", daemon=True)
        self.thread.start()

    def robot_ids(self) -> Optional[List[int]]:
        return sorted(self.bodies.values())

    def _read(self) -> None:
        failures = ReadFailures(self.log)
        while self.running:
            try:
                self.mocap.waitForNextFrame()
                stamp = time.monotonic()
                bodies = self.mocap.rigidBodies
            except Exception as err:   # a network hiccup in the SDK must not kill the hub
                failures.failed(err, time.monotonic())
                time.sleep(READ_RETRY_S)
                continue
            failures.read(stamp)
            self.frames.append(self._convert(stamp, bodies))
            self.wake.poke()

    def _convert(self, stamp: float, bodies) -> PoseFrame:
        """One mocap frame as a :class:`PoseFrame`: listed bodies only (others are logged once and ignored),
        in the world frame (:func:`floor_positions`, :func:`yaws_from_mocap`, vectorised), occluded bodies
        (a position or an orientation that is not finite, or no rotation at all) dropped.

        Everything is read here, before the next ``waitForNextFrame``: the SDK's body objects and their arrays
        are views into its own storage, which the next frame rewrites (Vicon and Qualisys rebuild it), so a yaw
        read later came from a later frame, or from freed memory for a body that frame lacked. The SDK hands
        out one Python object per body, so reading their fields stays a loop; everything else is numpy, and the
        name -> robot id lookup is redone only when the set of body names changes."""
        names = tuple(bodies)
        if names != self._names:
            self._names, self._selection = names, self._select(names)
        ids, picks = self._selection
        values = list(bodies.values())
        if picks is not None:
            values = [values[k] for k in picks]
        if not values:
            return PoseFrame(stamp, [], np.zeros((0, 3)))
        positions = np.concatenate([body.position for body in values]).reshape(-1, 3)
        poses = floor_positions(positions, self.up_axis)
        poses[:, 2] = yaws_from_mocap(np.array([_WXYZ(body.rotation) for body in values], dtype=float),
                                      self.up_axis)
        seen = np.isfinite(poses).all(axis=1)   # occluded bodies come as NaN in some systems, lost ones as zeros
        if not seen.all():
            ids = [rid for rid, ok in zip(ids, seen.tolist()) if ok]
            poses = poses[seen]
        return PoseFrame(stamp, list(ids), poses)

    def _select(self, names: Tuple[str, ...]) -> Tuple[List[int], Optional[List[int]]]:
        """Robot ids of the listed bodies among ``names``, in order, and their positions in ``names`` (None
        when every body is listed). Logs each unlisted name the first time it is seen."""
        ids, picks = [], []
        for k, name in enumerate(names):
            robot = self.bodies.get(name)
            if robot is None:
                if name not in self.unknown_names:
                    self.unknown_names.add(name)
                    self.log(f"hub: ignoring rigid body {name!r} (not listed in source.bodies)")
                continue
            ids.append(robot)
            picks.append(k)
        return ids, (None if len(picks) == len(names) else picks)

    def poll(self, now: float) -> List[PoseFrame]:
        self.wake.drain()
        out = []
        while self.frames:
            out.append(self.frames.popleft())
        return out

    def next_due(self, now: float) -> float:
        return 0.1

    def close(self) -> None:
        self.running = False
        self.thread.join(timeout=1.0)
        self.wake.close()
