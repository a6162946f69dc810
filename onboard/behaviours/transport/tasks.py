"""Caging tasks, bids, owners, cage members and liveness, all kept in the replicated tuple space.

Keys (values are small JSON mappings; a peer's entry of another shape is refused as it arrives, entries.py):
  task/<tid>    {"x", "y", "branch": "S"|"L"|"R", "index", "pred", "epoch", "cancelled"}  the caging target
  bid/<tid>/<e> {"robot", "bid"}      lowest bid wins (ties: lower robot id) -- conflict rule on "bid/"
  owner/<tid>   {"robot", "bid", "epoch"}  the robot that took the task; same conflict rule on "owner/"
  member/<rid>  {"tid", "branch", "index"}  a robot settled in the cage; "dead": true once a member found it
                                            dead before closure (it no longer counts, its slot is re-opened)
  pos/<rid>     [x, y, normal, [sx, sy]]    position heartbeat of members and travellers, with the world angle
                                            of the contact normal x_o (null when not touching) and the point
                                            of the object's surface the IR sees (null when unseen, and
                                            outside settle/push/rotate): written when the robot or that
                                            point moved HEARTBEAT_MOVE_M or the normal changed, and at
                                            least every HEARTBEAT_PERIOD_S (liveness times out after 4 s;
                                            a still caged member: every 10 s, see below)
  closed        {"pair": [a, b]}            the cage is closed (Proposition 1)
  grow          {"level": n}               out of robots: I_d grows by 2 % per level until closure
  path          [[x, y, yaw_deg], ...]      the agreed path
  arrive/<k>/<phase>/<rid>  1               barrier flags per waypoint and phase ("p" push, "r" rotate, "c" return)
  done          1                           the last waypoint is reached
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Optional, Tuple

from ...stigmergy import TupleSpace, lowest_field
from .entries import entry_problem
from .liveness import Liveness

BRANCH_DIRECTION = {"L": 1, "R": -1, "S": 0}   # L grows counter-clockwise around the object, R clockwise



@dataclass
class Task:
    tid: str
    x: float
    y: float
    branch: str
    index: int
    pred: Optional[int]
    epoch: int
    cancelled: bool = False

    @property
    def position(self) -> Tuple[float, float]:
        return (self.x, self.y)


def task_id(branch: str, index: int) -> str:
    return "S" if branch == "S" else f"{branch}{index}"


def new_space(owner: int) -> TupleSpace:
    """The transport's replica: relays and anti-entropy tuned for swarms where ~100 robots hear each other
    (see TupleSpace: an accepted entry is relayed once, after 0-7 steps, unless two other robots relayed it
    first; the round-robin share rides along once a second)."""
    rule = lowest_field("bid", "robot")
    return TupleSpace(owner, conflict_rules={"bid/": rule, "owner/": rule}, relay_rounds=1, relay_delay_steps=7,
                      relay_quorum=2, anti_entropy_period=10, check=entry_problem)


class TaskBoard(Liveness):
    """Typed access to the tuple space, plus who is alive (from the pos/ heartbeats as this robot sees them, in
    :class:`~onboard.behaviours.transport.liveness.Liveness`)."""

    def __init__(self, space: TupleSpace, liveness_timeout_s: float):
        self.space = space
        self.timeout = liveness_timeout_s
        self._heartbeats: Dict[int, Tuple[int, float]] = {}   # rid -> (timestamp seen, local time it changed)
        self._now: Optional[float] = None          # the time of the latest refresh_liveness
        self._beat_at: Optional[float] = None      # when this robot last wrote its heartbeat
        self._beat_state: Optional[str] = None     # the state it was in then
        # Views parsed from the space, rebuilt only when their family's revision moves (space.revision):
        # behaviours ask for tasks, owners and members several times per step, and they rarely change.
        self._tasks_at = -1
        self._task_fields: Dict[str, Optional[Dict[str, Any]]] = {}   # tid -> Task fields, None if malformed
        self._task_list: List[Dict[str, Any]] = []                   # fields of the valid tasks, by key
        self._owners_at: Tuple[int, int] = (-1, -1)
        self._owned: Dict[Any, List[str]] = {}                       # robot -> tids it validly owns
        self._odd_owners: List[Tuple[Any, str]] = []                 # (unhashable robot value, tid)
        self._members_at = -1
        self._members: Dict[int, dict] = {}
        self._views_at = -1
        self._views: Dict[Any, Any] = {}      # what is derived from the members (slots, ring, seed), by name
        self._arrivals: Dict[str, set] = {}
        self._arrivals_at = -1
        # best_bid per (tid, epoch), and the open tasks with their best bids (what an idle robot looks at
        # every step): both depend only on the task, owner, bid and member families.
        self._bids_at: Tuple[int, ...] = ()
        self._best_bids: Dict[Tuple[str, int], Optional[dict]] = {}
        self._open_at: Tuple[int, ...] = ()
        self._open: List[Tuple[Dict[str, Any], str, Optional[dict]]] = []

    # --- tasks and bids -----------------------------------------------------------------------------
    def put_task(self, task: Task) -> None:
        self.space.put(f"task/{task.tid}", {"x": round(task.x, 4), "y": round(task.y, 4), "branch": task.branch,
                                            "index": task.index, "pred": task.pred, "epoch": task.epoch,
                                            "cancelled": task.cancelled})

    def task(self, tid: str) -> Optional[Task]:
        """A fresh copy of task ``tid`` (callers may change it before ``put_task``), or None."""
        fields = self._parsed_tasks().get(tid)
        return None if fields is None else _task_from(fields)

    def tasks(self) -> List[Task]:
        """Fresh copies of every well-formed task, in key order."""
        self._parsed_tasks()
        return [_task_from(fields) for fields in self._task_list]

    def tasks_opened_by(self, robot: Any) -> List[Task]:
        """Fresh copies of the tasks ``robot`` opened (its ``pred``) that are not cancelled, in key order: the
        ones a cage member looks after every step, without copying every other task of the cage first."""
        self._parsed_tasks()
        return [_task_from(fields) for fields in self._task_list
                if fields["pred"] == robot and not fields["cancelled"]]

    def _parsed_tasks(self) -> Dict[str, Optional[Dict[str, Any]]]:
        revision = self.space.revision("task")
        if revision != self._tasks_at:
            self._tasks_at = revision
            self._task_fields = {key[len("task/"):]: _parse_task(key[len("task/"):], value)
                                 for key, value in self.space.items("task/")}
            self._task_list = [fields for fields in self._task_fields.values() if fields is not None]
        return self._task_fields

    def owner(self, task: Task) -> Optional[dict]:
        value = self.space.get(f"owner/{task.tid}")
        if isinstance(value, dict) and value.get("epoch") == task.epoch:
            return value
        return None

    def is_open(self, task: Task) -> bool:
        return not task.cancelled and self.owner(task) is None

    def best_bid(self, task: Task) -> Optional[dict]:
        """The lowest valid bid: a bid by a robot that meanwhile took another task or joined the cage is
        void (it will never take this one), so the task is not lost."""
        revisions = self.space.revisions(_BID_FAMILIES)
        if revisions != self._bids_at:
            self._bids_at, self._best_bids = revisions, {}
        if type(task.epoch) is not int or type(task.tid) is not str:   # a caller's odd Task: no caching
            return self._best_bid(task.tid, task.epoch)
        slot = (task.tid, task.epoch)
        best = self._best_bids.get(slot, _MISSING)
        if best is _MISSING:
            best = self._best_bids[slot] = self._best_bid(task.tid, task.epoch)
        return best

    def _best_bid(self, tid: str, epoch: Any) -> Optional[dict]:
        value = self.space.get(f"bid/{tid}/{epoch}")
        if not isinstance(value, dict) or "bid" not in value:
            return None
        return None if self.busy(value.get("robot"), tid) else value

    def open_tasks(self) -> List[Tuple[Dict[str, Any], str, Optional[dict]]]:
        """``(fields, "tid/epoch", best_bid)`` of every open task (``is_open``), in key order: the same tasks as
        filtering ``tasks()``, without making a Task per task per step. ``fields`` are the task's fields as
        :class:`Task` holds them (read-only: ``task_from(fields)`` makes a Task). Rebuilt only when a task,
        owner, bid or member changes."""
        revisions = self.space.revisions(_BID_FAMILIES)
        if revisions != self._open_at:
            self._parsed_tasks()
            found = []
            for fields in self._task_list:
                task = _task_from(fields)
                if self.is_open(task):
                    found.append((fields, f"{task.tid}/{task.epoch}", self.best_bid(task)))
            self._open_at, self._open = revisions, found
        return self._open

    def owned_by(self, robot: int) -> List[str]:
        """The tids ``robot`` validly owns (the owner entry's epoch is its live, uncancelled task's)."""
        self._index_owners()
        return list(self._owned.get(robot, ()))

    def busy(self, robot: Any, except_tid: str = "") -> bool:
        if f"member/{robot}" in self.space:        # a member, or one that died in the cage: it bids no more
            return True
        self._index_owners()
        try:
            owned = self._owned.get(robot, ())
        except TypeError:                          # an unhashable robot value (a peer's malformed bid)
            owned = ()
        if owned and (len(owned) > 1 or owned[0] != except_tid):   # tids are distinct: two can't both match
            return True
        return bool(self._odd_owners) and \
            any(tid != except_tid and value == robot for value, tid in self._odd_owners)

    def _index_owners(self) -> None:
        """Which robot validly owns which task: the owner entry's epoch is the live, uncancelled task's."""
        revisions = (self.space.revision("owner"), self.space.revision("task"))
        if revisions == self._owners_at:
            return
        self._owners_at = revisions
        self._owned, self._odd_owners = {}, []
        tasks = self._parsed_tasks()
        for key, value in self.space.items("owner/"):
            if not isinstance(value, dict):
                continue
            tid = key[len("owner/"):]
            fields = tasks.get(tid)
            if fields is None or fields["cancelled"] or fields["epoch"] != value.get("epoch"):
                continue
            robot = value.get("robot")
            try:
                self._owned.setdefault(robot, []).append(tid)
            except TypeError:
                self._odd_owners.append((robot, tid))

    def bid(self, task: Task, robot: int, amount: float) -> None:
        self.space.put(f"bid/{task.tid}/{task.epoch}", {"robot": robot, "bid": round(amount, 4)})

    def take(self, task: Task, robot: int, amount: float) -> None:
        self.space.put(f"owner/{task.tid}", {"robot": robot, "bid": round(amount, 4), "epoch": task.epoch})

    # --- members (their heartbeats: Liveness) -------------------------------------------------------
    def join_cage(self, robot: int, task: Task) -> None:
        self.space.put(f"member/{robot}", {"tid": task.tid, "branch": task.branch, "index": task.index})

    def is_member(self, robot: Any) -> bool:
        """``robot`` has joined the cage (its ``member/<rid>`` entry is in this replica) and was not declared
        dead since (``declare_dead``)."""
        value = self.space.get(f"member/{robot}")
        return value is not None and not _declared_dead(value)

    def declare_dead(self, robot: int) -> None:
        """Ours: ``robot``, a member, died before the cage closed. It no longer counts as a member (``members``,
        the seed, the branch slots), so the ring, the closure test and the centre guess are made of live
        members only, and its slot can be taken again; its heartbeat stays, so its successor still measures
        from where it stopped."""
        value = self.space.get(f"member/{robot}")
        if isinstance(value, dict) and not _declared_dead(value):
            self.space.put(f"member/{robot}", dict(value, dead=True))

    def members(self) -> Dict[int, dict]:
        return dict(self._current_members())

    def member_count(self) -> int:
        """len(members()), without copying them (asked every step by every pushing robot)."""
        return len(self._current_members())

    def branch_slots(self, branch: str) -> List[Tuple[int, int]]:
        """``(index, rid)`` of the members of ``branch`` with an integer index >= 1, by index; of two members
        claiming one index, the later in ``members()`` wins. The closure test walks this every step for every
        branch member."""
        def build(members: Dict[int, dict]) -> List[Tuple[int, int]]:
            by_index = {v.get("index"): rid for rid, v in members.items() if v.get("branch") == branch}
            return [(k, by_index[k]) for k in sorted(k for k in by_index if isinstance(k, int) and k >= 1)]

        return self._member_view(("slots", branch), build)

    def ring_slots(self) -> Tuple[Dict[Tuple[Any, Any], int], Dict[str, Optional[int]]]:
        """The members by ``(branch, index)`` (of two on one slot, the later in ``members()`` wins), and the
        highest integer index of branches L and R (None when a branch has none): what every caged member
        looks up each step to find its ring neighbours."""
        def build(members: Dict[int, dict]):
            by_slot = {(v.get("branch"), v.get("index")): rid for rid, v in members.items()}
            tips = {b: max((i for (bb, i) in by_slot if bb == b and type(i) is int), default=None) for b in "LR"}
            return by_slot, tips

        return self._member_view("ring", build)

    def seed_member(self) -> Optional[int]:
        """The first member of branch S in ``members()`` (the seed), or None."""
        return self._member_view("seed", lambda members: next(
            (rid for rid, v in members.items() if v.get("branch") == "S"), None))

    def _member_view(self, name: Any, build: Callable[[Dict[int, dict]], Any]) -> Any:
        """``build(members)``, made once per change of the member family and shared until the next (callers
        must not change it)."""
        members = self._current_members()
        if self._views_at != self._members_at:
            self._views_at, self._views = self._members_at, {}
        if name not in self._views:
            self._views[name] = build(members)
        return self._views[name]

    def _current_members(self) -> Dict[int, dict]:
        revision = self.space.revision("member")
        if revision != self._members_at:
            self._members_at = revision
            found = {}
            for key, value in self.space.items("member/"):
                if _declared_dead(value):
                    continue
                try:
                    found[int(key[len("member/"):])] = value
                except ValueError:
                    continue
            self._members = found
        return self._members

    def mission_robots(self) -> List[Any]:
        """The robots at work on the mission as far as this replica knows: cage members and task owners."""
        self._index_owners()
        return list(self._current_members()) + list(self._owned)

    # --- cage-wide flags ------------------------------------------------------------------------------
    def grow_level(self) -> int:
        value = self.space.get("grow")
        return int(value.get("level", 0)) if isinstance(value, dict) else 0

    def arrivals(self, waypoint: int, phase: str) -> set:
        revision = self.space.revision("arrive")
        if revision != self._arrivals_at:
            self._arrivals_at, self._arrivals = revision, {}
        prefix = f"arrive/{waypoint}/{phase}/"
        found = self._arrivals.get(prefix)
        if found is None:
            found = self._arrivals[prefix] = {int(k[len(prefix):]) for k in self.space.keys(prefix)
                                              if k[len(prefix):].isdigit()}
        return set(found)

    def arrive(self, waypoint: int, phase: str, robot: int) -> None:
        key = f"arrive/{waypoint}/{phase}/{robot}"
        if key not in self.space:
            self.space.put(key, 1)


def _declared_dead(value: Any) -> bool:
    return isinstance(value, dict) and value.get("dead") is True


def _parse_task(tid: str, value: Any) -> Optional[Dict[str, Any]]:
    """A task entry's fields as :class:`Task` holds them, or None if the entry is malformed."""
    if not isinstance(value, dict):
        return None
    try:
        return {"tid": tid, "x": float(value["x"]), "y": float(value["y"]), "branch": str(value["branch"]),
                "index": int(value["index"]), "pred": value.get("pred"), "epoch": int(value.get("epoch", 0)),
                "cancelled": bool(value.get("cancelled", False))}
    except (KeyError, TypeError, ValueError):
        return None


_new_instance = object.__new__
_BID_FAMILIES = ("task", "owner", "bid", "member")
_MISSING: Any = object()


def task_from(fields: Dict[str, Any]) -> Task:
    """A fresh Task from the ``fields`` that ``TaskBoard.open_tasks`` hands out."""
    return _task_from(fields)


def _task_from(fields: Dict[str, Any]) -> Task:
    # What Task(**fields) makes, without the dataclass __init__'s per-field cost (tasks() runs every step).
    task = _new_instance(Task)
    task.__dict__.update(fields)
    return task


def distance(a: Tuple[float, float], b: Tuple[float, float]) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])
