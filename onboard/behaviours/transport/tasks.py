"""Caging tasks, bids, owners, cage members and liveness, all kept in the replicated tuple space.

Keys (values are small JSON mappings):
  task/<tid>    {"x", "y", "branch": "S"|"L"|"R", "index", "pred", "epoch", "cancelled"}  the caging target
  bid/<tid>/<e> {"robot", "bid"}      lowest bid wins (ties: lower robot id) -- conflict rule on "bid/"
  owner/<tid>   {"robot", "bid", "epoch"}  the robot that took the task; same conflict rule on "owner/"
  member/<rid>  {"tid", "branch", "index"}  a robot settled in the cage
  pos/<rid>     [x, y, normal]              position heartbeat of members and travellers, every step, with the
                                            world angle of the contact normal x_o (null when not touching)
  closed        {"pair": [a, b]}            the cage is closed (Proposition 1)
  grow          {"level": n}               out of robots: I_d grows by 2 % per level until closure
  path          [[x, y, yaw_deg], ...]      the agreed path
  arrive/<k>/<phase>/<rid>  1               barrier flags per waypoint and phase ("p" push, "r" rotate)
  done          1                           the last waypoint is reached
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Tuple

from ...stigmergy import TupleSpace, lowest_field

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
    rule = lowest_field("bid", "robot")
    return TupleSpace(owner, conflict_rules={"bid/": rule, "owner/": rule})


class TaskBoard:
    """Typed access to the tuple space, plus who is alive (from the pos/ heartbeats as this robot sees them)."""

    def __init__(self, space: TupleSpace, liveness_timeout_s: float):
        self.space = space
        self.timeout = liveness_timeout_s
        self._heartbeats: Dict[int, Tuple[int, float]] = {}   # rid -> (timestamp seen, local time it changed)

    # --- tasks and bids -----------------------------------------------------------------------------
    def put_task(self, task: Task) -> None:
        self.space.put(f"task/{task.tid}", {"x": round(task.x, 4), "y": round(task.y, 4), "branch": task.branch,
                                            "index": task.index, "pred": task.pred, "epoch": task.epoch,
                                            "cancelled": task.cancelled})

    def task(self, tid: str) -> Optional[Task]:
        value = self.space.get(f"task/{tid}")
        if not isinstance(value, dict):
            return None
        try:
            return Task(tid, float(value["x"]), float(value["y"]), str(value["branch"]), int(value["index"]),
                        value.get("pred"), int(value.get("epoch", 0)), bool(value.get("cancelled", False)))
        except (KeyError, TypeError, ValueError):
            return None

    def tasks(self) -> List[Task]:
        found = (self.task(key[len("task/"):]) for key, _ in self.space.items("task/"))
        return [t for t in found if t is not None]

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
        value = self.space.get(f"bid/{task.tid}/{task.epoch}")
        if not isinstance(value, dict) or "bid" not in value:
            return None
        return None if self.busy(value.get("robot"), task.tid) else value

    def busy(self, robot: Any, except_tid: str = "") -> bool:
        if f"member/{robot}" in self.space:
            return True
        for key, value in self.space.items("owner/"):
            if key != f"owner/{except_tid}" and isinstance(value, dict) and value.get("robot") == robot:
                task = self.task(key[len("owner/"):])
                if task is not None and not task.cancelled and task.epoch == value.get("epoch"):
                    return True
        return False

    def bid(self, task: Task, robot: int, amount: float) -> None:
        self.space.put(f"bid/{task.tid}/{task.epoch}", {"robot": robot, "bid": round(amount, 4)})

    def take(self, task: Task, robot: int, amount: float) -> None:
        self.space.put(f"owner/{task.tid}", {"robot": robot, "bid": round(amount, 4), "epoch": task.epoch})

    # --- members and heartbeats ---------------------------------------------------------------------
    def join_cage(self, robot: int, task: Task) -> None:
        self.space.put(f"member/{robot}", {"tid": task.tid, "branch": task.branch, "index": task.index})

    def members(self) -> Dict[int, dict]:
        found = {}
        for key, value in self.space.items("member/"):
            try:
                found[int(key[len("member/"):])] = value
            except ValueError:
                continue
        return found

    def heartbeat(self, robot: int, x: float, y: float, normal: Optional[float]) -> None:
        self.space.put(f"pos/{robot}", [round(x, 4), round(y, 4), None if normal is None else round(normal, 3)])

    def refresh_liveness(self, now: float) -> None:
        for key, _ in self.space.items("pos/"):
            entry = self.space.entry(key)
            try:
                rid = int(key[len("pos/"):])
            except ValueError:
                continue
            seen = self._heartbeats.get(rid)
            if seen is None or entry.timestamp > seen[0]:
                self._heartbeats[rid] = (entry.timestamp, now)

    def alive(self, robot: int, now: float) -> bool:
        seen = self._heartbeats.get(robot)
        return seen is not None and now - seen[1] <= self.timeout

    def heard_of(self, robot: int) -> bool:
        return robot in self._heartbeats

    def position(self, robot: int) -> Optional[Tuple[float, float]]:
        value = self.space.get(f"pos/{robot}")
        if isinstance(value, list) and len(value) >= 2:
            return (float(value[0]), float(value[1]))
        return None

    def contact_normal(self, robot: int) -> Optional[float]:
        value = self.space.get(f"pos/{robot}")
        if isinstance(value, list) and len(value) >= 3 and isinstance(value[2], (int, float)):
            return float(value[2])
        return None

    # --- cage-wide flags ------------------------------------------------------------------------------
    def grow_level(self) -> int:
        value = self.space.get("grow")
        return int(value.get("level", 0)) if isinstance(value, dict) else 0

    def arrivals(self, waypoint: int, phase: str) -> set:
        prefix = f"arrive/{waypoint}/{phase}/"
        return {int(k[len(prefix):]) for k, _ in self.space.items(prefix) if k[len(prefix):].isdigit()}

    def arrive(self, waypoint: int, phase: str, robot: int) -> None:
        key = f"arrive/{waypoint}/{phase}/{robot}"
        if key not in self.space:
            self.space.put(key, 1)


def distance(a: Tuple[float, float], b: Tuple[float, float]) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])
