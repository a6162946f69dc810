"""Runs a scenario: owns the control loop, computes every robot's sensors at once, steps the behaviours,
forwards their commands to physics, records trajectories and evaluates the run against ground truth.
"""
from __future__ import annotations

import math
import random
import time
import traceback
from typing import Any, Callable, Dict, List, Optional

import numpy as np

from onboard.agent.telemetry_message import widest_telemetry_message
from onboard.behaviour import (
    USER_CODE_ERRORS,
    BehaviourError,
    build_params,
    get_behaviour,
    ignored_return_text,
    make_behaviours,
    takes_param,
    telemetry_of,
)
from onboard.geometry import neighbour_mask, pairwise_range_bearing, wrap
from onboard.protocol import ProtocolError, encode
from onboard.tracebacks import where_in_users_code

from .hal import SensorFrame, make_robot
from .metrics import EvaluatorError, evaluator_call, make_evaluator, merge_result
from .radio import RadioNetwork
from .scenario import Scenario
from .sensing import ProximityModel
from .trajectory import Recording, trajectory_arrays
from .wall_clock import WallClockLimit, WallClockLimitReached
from .world import World

Progress = Callable[[float, float], None]
#: Where a control step's wall time goes (``Simulation.phase_seconds``; ``khepri bench sim`` prints it).
PHASES = ("physics", "sensing", "behaviours", "radio", "evaluation")
# A robot's step() that runs this long (wall time) is said once a run: on a robot, the agent's step watchdog
# stops the wheels after 0.25 s (onboard/agent/safety.py), so what runs in simulation would not run there.
SLOW_STEP_S = 0.25


def mission_params(behaviour_cls, scenario: Scenario) -> Dict[str, Any]:
    """The scenario's params plus the operator's mission (path, initial object estimate) for behaviours
    that declare those parameters. The estimate is the object's *initial* placement, which the paper assumes
    known; the robots never get the object's live pose."""
    params = dict(scenario.params)
    if takes_param(behaviour_cls, "path") and "path" not in params:
        params["path"] = [list(w) for w in scenario.path]
    if takes_param(behaviour_cls, "object_estimate") and "object_estimate" not in params \
            and scenario.object is not None:
        params["object_estimate"] = [*scenario.object.position, scenario.object.yaw_deg]
    return params


_SURELY_WRAPPED = 3.0     # |angle| below this (< pi): geometry.wrap returns the angle itself, bit for bit


def _wrap_noisy(angles: np.ndarray) -> None:
    """``angles[:] = wrap(angles)`` for bearings plus noise, which are mostly inside (-pi, pi] already: there
    wrap's arithmetic gives back the same float (x - 2 pi * floor((x + pi) / 2 pi) = x - 0.0), so only the
    few beyond +-3 rad go through it."""
    flat = angles.reshape(-1)
    outside = np.flatnonzero(np.abs(flat) >= _SURELY_WRAPPED)
    if len(outside):
        flat[outside] = wrap(flat[outside])


class Simulation:
    def __init__(self, scenario: Scenario, seed: Optional[int] = None):
        self.scenario = scenario
        self.seed = scenario.seed if seed is None else seed
        streams = np.random.SeedSequence(self.seed).spawn(5)
        self.rng_sensors, self.rng_radio, self.rng_pose = (np.random.default_rng(s) for s in streams[1:4])
        random.seed(self.seed)   # behaviours that use the random module stay reproducible too
        self.world = World(scenario, np.random.default_rng(streams[0]))
        self.count = len(self.world.robots)
        self.period = 1.0 / scenario.physics.control_hz
        self.substeps = int(round(self.period / scenario.physics.dt_s))
        self.frame = SensorFrame(inboxes=[[] for _ in range(self.count)], pose_rows=[None] * self.count)
        self.ir = ProximityModel(self.world.spec.radius_m, self.world.spec.proximity_range_m)
        self.radio = RadioNetwork(self.count, scenario.comm.drop, scenario.comm.latency_s, self.period,
                                  self.rng_radio)
        behaviour_cls = get_behaviour(scenario.behaviour)
        params = build_params(behaviour_cls, mission_params(behaviour_cls, scenario))
        self.robots = [make_robot(self.frame, i, self.world.spec) for i in range(self.count)]
        self.behaviours = make_behaviours(behaviour_cls, self.robots, params)
        self.evaluator = make_evaluator(scenario.behaviour, scenario, self.world)
        self.warnings = evaluator_call(self.evaluator, "warnings", params)   # said before the run, kept in result.json
        self.faults = sorted((f.at_s, f.robot, f.restart_after_s) for f in scenario.faults)   # one per robot
        self.restarting: Dict[int, float] = {}     # robot -> when its restarted agent's behaviour starts
        self.behaviour_class, self.params = behaviour_cls, params     # for a restarted agent's new behaviour
        self.pose_history: List[np.ndarray] = []
        self.recording = Recording()
        self.step_index = 0
        self.telemetry: List[Optional[Dict[str, Any]]] = [None] * self.count
        self.stop_reason = ""
        self.phase_seconds: Dict[str, float] = dict.fromkeys(PHASES, 0.0)
        self.say: Callable[[str], None] = lambda line: None     # a note during the run (sim run prints it)
        self.slow_step_said = self.return_said = False
        self._noise = np.empty((2, self.count, self.count))   # range and bearing noise of one step

    # --- sensing --------------------------------------------------------------------------------------
    def _sense(self, poses: np.ndarray, alive: np.ndarray) -> None:
        comm, sensors, frame = self.scenario.comm, self.scenario.sensors, self.frame
        frame.time_s = self.step_index * self.period
        true_ranges, true_bearings = pairwise_range_bearing(poses[:, :2], poses[:, 2])
        mask = neighbour_mask(true_ranges, comm.range_m) & alive[None, :] & alive[:, None]
        # normal(0, s) is 0 + s * standard_normal, drawn one after the other: one draw of both matrices gives
        # the same numbers from the same stream, into a buffer reused every step.
        noise = self._noise
        self.rng_sensors.standard_normal(out=noise)
        ranges = true_ranges + noise[0] * comm.range_noise_m
        np.maximum(ranges, 0.0, out=ranges)
        bearings = true_bearings + noise[1] * comm.bearing_noise_rad
        _wrap_noisy(bearings)
        frame.set_neighbours(mask, ranges, bearings)
        frame.set_proximity(self.ir.readings(poses[:, :2], poses[:, 2], true_ranges, self.world.obstacle_groups(),
                                             self.rng_sensors, sensors.proximity_noise))
        frame.set_odometry(self.world.odometry())
        self._update_positioning(poses)

    def _update_positioning(self, poses: np.ndarray) -> None:
        """Motion capture as relayed by the hub: delayed, noisy, sometimes missing."""
        s = self.scenario.sensors
        self.pose_history.append(poses.copy())
        lag = min(int(round(s.pose_latency_s / self.period)), len(self.pose_history) - 1)
        measured = self.pose_history[-1 - lag]
        del self.pose_history[: max(0, len(self.pose_history) - lag - 1)]
        stamp = (self.step_index - lag) * self.period
        noise_xy = self.rng_pose.normal(0.0, s.pose_noise_m, (self.count, 2))
        noise_yaw = self.rng_pose.normal(0.0, s.pose_noise_rad, self.count)
        arrived = self.rng_pose.random(self.count) >= s.pose_dropout
        xy = (measured[:, :2] + noise_xy).tolist()
        yaws = (measured[:, 2] + noise_yaw).tolist()
        rows = self.frame.pose_rows
        for i in np.nonzero(arrived)[0].tolist():
            x, y = xy[i]
            rows[i] = (x, y, math.remainder(yaws[i], 2.0 * math.pi), stamp)

    # --- one control step -----------------------------------------------------------------------------
    def step(self) -> None:
        t = self.step_index * self.period
        clock, spent = time.perf_counter, self.phase_seconds
        started = clock()
        while self.faults and self.faults[0][0] <= t + 1e-9:
            _, index, down_s = self.faults.pop(0)
            if down_s is None:
                self.world.kill(index)
                self.behaviours[index].state = "dead"
            else:
                self.restarting[index] = t + down_s
        if self.restarting:
            self._restart_agents(t)
        alive = self.world.alive()
        poses = self.world.robot_poses()
        self._sense(poses, alive)
        sensed = clock()
        self.radio.deliver(self.step_index, self.frame.inboxes, alive)
        delivered = clock()
        self._step_behaviours(alive)
        stepped = clock()
        self._route_broadcasts(t)
        routed = clock()
        self.telemetry = self._collect_telemetry(alive)
        evaluator_call(self.evaluator, "on_step", t, self.telemetry)
        self._record(t, poses, alive)
        evaluated = clock()
        self.world.step(self.substeps)
        self.step_index += 1
        spent["sensing"] += sensed - started
        spent["radio"] += (delivered - sensed) + (routed - stepped)
        spent["behaviours"] += stepped - delivered
        spent["evaluation"] += evaluated - routed
        spent["physics"] += clock() - evaluated

    def _restart_agents(self, t: float) -> None:
        """A robot whose agent is down: wheels stopped, and what the radio brings it is lost (its agent's socket
        is gone), until a new behaviour starts on it that knows nothing of the old one, as a restarted agent."""
        for index, back_at in list(self.restarting.items()):
            self.frame.inboxes[index] = []         # what reached it while it was down (up to the step before)
            if t + 1e-9 >= back_at:
                del self.restarting[index]
                # A new agent's wheels start stopped: the old behaviour's last command, kept in the robot's HAL,
                # drove a new behaviour that had not set them yet.
                self.robots[index].wheels.stop()
                self.robots[index].odometry.count_from_here(tuple(self.world.odometry()[index].tolist()))
                self.behaviours[index] = make_behaviours(self.behaviour_class, [self.robots[index]], self.params)[0]

    def _step_behaviours(self, alive: np.ndarray) -> None:
        robots, commands, i, clock, down = self.robots, [], 0, time.perf_counter, self.restarting
        try:
            for i, living in enumerate(alive.tolist()):
                if down and i in down:
                    commands.append((i, 0.0, 0.0))      # its agent is down: the robot stops (the agent's exit)
                elif living:
                    started = clock()
                    returned = self.behaviours[i].step()
                    if clock() - started > SLOW_STEP_S and not self.slow_step_said:
                        self._say_slow_step(i, clock() - started)
                    if returned is not None and not self.return_said:
                        self._say_returned(i, returned)
                    wheels = robots[i].wheels
                    commands.append((i, wheels.left, wheels.right))
        except USER_CODE_ERRORS as exc:     # the user's code: name the robot and the line (a try costs nothing here)
            raise BehaviourError(i, "step()", exc) from exc
        except (KeyboardInterrupt, WallClockLimitReached) as exc:   # stopped from outside: say in whose step
            exc.where = f"robot {i}'s step(){where_in_users_code(traceback.extract_tb(exc.__traceback__)[1:])}"
            raise
        self.world.command_many(commands)

    def _say_returned(self, robot: int, returned: Any) -> None:
        self.return_said = True
        self._note(f"robot {robot}'s step() returned {ignored_return_text(returned)}")

    def _say_slow_step(self, robot: int, seconds: float) -> None:
        self.slow_step_said = True
        note = (f"robot {robot}'s step() took {seconds:.2f} s of wall time at t = {self.step_index * self.period:.1f} "
                f"s (said once a run): on a robot the agent's step watchdog stops the wheels after {SLOW_STEP_S:g} s "
                f"of one step(), and the simulation waits for it")
        self._note(note)

    def _note(self, note: str) -> None:
        self.warnings = [*self.warnings, note]
        self.say(note)

    def _collect_telemetry(self, alive: np.ndarray) -> List[Optional[Dict[str, Any]]]:
        down = self.restarting          # a robot whose agent is down reports nothing, as a dead one
        telemetry: List[Optional[Dict[str, Any]]] = [
            telemetry_of(behaviour, i) if living and not (down and i in down) else None
            for i, (behaviour, living) in enumerate(zip(self.behaviours, alive.tolist()))]
        # Every robot's at the first step, then one robot's per step, in turn: a value the wire cannot carry
        # (a set, an object, too many bytes) fails here, not only in `khepri sil` or on the robots. Encoding
        # every robot's every step would cost 100 robots about a tenth of the simulator's time.
        if telemetry:
            check_telemetry_fits_the_wire(telemetry, None if self.step_index == 0 else self.step_index % len(telemetry))
        return telemetry

    def _route_broadcasts(self, t: float) -> None:
        for i, robot in enumerate(self.robots):
            outbox = robot.radio.outbox
            if outbox:
                receivers = self.frame.receivers(i)       # radio reaches exactly the robots in d_C
                for payload in outbox:
                    self.radio.send(self.step_index, i, payload, t, receivers)
                outbox.clear()

    def phase_times(self) -> Dict[str, float]:
        """Wall seconds spent so far per phase; encoding broadcasts (inside the behaviours' steps) counts
        as radio, not behaviours."""
        encoding = sum(robot.radio.encode_seconds for robot in self.robots)
        times = dict(self.phase_seconds)
        times["behaviours"] -= encoding
        times["radio"] += encoding
        return times

    def _record(self, t: float, poses: np.ndarray, alive: np.ndarray) -> None:
        rec = self.recording
        rec.t.append(t)
        rec.robot_pose.append(poses)
        rec.robot_alive.append(alive)
        obj = self.world.object_pose()
        if obj is not None:
            rec.object_pose.append(obj)
        rec.centroid_estimate.append(evaluator_call(self.evaluator, "centroid_estimate", self.telemetry))

    def done(self) -> bool:
        """True when every live robot's behaviour says it has finished (none is, while an agent is down)."""
        alive = self.world.alive()
        if not alive.any() or self.restarting:
            return False
        for i, behaviour in enumerate(self.behaviours):
            try:
                if alive[i] and not behaviour.finished:
                    return False
            except USER_CODE_ERRORS as exc:
                raise BehaviourError(i, "finished", exc) from exc
        return True

    def run(self, time_limit_s: Optional[float] = None, progress: Optional[Progress] = None,
            wall_limit_s: Optional[float] = None, keep_on_interrupt: bool = False) -> Dict[str, Any]:
        """Run to the end (time limit, finished behaviour, every robot failed) and return the result. A run
        that crashes or outlives ``wall_limit_s`` seconds of wall time still returns what was recorded up to
        there, with ``stop_reason`` and ``error`` saying why it ended; so does one interrupted (Ctrl-C) if
        ``keep_on_interrupt``, else KeyboardInterrupt goes on up (a study's worker must leave no result)."""
        limit = self.scenario.time_limit_s if time_limit_s is None else time_limit_s
        started = time.perf_counter()
        steps = int(math.ceil(limit / self.period - 1e-9))
        self.stop_reason = "time limit"
        error: Optional[str] = None
        trace: Optional[List[str]] = None
        try:
            with WallClockLimit(wall_limit_s):
                for _ in range(steps):
                    self.step()
                    if progress is not None and self.step_index % 10 == 0:
                        progress(self.step_index * self.period, limit)
                    if self.done():
                        self.stop_reason = "behaviour finished"
                        break
                    if not self.world.alive().any():   # nothing can happen any more: no need to wait for the limit
                        self.stop_reason = "every robot failed"
                        break
        except (WallClockLimitReached, KeyboardInterrupt) as exc:   # a hung behaviour, or the user: keep the results
            if isinstance(exc, KeyboardInterrupt) and not keep_on_interrupt:
                raise
            self.stop_reason = "wall-clock limit" if isinstance(exc, WallClockLimitReached) else "interrupted"
            what = f"wall-clock limit of {wall_limit_s:g} s reached" if isinstance(exc, WallClockLimitReached) \
                else f"interrupted ({getattr(exc, 'how', 'Ctrl-C')})"
            inside = f" while {exc.where} ran" if getattr(exc, "where", None) else ""
            error = f"{what}{inside} (at t = {self.step_index * self.period:.1f} s)"
            self.recording.trim(has_object=self.world.object_pose() is not None)
        except Exception as exc:  # a crashed run is recorded, not lost: results up to here are kept
            users = isinstance(exc, (BehaviourError, EvaluatorError))    # they name the call and the line
            what = str(exc) if users else f"{type(exc).__name__}: {exc}"
            error = f"{what} (at t = {self.step_index * self.period:.1f} s)"
            trace = exc.lines if users else None
            self.stop_reason = "crashed"
        stop_error = self._stop_behaviours()
        error = error or stop_error
        wall = time.perf_counter() - started
        sim_time = self.step_index * self.period
        result: Dict[str, Any] = {
            "scenario": self.scenario.name,
            "seed": self.seed,
            "robots": self.count,
            "behaviour": self.scenario.behaviour,
            "sim_time_s": round(sim_time, 6),
            "wall_time_s": round(wall, 3),
            "real_time_factor": round(sim_time / wall, 2) if wall > 0 else None,
            "stop_reason": self.stop_reason,
            "radio": self.radio.stats(),
        }
        if self.warnings:
            result["warnings"] = list(self.warnings)
        failure = merge_result(self.evaluator, result, error)
        if failure is not None:
            error, trace = str(failure), failure.lines
        result["telemetry"] = list(self.telemetry)    # each robot's last telemetry() (telemetry_of made it plain JSON)
        if error:
            result["error"] = error
        if trace:
            result["traceback"] = trace
        return result

    def _stop_behaviours(self) -> Optional[str]:
        """Stop every behaviour even if one's stop() raises (the run's results must still be written)."""
        problem = None
        for i, behaviour in enumerate(self.behaviours):
            try:
                behaviour.stop()
            except USER_CODE_ERRORS as exc:
                problem = problem or str(BehaviourError(i, "stop()", exc))
        return problem

    def trajectory_arrays(self) -> Dict[str, np.ndarray]:
        return trajectory_arrays(self.recording, self.scenario, self.world)


def check_telemetry_fits_the_wire(telemetry: List[Optional[Dict[str, Any]]], robot: Optional[int] = None) -> None:
    """BehaviourError (robot, ``telemetry()``) for telemetry an agent could not send to the hub: every robot's,
    or only ``robot``'s (looked up directly: this runs at every step)."""
    robots = range(len(telemetry)) if robot is None else (robot,)
    for i in robots:
        data = telemetry[i]
        if data is None:
            continue
        try:
            # telemetry_of made it plain JSON already; the rest of the message is the agent's own, at its widest
            encode(widest_telemetry_message(data))
        except ProtocolError as err:
            key = err.field.rpartition("telemetry.behaviour.")[2] if "." in err.field else ""
            said = f"telemetry[{key!r}] {err.problem}" if key else \
                f"{err.problem} (plain JSON only: dict, list, str, numbers, bool, None)"
            problem = ValueError(f"the hub could not be sent this telemetry, so every agent in a lab would stop "
                                 f"on it: {said}")
            raise BehaviourError(i, "telemetry()", problem) from None
