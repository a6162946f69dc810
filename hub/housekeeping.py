"""The hub's periodic checks: stale poses, a source that places no robot, silent motion capture, the 1 Hz
status record, the run's progress (sim source), and a run whose robots all report their job finished.

A mixin of :class:`~.server.Hub`, like :class:`~.downlink.Downlink` and :class:`~.uplink.Uplink`: the loop calls
:meth:`Housekeeping.housekeeping` once each time round.
"""
from __future__ import annotations

import math
from typing import List

import numpy as np

from .run_events import follow_progress, stop_hint

MOCAP_SILENT_S = 1.0      # warn when no pose frame arrived for this long
# Two robots' centres closer than this on the floor cannot be (a KheperaIV is 0.14 m across): said once.
OVERLAP_M = 0.07
OVERLAP_CHECK_S = 30.0
NO_POSE_YET_WARNING_S = 2.0    # warn when no frame has placed a robot this long after start...
NO_POSE_YET_REPEAT_S = 30.0    # ...and again this often while none does


class Housekeeping:
    def housekeeping(self, now: float) -> None:
        self.resend_unacknowledged(now)
        if not self.run.lockstep:       # in lockstep the hub paces the frames itself: none is ever late
            self._expire_stale_poses(now)
        self._warn_if_no_pose_yet(now)
        self.say_silent_robots(now)
        self.drops.flush(now)
        # A replay at the end of its log said so itself; "no motion-capture frame" would only blur that.
        silent = now - self.last_frame_stamp > self.silent_s and self.last_frame_stamp > -math.inf \
            and not self.source.ended
        if silent != self.mocap_silent:
            self.mocap_silent = silent
            self.log(f"hub: no motion-capture frame for {self.silent_s:g} s: robots without a pose are held" if silent
                     else "hub: motion capture is back")
        if self.recorder is not None and now >= self._next_status_record:
            self._next_status_record = now + 1.0
            self.recorder.write("/hub/status", self.control.status(now))
        follow_progress(self)
        self._say_when_finished(now)
        if now >= self.overlap_check_at:
            self._say_overlapping_robots(now)

    def _say_when_finished(self, now: float) -> None:
        """Once per run, when every connected robot says its job is done (the behaviour's ``finished``, which
        ends a simulated run): said, not acted on; ending a lab run is the operator's ``ctl stop``."""
        if self.mode != "run" or self.run_id is None or self._finished_said == self.run_id:
            return
        connected = [r for r in self.robots.values() if r.connected(now, self.config.watchdog_s)]
        runs = [((r.telemetry or {}).get("behaviour") or {}) for r in connected]
        if connected and all(r.run_id == self.run_id for r in connected) and all(b.get("finished") for b in runs):
            self._finished_said = self.run_id
            self.log(f"hub: run {self.run_id}: every connected robot ({len(connected)}) reports its job finished"
                     + stop_hint(self))

    def _say_overlapping_robots(self, now: float) -> None:
        """Two robots whose bodies lie closer on the floor than two robots can: the wrong ``source.up_axis``
        (a Z-up system read as Y-up puts every robot on one line, at minus its height) or one body mapped
        twice. Nothing else tells: the hub serves the poses, and the robots steer by them. Said once; looked at
        every second until two robots are placed, then every OVERLAP_CHECK_S (it costs 0.1-0.2 ms at 100 robots,
        which a pose frame due then would wait for)."""
        rows = np.flatnonzero(self.sensors.present)
        self.overlap_check_at = now + (1.0 if len(rows) < 2 else OVERLAP_CHECK_S)
        if len(rows) < 2:
            return
        xy = self.poses[rows, :2]
        apart = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
        apart[np.diag_indices(len(rows))] = np.inf
        i, j = np.unravel_index(int(np.argmin(apart)), apart.shape)
        if apart[i, j] >= OVERLAP_M:
            return
        self.overlap_check_at = math.inf
        first, second = self.ids[int(rows[i])], self.ids[int(rows[j])]
        self.log(f"hub: warning: robots {first} and {second} are {apart[i, j]:.2f} m apart on the floor, closer "
                 f"than two robots can be: is source.up_axis ({self.config.source.up_axis}) right for this system "
                 "(z: Vicon, Qualisys; y: OptiTrack Motive's default), and is each body its own robot in "
                 "source.bodies?")

    def _expire_stale_poses(self, now: float) -> None:
        """Bodies not seen for ``source.stale_s`` lose their pose, and their robots are held, also when no
        frame comes at all (motion capture stopped, the replay ended). Presence used to be recomputed only
        when a frame arrived, so without frames every robot ran on, for ever, on its last pose."""
        stale = self.sensors.present & (now - self.seen_at > self.stale_s)
        if stale.any():
            present = self.sensors.present & ~stale
            self.sensors.update(self.poses, present)
            self._check_geofence(present)

    def expect_frames_from(self, when: float) -> None:
        """The source delivers frames from ``when`` on (math.inf: not yet), and the no-frame warning counts from
        then: `khepri sil --realtime` starts physics only once its agents have connected, and said "no
        motion-capture frame yet after 2 s" in every run."""
        self.frames_expected_from = when
        self._next_no_pose_warning = when + NO_POSE_YET_WARNING_S

    def _warn_if_no_pose_yet(self, now: float) -> None:
        """A source that never delivers (no server, wrong host, a log without poses) is said from the start,
        not only once frames stop after a first one. Lockstep frames wait for the agents: nothing to say."""
        if self.placed_a_robot or self.run.lockstep or now < self._next_no_pose_warning:
            return
        self._next_no_pose_warning = now + NO_POSE_YET_REPEAT_S
        after, source = f"{now - self.frames_expected_from:.0f} s", self.source.description
        if self.last_frame_stamp == -math.inf:
            self.log(f"hub: no motion-capture frame yet after {after} from {source}")
        else:
            check = "robots against the ids the log's /mocap/poses place" if self.config.source.type == "replay" \
                else "source.bodies and robots"
            self.log(f"hub: the frames from {source} hold none of this lab's robots yet after {after} "
                     f"(check {check}; this lab's robots: {format_ids(self.ids)})")


def format_ids(ids: List[int], limit: int = 10) -> str:
    shown = ", ".join(map(str, ids[:limit]))
    return shown + (f" and {len(ids) - limit} more" if len(ids) > limit else "")
