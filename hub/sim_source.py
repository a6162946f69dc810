"""The ``sim`` source: the pymunk world plays the robots and the cameras.

It publishes ground-truth poses as the motion capture, applies the wheel commands the agents send, and
supplies IR and encoder readings for agents that use the ``sim`` driver -- with the simulator's own models
(``sim_backend.sensing``), so a software-in-the-loop run senses what ``khepri sim run`` senses.

Two pacings: real time (a frame every ``1 / frame_hz`` s of wall time, physics in between) and lockstep
(the hub calls :meth:`advance` once per control step, when every agent has answered).

A new run can begin in the world the scenario builds (:meth:`restart`, ``source.reset_each_run``: hub/new_run.py).
"""
from __future__ import annotations

import math
from typing import Dict, List, Optional

import numpy as np

from onboard.config import ConfigError
from onboard.hal import clamp_wheel_speeds
from sim_backend.scenario import Scenario
from sim_backend.sensing import ProximityModel
from sim_backend.world import World

from .sources import PoseFrame, PoseSource


class SimSource(PoseSource):
    not_the_real_robots = "this hub simulates the robots"
    def __init__(self, scenario: Scenario, seed: Optional[int] = None, frame_hz: float = 50.0):
        refuse_agent_restarts(scenario)
        self.scenario = scenario
        self.seed = scenario.seed if seed is None else seed
        self.hub_seed = np.random.SeedSequence(self.seed).spawn(5)[4]    # for the hub's virtual sensors and relay
        self.description = f"sim {scenario.name} (seed {self.seed})"
        self.steps = 0                   # physics substeps done: the simulated clock, which no restart turns back
        self._build(0.0)
        # What the wheels rolled in the worlds before this one. The encoders a frame reports count on across a
        # new run, as a real robot's do when it is carried back to its start; an agent's driver reads deltas.
        self.odometry_before = np.zeros((len(self.world.robots), 2))
        self.count = len(self.world.robots)
        self.control_period = 1.0 / scenario.physics.control_hz
        self.dt = scenario.physics.dt_s
        self.substeps_per_control = int(round(self.control_period / self.dt))
        self.substeps_per_frame = max(1, int(round(1.0 / (frame_hz * self.dt))))
        self.ir = ProximityModel(self.world.spec.radius_m, self.world.spec.proximity_range_m)
        self.next_frame_at: Optional[float] = None

    def _build(self, start_s: float) -> None:
        """The scenario's world at its start, as ``khepri sim run`` builds it for this seed, with the faults due
        that many seconds after ``start_s`` (the simulated time this world starts at)."""
        # Same stream layout as the simulator: stream 0 places the robots, so SIL starts where sim starts.
        streams = np.random.SeedSequence(self.seed).spawn(5)
        self.world = World(self.scenario, np.random.default_rng(streams[0]))
        self.rng_ir = np.random.default_rng(streams[1])
        self.faults = sorted((start_s + f.at_s, f.robot) for f in self.scenario.faults)
        self.killed: List[int] = []
        self.built_at_step = self.steps

    @property
    def pristine(self) -> bool:
        """Whether the world is as built: physics has not stepped since (nothing has moved; only a fault due at the
        start can have fired, as it would in a new world)."""
        return self.steps == self.built_at_step

    def restart(self, now: float) -> PoseFrame:
        """Back to the scenario's start for a new run: the world built again for the same seed (robots, object,
        their velocities, IR noise) and the faults counted from now; the encoders count on. The simulated clock
        runs on, as the hub's log and the agents' frames want it. The first frame of the new world, stamped
        ``now``; in real time it stands for the frame due now."""
        self.odometry_before = self.odometry_before + self.world.odometry()
        self._build(self.time_s)
        if self.next_frame_at is not None:
            self.next_frame_at = now + self.substeps_per_frame * self.dt
        return self.snapshot(now)

    @property
    def time_s(self) -> float:
        return self.steps * self.dt

    def robot_ids(self) -> List[int]:
        return list(range(self.count))

    # --- actuation --------------------------------------------------------------------------------------
    def command(self, robot: int, left_m_s: float, right_m_s: float) -> None:
        # The agent's HAL already clamps; the physics clamps again so a bad agent cannot exceed the robot.
        left, right = clamp_wheel_speeds(left_m_s, right_m_s, self.world.spec.max_wheel_speed_m_s)
        self.world.command(robot, left, right)

    def advance(self, substeps: int) -> None:
        self.world.step(substeps)
        self.steps += substeps

    # --- sensing ----------------------------------------------------------------------------------------
    def snapshot(self, stamp: float) -> PoseFrame:
        """Fire due faults, then the poses of live robots plus every robot's IR and odometry."""
        t = self.time_s
        while self.faults and self.faults[0][0] <= t + 1e-9:
            _, index = self.faults.pop(0)
            self.world.kill(index)
            self.killed.append(index)
        poses = self.world.robot_poses()
        alive = self.world.alive()
        xy, yaw = poses[:, :2], poses[:, 2]
        centre_ranges = np.hypot(*(xy[None, :, :] - xy[:, None, :]).transpose(2, 0, 1))
        readings = self.ir.readings(xy, yaw, centre_ranges, self.world.obstacle_groups(), self.rng_ir,
                                    self.scenario.sensors.proximity_noise)
        ir = np.round(readings, 4).tolist()
        odometry = np.round(self.odometry_before + self.world.odometry(), 6).tolist()
        extras: Dict[int, Dict[str, list]] = {i: {"ir": ir[i], "odo": odometry[i]} for i in range(self.count)}
        live = np.nonzero(alive)[0]
        return PoseFrame(stamp, live.tolist(), poses[live], clock_s=round(t, 6), extras=extras,
                         killed=tuple(self.killed))

    # --- real-time pacing -------------------------------------------------------------------------------
    def poll(self, now: float) -> List[PoseFrame]:
        frame_period = self.substeps_per_frame * self.dt
        if self.next_frame_at is None:
            self.next_frame_at = now
        elif now < self.next_frame_at:
            return []
        else:
            self.advance(self.substeps_per_frame)
        # Fall behind by more than a second (a stalled PC) and the schedule restarts instead of racing.
        behind = now - self.next_frame_at
        self.next_frame_at = now + frame_period if behind > 1.0 else self.next_frame_at + frame_period
        return [self.snapshot(now)]

    def next_due(self, now: float) -> float:
        if self.next_frame_at is None:
            return 0.0
        return max(0.0, self.next_frame_at - now)

    def object_pose(self):
        return self.world.object_pose()

    def control_steps_done(self) -> int:
        return int(math.floor(self.steps / self.substeps_per_control + 1e-9))


def not_simulated_here(scenario: Scenario) -> List[str]:
    """The scenario's sensing faults that ``khepri sim run`` simulates and the hub's sim source does not: said
    before a run (``sil`` and a hub with this source), as a run's result would otherwise differ in silence (a
    behaviour's code for a missing pose never ran in sil)."""
    comm, sensors = scenario.comm, scenario.sensors
    said = []
    if comm.latency_s > 0:
        said.append(f"comm.latency_s ({comm.latency_s:g} s) is not simulated by the hub's sim source: the hub "
                    "relays a broadcast with the next frame, one control step later, as it does in the lab (where "
                    "the radio's own delay adds to that)")
    if sensors.pose_dropout > 0 or sensors.pose_latency_s > 0:
        named = [f"{name} ({value:g}{unit})" for name, value, unit in
                 (("sensors.pose_dropout", sensors.pose_dropout, ""),
                  ("sensors.pose_latency_s", sensors.pose_latency_s, " s")) if value > 0]
        said.append(f"{' and '.join(named)} {'are' if len(named) > 1 else 'is'} not simulated by the hub's sim "
                    "source: every robot gets its true pose (with the scenario's pose noise) in every frame. In the "
                    "lab, a body the motion capture misses for longer than source.stale_s has no pose and its "
                    "robot is held; `khepri sim run` simulates both")
    return said


def refuse_agent_restarts(scenario: Scenario) -> None:
    """A fault that restarts a robot's agent is the simulator's: here the agents are processes of their own
    (``khepri sil`` or real robots), and the world cannot restart them."""
    for i, fault in enumerate(scenario.faults):
        if fault.restart_after_s is not None:
            raise ConfigError(f"faults[{i}].restart_after_s", "agent restarts are simulated by `khepri sim run` "
                              "(and studies) only; with the hub, stop the robot's agent and start it again "
                              "(docs/lab.md: a restarted agent joins the run at once)")
