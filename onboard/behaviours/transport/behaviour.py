"""The transport state machine: bid -> (seed | travel -> attach) -> caged -> settle -> push/rotate -> done.

Written against the HAL only. Each step: merge what the radio brought into the tuple space, estimate the
own pose, run the current state's handler, publish a heartbeat and broadcast the tuple-space updates.
See docs/behaviour.md for the diagram and the equations' code locations.
"""
from __future__ import annotations

import math
from collections import deque
from typing import Any, Deque, Dict, FrozenSet, Optional, Set, Tuple

import numpy as np

from ...behaviour import Behaviour, register
from ...hal.ir_curve import ir_distance_m
from ...localisation import PoseTracker
from ...motion import vector_to_wheels
from . import control as c
from .caged import CagedPhase
from .caging import AVERAGE_SETTLE_STEPS, CagingPhases
from .closure import ClosurePhase
from .control import Vec
from .estimation import ObjectEstimation
from .estimator import ObjectFilter, ring_centroid, surrounds
from .params import TransportParams
from .perception import Percept, near, perceive, world_to_robot
from .reinforce import STALL_PROGRESS_M, ReinforcePhase
from .tasks import Task, TaskBoard, distance, new_space, task_from
from .transport import ProgressWatch, TransportPhases

# A spare robot that has heard no news of the mission this long is out of reach of it (left behind as the cage
# pushed away, or never near it): it counts as finished, though it goes on keeping clear.
LEFT_BEHIND_S = 60.0
# Ours (regroup_when_cut_off): before closure, a spare that has heard no heartbeat of any robot at work on the
# mission (cage members, task owners) this long is out of their radio range, and would never hear the tasks
# they open: it drives toward the object estimate until it hears one again, and stops this far from it.
REGROUP_AFTER_S = 30.0
REGROUP_STANDOFF_M = 1.0


@register("transport")
class Transport(CagingPhases, ClosurePhase, CagedPhase, TransportPhases, ObjectEstimation, ReinforcePhase, Behaviour):
    Params = TransportParams

    def __init__(self, robot, params: Optional[TransportParams] = None):
        super().__init__(robot, params)
        p = self.params
        self.space = new_space(robot.id)
        self.board = TaskBoard(self.space, p.liveness_timeout_s)
        self.tracker = PoseTracker(robot)
        self.state = "idle"
        self.task: Optional[Task] = None
        self.bid_seen: Dict[str, float] = {}     # "tid/epoch" -> local time a bid was first seen
        self.winner_seen: Dict[Tuple[str, Any], float] = {}    # ("tid/epoch", robot) -> when first seen winning
        self.last_bid: Dict[str, float] = {}
        self.settled_steps = 0
        self.settle_window: Deque[Tuple[float, Vec]] = deque(maxlen=AVERAGE_SETTLE_STEPS)   # _settled_on_average
        self.spawned: Optional[str] = None       # the task this robot opened for its successor
        self.spawned_times: Dict[Tuple[str, int], float] = {}   # (tid, epoch) -> when this robot opened it
        self.tips_seen_apart: Set[int] = set()   # opposite tips seen on the other side of the object (caging)
        self.on_its_way_since: Dict[Tuple[str, int, int], float] = {}   # (tid, epoch, robot) -> first seen so
        self.path: list = []
        self.estimated_at = 0.0
        self.grow_at = 0.0
        self.bidding_seen_at = -math.inf         # last local time some open task had a valid bid
        self.closed_at: Optional[float] = None
        self.filter: Optional[ObjectFilter] = None
        self.reference_ring: Dict[int, Vec] = {}
        self.reference_centre: Vec = (0.0, 0.0)         # the object's, when transport began
        self.reference_ring_centre: Vec = (0.0, 0.0)    # the live members' ring centroid then
        self.ring_offset: Optional[Vec] = None          # from the latter to the former (_dead_members_offset)
        self.offset_members: FrozenSet[int] = frozenset()   # the live members ring_offset is for
        self.yaw_history: Deque[Tuple[float, float]] = deque()   # (time, yaw measured) for _hold_yaw_of_two
        self.reference_normals: Dict[int, Vec] = {}
        self.reference_surface: Dict[int, Vec] = {}
        self.reference_yaw = 0.0
        self.reference_edges: Dict[tuple, float] = {}
        self.reference_contacts: Dict[int, float] = {}   # members' contact normal angles when transport began
        self.yaw_from_normals = False            # a small cage reads the yaw from contact normals (small_cage_yaw)
        self.formation: Dict[int, Vec] = {}
        self.waypoint = 0
        self.phase = "p"
        self.held_up_since: Optional[Tuple[Tuple[int, str], float]] = None   # (barrier, since when) half arrived
        self.effective = False
        self.rotating = False
        self.last_step: Optional[float] = None
        self.progress: Tuple[float, float] = (math.inf, 0.0)   # travel: (best distance to target, when)
        self.seed_still: Tuple[Optional[Vec], float] = (None, 0.0)   # seed: (where it last moved 2 cm, when)
        self.attach_since = 0.0                  # when this robot last went from travel to attach
        self.closest_error = math.inf            # attach: smallest |error| to the predecessor while touching
        self.approach_from: Optional[Vec] = None   # attach: where this robot was at the last step (_shoving)
        self.shove_advance = 0.0                 # attach: how far it drove toward the object without touching it
        self.shoving_object = False              # attach: pressed on the object below the contact reading
        self.object_seen_at = -math.inf          # attach: when the IR last saw the object
        self.given_back: Dict[str, float] = {}   # tid -> until when this robot does not bid for it again
        self.taken: Set[Tuple[str, int]] = set()  # (tid, epoch) of every task this behaviour object took
        self.reinforcing = False                 # idle, reinforce_push: behind the cage and pushing
        self.closed_seen_at: Optional[float] = None     # idle: when this spare first saw the cage closed
        self.stall_watch = ProgressWatch(STALL_PROGRESS_M)   # idle: the cage's progress (_push_stalled)
        self.next_stall_check = 0.0
        self.push_stalled = False                # the cage stalled pushing: this spare reinforces from now on
        self.quiet_since: Tuple[int, float] = (-1, 0.0)   # idle: (count of mission news, since when)
        self.left_behind = False
        self.cut_off: Tuple[float, bool] = (-math.inf, False)   # idle: (when last checked, cut off from the mission)
        self.percept: Optional[Percept] = None
        estimate = p.object_estimate or (0.0, 0.0, 0.0)
        self.hint: Vec = (estimate[0], estimate[1])
        self.initial_yaw = math.radians(estimate[2])

    # --- the loop ---------------------------------------------------------------------------------------
    def step(self) -> None:
        robot, now = self.robot, self.robot.clock.now()
        # For each message with a dict payload: space.merge(payload.get("ts"), sender).
        self.space.merge_messages(robot.radio.receive(), "ts")
        self.board.refresh_liveness(now)
        self._publish_mission()
        pose = self.tracker.update()
        if pose is None or pose.stale:
            # Without a recent position a robot cannot bid, cage or push: hold still until the hub is back.
            robot.wheels.stop()
        else:
            self.percept = perceive(pose.x, pose.y, pose.yaw, robot.range_and_bearing.neighbours(),
                                    robot.proximity.read())
            getattr(self, f"_on_{self.state}")(now)
            if self.state not in ("idle", "done"):
                self.board.heartbeat(robot.id, pose.x, pose.y, self._contact_normal(), self._published_surface(),
                                     state=self.state)
        self.last_step = now
        gossip = self.space.outgoing()
        if gossip:      # nothing new and no anti-entropy turn: stay quiet (most steps in a large swarm)
            robot.radio.broadcast({"ts": gossip})

    def _contact_normal(self) -> Optional[float]:
        percept = self.percept
        if percept is None or not percept.in_contact(self.params.proximity_threshold):
            return None
        return math.atan2(percept.object_vector[1], percept.object_vector[0])

    def _published_surface(self) -> Optional[Vec]:
        """The surface point for the heartbeat: only from members about to push or pushing, in a cage
        large enough for the estimate to use them; other robots keep their heartbeats (and radio traffic)
        as they were without it."""
        p = self.params
        if not p.surface_estimate or self.state not in ("settle", "push", "rotate") or self._small_cage():
            return None
        return self._surface_point()

    def _surface_point(self) -> Optional[Vec]:
        """The point of the object's surface this robot's IR sees (world frame): from its centre along x_o,
        a body radius plus the distance the strongest object reading stands for (hal.ir_curve)."""
        percept = self.percept
        gap = ir_distance_m(percept.object_peak) if percept is not None and percept.object_peak > 0 else None
        if gap is None:
            return None
        reach = self.robot.spec.radius_m + gap
        direction = c.unit(percept.object_vector)
        return (percept.position[0] + direction[0] * reach, percept.position[1] + direction[1] * reach)

    @property
    def finished(self) -> bool:
        """Done, or left behind (see _note_left_behind): the simulator stops once every robot is finished."""
        return self.state == "done" or (self.state == "idle" and self.left_behind)

    def _publish_mission(self) -> None:
        if "task/S" not in self.space and self.params.object_estimate is not None:
            self.board.put_task(Task("S", self.hint[0], self.hint[1], "S", 0, None, 0))
        if "path" not in self.space and self.params.path:
            self.space.put("path", [list(w) for w in self.params.path])

    def _drive(self, u: Vec, speed_scale: float = 1.0, turn_on_spot_beyond_rad: float = math.pi / 2) -> None:
        """Drive along the world-frame input u at cruise speed (the authors normalised u the same way)."""
        local, speed = world_to_robot(c.unit(u), self.percept.yaw), self.params.cruise_speed_m_s * speed_scale
        left, right = vector_to_wheels(local[0], local[1], speed, self.robot.spec.wheel_base_m,
                                       turn_on_spot_beyond_rad=turn_on_spot_beyond_rad)
        self.robot.wheels.set_speeds(left, right)

    def _hold(self) -> None:
        self.robot.wheels.stop()

    def _avoid(self, exclude: Optional[set] = None) -> Vec:
        p = self.params
        vectors = near(self.percept.neighbours, p.safety_distance_m, exclude)
        # u_avoid of no vectors is ZERO itself (the usual case: nobody within d_s)
        return c.u_avoid(vectors, p.safety_distance_m, 2.0) if vectors else c.ZERO

    def _caging_only_done(self) -> bool:
        """Without a path (a caging-only run) a closed cage is the end of the job."""
        if not self.params.path:
            self.state = "done"
            return True
        return False

    def _finish_if_done(self) -> bool:
        if "done" in self.space:
            self.state = "done"
            self._hold()
            return True
        return False

    # --- idle: bid for the nearest open task, stay out of the cage's way -----------------------------------
    def _on_idle(self, now: float) -> None:
        if self._finish_if_done():
            return
        regroup = moved = False
        if "closed" in self.space:
            if not self._caging_only_done() and (self.params.reinforce_push or self._push_stalled(now)):
                self._reinforce(now)
                return
        elif f"member/{self.robot.id}" in self.space:
            # The swarm voids this robot's bids (it holds member/<id>: a restarted agent whose earlier run of
            # the behaviour was a member, dead or not): a bid would only hold off the robots that can take
            # the task. It stays a spare.
            pass
        elif not self._release_earlier_tasks() and not self._take_won_task(now):
            task = self._nearest_open_task(now)
            if task is not None:
                self._bid(task, now)
                moved = self._head_start(task)
            regroup = task is None and self._cut_off(now)
        if regroup:
            self._regroup()
        elif not moved:
            self._keep_clear()
        self._note_left_behind(now)

    def _note_left_behind(self, now: float) -> None:
        """A spare robot (idle, with no task) that has heard no news of the mission for LEFT_BEHIND_S is out
        of reach of it, and `done` will never reach it: it counts as finished. News is any write other than
        a position heartbeat (tasks, bids, owners, members, closure, arrivals, `done`): a heartbeat says that
        a robot is alive, not that the mission moved on. Two cases: the cage pushed out of the robot's range
        after closure (paper-100-straight_rot seed 1: one robot stranded 7.4 m from everyone kept the run
        going to its time limit, 1900 s after the last waypoint), or the robot never heard the cage close
        because the spares that were not needed stayed where they started, out of range of the object.
        Anything new clears the flag."""
        space = self.space
        revision = space.revision() - space.revision("pos")
        if revision != self.quiet_since[0]:
            self.quiet_since = (revision, now)
            self.left_behind = False
        elif now - self.quiet_since[1] >= LEFT_BEHIND_S:
            self.left_behind = True

    def _cut_off(self, now: float) -> bool:
        """A spare with no open task to bid for is cut off from the mission when it has heard no heartbeat of
        any robot at work on it (members, task owners) for REGROUP_AFTER_S while it is more than
        REGROUP_STANDOFF_M from the object estimate. Robots at work beat at least once a second, and entries
        travel on from robot to robot, so in a connected swarm this does not happen. (The paper has no such
        rule: its robots all start within radio range.) Checked once a second: idle robots are most of a
        swarm."""
        p = self.params
        if not p.regroup_when_cut_off or p.object_estimate is None:
            return False
        if now - self.cut_off[0] < 1.0:
            return self.cut_off[1]
        x, y = self.percept.x, self.percept.y
        far = math.hypot(self.hint[0] - x, self.hint[1] - y) > REGROUP_STANDOFF_M
        robots = [r for r in self.board.mission_robots() if r != self.robot.id] if far else []
        cut_off = bool(robots) and not any(self.board.alive(r, now, REGROUP_AFTER_S) for r in robots)
        self.cut_off = (now, cut_off)
        return cut_off

    def _regroup(self) -> None:
        """Drive toward the object estimate, keeping clear of robots and obstacles, to get back in range."""
        percept = self.percept
        toward = c.unit((self.hint[0] - percept.x, self.hint[1] - percept.y))
        self._drive(c.add(toward, self._avoid(), c.scale(percept.obstacle_vector, -1.0)))

    def _release_earlier_tasks(self) -> bool:
        """A restarted agent: the space says this robot owns a task that this behaviour never took (its run
        before the restart did, and was attaching or travelling). Its heartbeats keep it alive, so nobody
        re-opens the task, and the swarm voids its bids while it owns one: the branch stalled, and two
        restarted lab-6 runs never closed their cage. Re-open the task as a new epoch, as attach_timeout_s
        does. In a run without restarts every task a robot owns, it took: nothing changes. True if it did."""
        released = False
        for tid in self.board.owned_by(self.robot.id):
            task = self.board.task(tid)
            if task is not None and (tid, task.epoch) not in self.taken:
                task.epoch += 1
                self.board.put_task(task)
                released = True
        return released

    def _take_won_task(self, now: float) -> bool:
        """After T_a with a valid bid stored, the robot whose id is stored takes the task -- whichever open
        task that is, even if another one is nearer now."""
        for fields, key, best in self.board.open_tasks():   # the open tasks with their best bids, cached
            if best is None:
                continue
            self.bid_seen.setdefault(key, now)
            won = best.get("robot") == self.robot.id
            waited = now - self.winner_seen.setdefault((key, best.get("robot")), now)
            if not won and waited >= self.params.allocation_time_s + self.params.liveness_timeout_s:
                # Ours: this winner has not taken it liveness_timeout_s after T_a, counted from when this robot
                # first saw it win (its take comes back as late as its bid came): it died while bidding, with no
                # heartbeat for liveness to miss, and the task was held for ever (behaviour.md section 6).
                task = task_from(fields)
                task.epoch += 1
                self.board.put_task(task)
                continue
            if won and now - self.bid_seen[key] >= self.params.allocation_time_s:
                task = task_from(fields)
                self.board.take(task, self.robot.id, float(best["bid"]))
                self.taken.add((task.tid, task.epoch))
                self.task = task
                self.state = "seed" if task.branch == "S" else "travel"
                self.progress, self.seed_still = (math.inf, now), (None, now)
                return True
        return False

    def _keep_clear(self) -> None:
        u = c.add(self._avoid(), c.scale(self.percept.obstacle_vector, -1.0))
        if c.norm(u) > 0.05:
            self._drive(u)
        else:
            self._hold()

    def _nearest_open_task(self, now: float) -> Optional[Task]:
        x, y = self.percept.x, self.percept.y
        best, best_key = None, None
        for fields, _, _ in self.board.open_tasks():
            if self.given_back.get(fields["tid"], -math.inf) > now:
                continue   # this robot timed out attaching there: leave it to another robot for a while
            # min by (distance, tid), the first of equals: math.hypot as in tasks.distance
            key = (math.hypot(x - fields["x"], y - fields["y"]), fields["tid"])
            if best_key is None or key < best_key:
                best, best_key = fields, key
        return None if best is None else task_from(best)

    def _bid(self, task: Task, now: float) -> None:
        key = f"{task.tid}/{task.epoch}"
        mine = distance(self.percept.position, task.position)
        best = self.board.best_bid(task)
        if best is not None:
            self.bid_seen.setdefault(key, now)
        lower = best is None or mine < float(best["bid"]) - 1e-3
        if lower and now - self.last_bid.get(key, -math.inf) >= self.params.rebid_period_s:
            self.board.bid(task, self.robot.id, mine)
            self.last_bid[key] = now
            self.bid_seen.setdefault(key, now)

    def _still_mine(self) -> bool:
        task = self.board.task(self.task.tid) if self.task else None
        owner = self.board.owner(task) if task else None
        if task is None or task.cancelled or task.epoch != self.task.epoch or "closed" in self.space or \
                (owner is not None and owner.get("robot") != self.robot.id):
            self._drop_task()
            return False
        self.task = task        # the predecessor may have re-aimed the target (same epoch, new position)
        return True

    def _vector_to(self, robot: Optional[int]) -> Optional[Vec]:
        """World-frame vector from this robot to ``robot``: its range and bearing when in range, else its
        shared position; None when neither is known."""
        if robot is None:
            return None
        vector = self.percept.neighbours.get(robot)
        if vector is None:
            where = self.board.position(robot)
            vector = c.sub(where, self.percept.position) if where is not None else None
        return vector

    def _small_cage(self) -> bool:
        """Fewer than ``surface_estimate_min_points`` members: too few surface points for the surface
        estimate (the ring centroid is used), and the cage whose side robots pace_formation slows."""
        return self.board.member_count() < self.params.surface_estimate_min_points

    def _spacing(self) -> float:
        return self.params.inter_robot_distance_m * (1.0 + 0.02 * self.board.grow_level())

    def _centre_guess(self) -> Vec:
        """Where the object's centre probably is before the cage closes: the ring of members once they lie all
        round the hint C_o(0), else the hint. (Not any 3 members: on a 7.2 x 12 m object the first dozen lie
        along one face, their ring centroid lies on that face, and tangents and pipelined targets taken from
        it point into the object or back along the branch.)"""
        points = [self.board.position(m) for m in self.board.members()]
        points = [q for q in points if q is not None]
        if surrounds(points, self.hint):
            return ring_centroid(np.asarray(points))
        return self.hint

    def _member_position(self, rid: Optional[int]) -> Optional[Vec]:
        if rid is None:
            return None
        return self.percept.position if rid == self.robot.id else self.board.position(rid)

    def telemetry(self) -> Dict[str, Any]:
        # Everything the evaluator and the operator need travels here (also over the wire from real robots).
        member = self.board.is_member(self.robot.id)
        data: Dict[str, Any] = {"state": self.state, "waypoint": self.waypoint, "member": member,
                                "closed": "closed" in self.space, "effective": bool(self.effective),
                                "rotating": bool(self.rotating)}
        if self.task is not None:
            data["task"] = self.task.tid
        if self.filter is not None and member:      # a spare's estimate (reinforce.py) is its own business
            data["estimate"] = [round(v, 4) for v in self.filter.pose]
        if self.space.refused:                      # peers' entries of a shape the readers cannot take (entries.py)
            data["refused_entries"] = self.space.refused
            data["last_refused"] = self.space.last_refusal[:200]
        return data
