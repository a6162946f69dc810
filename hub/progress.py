"""How a run on the ``sim`` source is going: where the object is, which waypoint it heads for, how it ended.

The hub holds the world there, so it knows the object. :class:`RunProgress` feeds the run's evaluator (the one
``khepri sim run`` and ``khepri sil`` write result.json with, ``sim_backend.metrics``) the agents' telemetry once
per control step, and reads from it which waypoints the run reached and, at the end, whether it completed. With
motion capture the hub does not know the object, and has none of this (``hub/run_events.py`` says a run's
start and end either way).
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Dict, List, Optional

from sim_backend.metrics import EvaluatorError, evaluator_call, make_evaluator, waypoint_error

if TYPE_CHECKING:
    from .server import Hub


STALL_SAY_S = 60.0      # simulated seconds without progress before the console says the push may have stalled


class RunProgress:
    """The sim source's object and waypoints during a run, judged by the behaviour's evaluator."""

    def __init__(self, behaviour: str, scenario: Any, world: Any, log: Callable[[str], None]):
        self.behaviour, self.scenario, self.world, self.log = behaviour, scenario, world, log
        self.evaluator: Any = None
        self.attached = False         # khepri sil feeds an evaluator of its own: the hub only reads it
        self.start_s = 0.0            # the simulated time the run started at: the evaluator's zero
        self.observed_step = -1       # the last control step observed
        self.stall_said: Optional[float] = None   # the stall said (its evaluator's progress_at), once each
        self.start(0.0)               # before the first run: nothing reached yet

    def attach(self, evaluator: Any) -> None:
        """Read ``evaluator``, which its owner feeds (``khepri sil``'s session), instead of one of the hub's."""
        self.evaluator, self.attached = evaluator, True

    def start(self, clock_s: float, world: Any = None) -> None:
        """A new run: a fresh evaluator, its clock at 0, on ``world`` when the run has a new one (the sim source
        sets the world back to the scenario's start for each run, unless told not to: hub/new_run.py)."""
        self.start_s = clock_s
        self.stall_said = None
        if world is not None:
            self.world = world
        if self.attached:
            return
        try:
            self.evaluator = make_evaluator(self.behaviour, self.scenario, self.world)
        except EvaluatorError as err:
            self._give_up(err)

    def follow(self, hub: Hub) -> bool:
        """Feed the hub's newest control step to the evaluator, once; whether it was a new one."""
        step = hub.source.control_steps_done()
        if step == self.observed_step:
            return False
        self.observed_step = step
        if self.evaluator is not None and not self.attached:
            try:
                evaluator_call(self.evaluator, "on_step", hub.source.time_s - self.start_s, run_telemetry(hub))
            except EvaluatorError as err:
                self._give_up(err)
        self._say_a_stall(hub)
        return True

    def _say_a_stall(self, hub: Hub) -> None:
        """Once per stall: the object has come no nearer its next waypoint for STALL_SAY_S since the cage closed
        (the transport evaluator's ``progress_at``). A cage that lost a pusher stood still for minutes, every
        robot reporting `push`, and nothing on the console said so."""
        since = getattr(self.evaluator, "progress_at", None)
        if not isinstance(since, float) or since == self.stall_said:
            return
        if hub.mode != "run":       # e-stopped or stopped: the robots were told to stand; not a stall
            self.stall_said = since
            return
        now = hub.source.time_s - self.start_s
        if now - since < STALL_SAY_S:
            return
        self.stall_said = since
        status = self.status() or {}
        away = status.get("distance_m")
        where = f", {away:.2f} m from waypoint {status['target'] + 1}" if away is not None else ""
        self.log(f"hub: run {hub.run_id}: the object has come no nearer its next waypoint for {now - since:.0f} s of "
                 f"simulated time{where}: the push may have stalled (`ctl status` shows each robot; `ctl stop` ends "
                 "the run)")

    def _give_up(self, err: EvaluatorError) -> None:
        """A user's evaluator that raises costs the waypoint count, not the hub."""
        self.log(f"hub: {err}: `ctl status` shows the object without its waypoints from now on")
        self.evaluator = None

    def reached(self) -> Optional[int]:
        if self.evaluator is None:
            return None
        try:
            return evaluator_call(self.evaluator, "waypoints_reached")
        except EvaluatorError as err:
            self._give_up(err)
            return None

    def status(self) -> Optional[Dict[str, Any]]:
        """``ctl status``'s ``object``: None when the scenario has no object."""
        truth = self.world.object_pose()
        if truth is None:
            return None
        path = self.scenario.path
        reached = self.reached() if path else None
        status: Dict[str, Any] = {"pose": [round(float(v), 4) + 0.0 for v in truth], "waypoints": len(path),
                                  "reached": reached, "target": None, "distance_m": None, "yaw_error_rad": None}
        if reached is not None:
            target = min(reached, len(path) - 1)      # the next one; the last once all are reached
            distance, yaw_error = waypoint_error(truth, path[target])
            status.update(target=target, distance_m=round(distance, 4), yaw_error_rad=round(yaw_error, 4))
        return status

    def verdict(self) -> Dict[str, Any]:
        """``outcome`` (``completed``, ``not completed``, or None when the evaluator gives no verdict) and
        ``failures``, from the evaluator's result() as result.json has them."""
        result: Dict[str, Any] = {}
        if self.evaluator is not None:
            try:
                result = evaluator_call(self.evaluator, "result")
            except EvaluatorError as err:
                self._give_up(err)
        completed = result.get("completed")
        outcome = None if completed is None else "completed" if completed else "not completed"
        return {"outcome": outcome, "failures": list(result.get("failures") or [])}


def run_telemetry(hub: Hub) -> List[Optional[Dict[str, Any]]]:
    """What the evaluator gets each step, as in ``khepri sim run``: robot i's behaviour telemetry, None for a
    robot that is dead, or whose agent is not in this run."""
    alive = hub.source.world.alive()
    telemetry: List[Optional[Dict[str, Any]]] = []
    for index, live in enumerate(alive):
        robot = hub.robots.get(index)
        held = robot is not None and live and robot.run_id == hub.run_id and robot.telemetry is not None
        telemetry.append(robot.telemetry.get("behaviour") if held else None)
    return telemetry
