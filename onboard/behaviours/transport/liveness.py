"""Position heartbeats on the task board (``pos/<rid>`` in the tuple space, see tasks.py): writing this robot's,
and reading from the others' who is alive, where it is and where its IR sees the object.

When a heartbeat is written again is decided in heartbeat.py.
"""
from __future__ import annotations

from typing import Dict, Optional, Tuple

from ...stigmergy import TupleSpace
from .heartbeat import DEFAULT_HEARTBEAT_RULE, HEARTBEAT_RULES, says_nothing_new


class Liveness:
    """Mixed into :class:`~onboard.behaviours.transport.tasks.TaskBoard`, which sets this state up."""

    space: TupleSpace
    timeout: float                                 # the liveness timeout (s)
    _heartbeats: Dict[int, Tuple[int, float]]      # rid -> (timestamp seen, local time it changed)
    _now: Optional[float]                          # the time of the latest refresh_liveness
    _beat_at: Optional[float]                      # when this robot last wrote its heartbeat
    _beat_state: Optional[str]                     # the state it was in then

    def heartbeat(self, robot: int, x: float, y: float, normal: Optional[float],
                  surface: Optional[Tuple[float, float]] = None, now: Optional[float] = None,
                  state: Optional[str] = None) -> None:
        """Publish this robot's position, contact normal and the point of the object's surface its IR sees,
        if one of them changed enough, the last heartbeat is getting old or the robot's ``state`` changed;
        ``now`` defaults to the time given to the latest ``refresh_liveness``. What counts as enough, and
        as old, depends on the state (HEARTBEAT_RULES)."""
        now = self._now if now is None else now
        key = f"pos/{robot}"
        value = [round(x, 4), round(y, 4), None if normal is None else round(normal, 3),
                 None if surface is None else [round(surface[0], 4), round(surface[1], 4)]]
        held = self.space.get(key)
        rule = HEARTBEAT_RULES.get(state, DEFAULT_HEARTBEAT_RULE)
        if now is not None and self._beat_at is not None and now - self._beat_at < rule.period_s - 1e-9 \
                and state == self._beat_state and isinstance(held, list) and len(held) == 4 \
                and says_nothing_new(held, value, rule):
            return
        self.space.put(key, value)
        self._beat_at, self._beat_state = now, state

    def refresh_liveness(self, now: float) -> None:
        self._now = now
        # Only the heartbeats that changed since the last call: an unchanged entry has nothing newer to say.
        for key in self.space.changed_keys("pos"):
            entry = self.space.entry(key)
            try:
                rid = int(key[len("pos/"):])
            except ValueError:
                continue
            seen = self._heartbeats.get(rid)
            if seen is None or entry.timestamp > seen[0]:
                self._heartbeats[rid] = (entry.timestamp, now)

    def alive(self, robot: int, now: float, within: Optional[float] = None) -> bool:
        """A heartbeat of ``robot`` arrived within the liveness timeout (or ``within`` seconds) of ``now``."""
        seen = self._heartbeats.get(robot)
        return seen is not None and now - seen[1] <= (self.timeout if within is None else within)

    def last_heard(self, robot: int) -> Optional[float]:
        """The local time ``robot``'s heartbeat last changed (None: never heard of it)."""
        seen = self._heartbeats.get(robot)
        return None if seen is None else seen[1]

    def heard_of(self, robot: int) -> bool:
        return robot in self._heartbeats

    def position(self, robot: int) -> Optional[Tuple[float, float]]:
        value = self.space.get(f"pos/{robot}")
        if isinstance(value, list) and len(value) >= 2:
            return (float(value[0]), float(value[1]))
        return None

    def surface_point(self, robot: int) -> Optional[Tuple[float, float]]:
        """Where the robot's IR last saw the object's surface (world frame), if it saw it."""
        value = self.space.get(f"pos/{robot}")
        if isinstance(value, list) and len(value) >= 4 and isinstance(value[3], list) and len(value[3]) == 2:
            try:
                return (float(value[3][0]), float(value[3][1]))
            except (TypeError, ValueError):
                return None
        return None

    def contact_normal(self, robot: int) -> Optional[float]:
        value = self.space.get(f"pos/{robot}")
        if isinstance(value, list) and len(value) >= 3 and isinstance(value[2], (int, float)):
            return float(value[2])
        return None
