"""The pymunk world: KheperaIV bodies with traction-limited wheels, the object with ground friction, walls.

Top-down 2-D in metres, kilograms and seconds. Friction with the floor follows pymunk's ``examples/tank.py``:
each dynamic body is tied to a "floor" body by a pivot joint (linear friction) and a gear joint (rotational
friction) whose ``max_force`` is the Coulomb limit and whose ``max_bias`` is 0 (so they only resist motion,
never correct position). For the object the floor is the static body; for a robot it is a kinematic body
moving at the commanded wheel velocity, so the robot follows its wheels until the traction limit
mu * m * g is reached -- it cannot push harder than its tyres grip.
"""
from __future__ import annotations

import atexit
import gc
import math
import weakref
from typing import List, Optional

import numpy as np
import pymunk
import pymunk.batch

from onboard.config import ConfigError
from onboard.hal import RobotSpec

from .scenario import Scenario
from .sensing import ObstacleGroup
from .shapes import Geometry, build_geometry, dimension_field, extent_at
from .spawn import object_span, spawn_poses

GRAVITY = 9.81
COLLISION_SLOP_M = 0.0005        # allowed overlap; pymunk's default (0.1) is meant for pixels
ROBOT_CONTACT_FRICTION = 0.4     # plastic shell against foam/cardboard/plastic (combined by product in pymunk)
OBJECT_CONTACT_FRICTION = 1.0
WALL_THICKNESS_M = 0.02

# Every world not yet garbage-collected, so that the ones still alive when the interpreter exits are freed
# while it can (see _free_live_worlds).
_LIVE_WORLDS: weakref.WeakSet = weakref.WeakSet()


# Body fields read and written once per substep for all bodies at once (pymunk.batch), in buffer order.
_MOTION_FIELDS = pymunk.batch.BodyFields.ANGLE | pymunk.batch.BodyFields.VELOCITY | \
    pymunk.batch.BodyFields.ANGULAR_VELOCITY
_VELOCITY_FIELDS = pymunk.batch.BodyFields.VELOCITY | pymunk.batch.BodyFields.ANGULAR_VELOCITY
_POSE_FIELDS = pymunk.batch.BodyFields.POSITION | pymunk.batch.BodyFields.ANGLE


def _as_slice(rows: np.ndarray):
    """``rows`` as a slice when evenly spaced (indexing with it gives views, not copies), else unchanged."""
    if len(rows) >= 2 and rows[1] > rows[0] and np.all(np.diff(rows) == rows[1] - rows[0]):
        return slice(int(rows[0]), int(rows[-1]) + 1, int(rows[1] - rows[0]))
    if len(rows) == 1:
        return slice(int(rows[0]), int(rows[0]) + 1)
    return rows


class SimRobot:
    """One robot's two bodies. Its command, odometry and alive flag live in the world's arrays, so that a
    substep updates every robot with a few numpy operations instead of a Python loop."""

    def __init__(self, world: World, index: int, body: pymunk.Body, wheels: pymunk.Body):
        self._world, self.index = world, index
        self.body = body
        self.wheels = wheels         # kinematic "floor under the tyres"

    @property
    def alive(self) -> bool:
        return bool(self._world._alive[self.index])

    @property
    def left_cmd(self) -> float:
        return float(self._world._commands[self.index, 0])

    @property
    def right_cmd(self) -> float:
        return float(self._world._commands[self.index, 1])

    @property
    def left_odo(self) -> float:
        return float(self._world._odometry[self.index, 0])

    @property
    def right_odo(self) -> float:
        return float(self._world._odometry[self.index, 1])


class World:
    """Physics only: no sensing policy, no behaviours, no drawing."""

    def __init__(self, scenario: Scenario, rng: np.random.Generator, spec: Optional[RobotSpec] = None):
        self.scenario = scenario
        self.spec = spec or RobotSpec(max_wheel_speed_m_s=scenario.robots.max_wheel_speed_m_s)
        self.dt = scenario.physics.dt_s
        self.space = pymunk.Space()
        self.space.iterations = scenario.physics.iterations
        self.space.collision_slop = COLLISION_SLOP_M
        self.time_s = 0.0
        self.geometry: Optional[Geometry] = None
        self.object_body: Optional[pymunk.Body] = None
        self._outline = None
        self._outline_starts: Optional[np.ndarray] = None      # index of each outline ring's first segment
        self.wall_segments = np.zeros((0, 4))
        if scenario.object is not None:
            self._add_object()
        if scenario.arena.walls is not None:
            self._add_walls(scenario.arena.walls)
            if self.geometry is not None:
                self._check_object_fits(scenario.arena.walls)
        self.robots: List[SimRobot] = []
        poses = spawn_poses(self, rng, WALL_THICKNESS_M)
        self._commands = np.zeros((len(poses), 2))     # commanded (left, right) wheel speeds
        self._odometry = np.zeros((len(poses), 2))     # cumulative commanded wheel distances
        self._alive = np.ones(len(poses), dtype=bool)
        for x, y, yaw in poses:
            self._add_robot(x, y, yaw)
        self._batch = pymunk.batch.Buffer()             # filled by pymunk when reading bodies
        self._index_bodies()
        _LIVE_WORLDS.add(self)

    def release(self) -> None:
        """Take everything out of the pymunk space and let go of it; the world cannot step afterwards."""
        space = self.space
        if space is None:
            return
        space.remove(*space.constraints)
        space.remove(*space.shapes)
        space.remove(*space.bodies)
        for robot in self.robots:
            robot.body = robot.wheels = None
        self.object_body = None
        self.space = None

    # --- construction -------------------------------------------------------------------------------
    def _add_object(self) -> None:
        spec = self.scenario.object
        geom = build_geometry(spec)
        self.geometry = geom
        if spec.static:
            body = pymunk.Body(body_type=pymunk.Body.STATIC)
        else:
            body = pymunk.Body(spec.mass, spec.mass * geom.radius_of_gyration_m ** 2)
        body.position = tuple(spec.position)
        body.angle = math.radians(spec.yaw_deg)
        shapes: List[pymunk.Shape] = [pymunk.Poly(body, [tuple(p) for p in piece]) for piece in geom.convex_pieces]
        shapes += [pymunk.Circle(body, r, (cx, cy)) for cx, cy, r in geom.circles]
        for shape in shapes:
            shape.friction = OBJECT_CONTACT_FRICTION
        self.space.add(body, *shapes)
        if not spec.static:
            normal_force = spec.friction * spec.mass * GRAVITY
            # Rotational Coulomb friction of a uniformly loaded footprint: mu * m * g * mean contact radius.
            self._tie_to_floor(body, self.space.static_body, normal_force, normal_force * geom.mean_radius_m)
        self.object_body = body

    def _check_object_fits(self, walls) -> None:
        """The object must start inside the walls, and fit inside them at every waypoint: otherwise pymunk
        pushes it out of the wall at the first step (a different start than the scenario says), or the run
        can only end at its time limit."""
        spec = self.scenario.object
        poses = [("object.position", spec.position[0], spec.position[1], spec.yaw_deg)]
        poses += [(f"path[{i}]", px, py, yaw) for i, (px, py, yaw) in enumerate(self.scenario.path)]
        xmin, ymin, xmax, ymax = walls
        width, height = object_span(self)
        if width > xmax - xmin or height > ymax - ymin:
            # Where it starts does not matter then: say so of the size, the likely typo (centimetres for metres).
            raise ConfigError(dimension_field(spec), f"the object is {width:.3g} x {height:.3g} m, larger than the "
                              f"arena ({xmax - xmin:g} x {ymax - ymin:g} m inside arena.walls); sizes are in metres")
        for field_name, px, py, yaw_deg in poses:
            left, bottom, right, top = extent_at(self.geometry, px, py, math.radians(yaw_deg))
            if left < xmin or bottom < ymin or right > xmax or top > ymax:
                at = "starts" if field_name == "object.position" else "would be at this waypoint"
                raise ConfigError(field_name, f"the object {at} across the arena walls: it covers x "
                                  f"[{left:.2f}, {right:.2f}], y [{bottom:.2f}, {top:.2f}]; the walls are "
                                  f"[{xmin:g}, {ymin:g}, {xmax:g}, {ymax:g}]")

    def _add_walls(self, walls) -> None:
        xmin, ymin, xmax, ymax = walls
        corners = [(xmin, ymin), (xmax, ymin), (xmax, ymax), (xmin, ymax)]
        rows = []
        for a, b in zip(corners, corners[1:] + corners[:1]):
            seg = pymunk.Segment(self.space.static_body, a, b, WALL_THICKNESS_M / 2)
            seg.friction = 1.0
            self.space.add(seg)
            rows.append((*a, *b))
        self.wall_segments = np.asarray(rows, dtype=float)

    def _add_robot(self, x: float, y: float, yaw: float) -> None:
        spec, mass = self.spec, self.scenario.robots.mass_kg
        body = pymunk.Body(mass, pymunk.moment_for_circle(mass, 0.0, spec.radius_m))
        body.position = (x, y)
        body.angle = yaw
        shape = pymunk.Circle(body, spec.radius_m)
        shape.friction = ROBOT_CONTACT_FRICTION
        wheels = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
        wheels.position = (x, y)
        self.space.add(body, shape, wheels)
        traction = self.scenario.robots.traction * mass * GRAVITY
        # Each wheel carries half the weight at half the wheel base from the centre.
        self._tie_to_floor(body, wheels, traction, traction * spec.wheel_base_m / 2.0)
        self.robots.append(SimRobot(self, len(self.robots), body, wheels))

    def _index_bodies(self) -> None:
        """Where each robot's body and wheels sit in pymunk's batch buffers (the space's body order)."""
        self._batch.clear()
        pymunk.batch.get_space_bodies(self.space, pymunk.batch.BodyFields.BODY_ID, self._batch)
        ids = np.frombuffer(self._batch.int_buf(), dtype=np.uintp)
        row_of = {int(body_id): row for row, body_id in enumerate(ids)}
        self._body_count = len(ids)
        self._robot_rows = _as_slice(np.array([row_of[r.body.id] for r in self.robots], dtype=np.intp))
        self._wheel_rows = _as_slice(np.array([row_of[r.wheels.id] for r in self.robots], dtype=np.intp))
        # Written by numpy and read by pymunk: a buffer of its own, since pymunk grows (reallocates) the
        # arrays of a buffer it fills, which must therefore never wrap numpy memory.
        self._velocities = np.zeros((len(ids), 3))      # vx, vy, omega of every body
        self._velocity_batch = pymunk.batch.Buffer()
        self._velocity_batch.set_float_buf(self._velocities)

    def _tie_to_floor(self, body: pymunk.Body, floor: pymunk.Body, max_force: float, max_torque: float) -> None:
        pivot = pymunk.PivotJoint(floor, body, (0.0, 0.0), (0.0, 0.0))
        pivot.max_bias = 0.0
        pivot.max_force = max_force
        gear = pymunk.GearJoint(floor, body, 0.0, 1.0)
        gear.max_bias = 0.0
        gear.max_force = max_torque
        self.space.add(pivot, gear)

    # --- control and stepping -----------------------------------------------------------------------
    def command(self, index: int, left_m_s: float, right_m_s: float) -> None:
        if self._alive[index]:
            self._commands[index] = (left_m_s, right_m_s)

    def kill(self, index: int) -> None:
        """The robot stops for good (battery out, crash): wheels locked, body stays as an obstacle."""
        self._alive[index] = False
        self._commands[index] = 0.0

    def command_many(self, commands: List[tuple]) -> None:
        """``command`` for many robots at once: ``(index, left_m_s, right_m_s)`` rows (one numpy write)."""
        if not commands:
            return
        rows = np.array(commands, dtype=float)
        index = rows[:, 0].astype(np.intp)
        living = self._alive[index]
        self._commands[index[living]] = rows[living, 1:]

    def step(self, substeps: int = 1) -> None:
        forward = self._commands.mean(axis=1)
        turn_rate = (self._commands[:, 1] - self._commands[:, 0]) / self.spec.wheel_base_m
        rolled = self._commands * self.dt          # wheel distance per substep
        for _ in range(substeps):
            self._drive_wheels(forward, turn_rate)
            # Encoders count wheel rotation, slip included: odometry drifts when pushing hard.
            self._odometry += rolled
            self.space.step(self.dt)
            self.time_s += self.dt

    def _drive_wheels(self, forward: np.ndarray, turn_rate: np.ndarray) -> None:
        """Set every wheels body to its robot's commanded motion along the robot's current heading.

        pymunk.batch writes all bodies' velocities, so the other bodies get back the values just read."""
        self._batch.clear()
        pymunk.batch.get_space_bodies(self.space, _MOTION_FIELDS, self._batch)
        # A view of pymunk's buffer: used up before the next batch call can reallocate it.
        motion = np.frombuffer(self._batch.float_buf(), dtype=float).reshape(-1, 4)   # angle, vx, vy, omega
        if len(motion) != self._body_count:
            raise RuntimeError("bodies were added to or removed from the space after the world was built")
        velocities = self._velocities
        velocities[:] = motion[:, 1:]
        heading = motion[self._robot_rows, 0]
        wheels = velocities[self._wheel_rows]      # a view when the rows are evenly spaced (the usual case)
        if wheels.base is velocities:
            np.multiply(forward, np.cos(heading), out=wheels[:, 0])
            np.multiply(forward, np.sin(heading), out=wheels[:, 1])
            wheels[:, 2] = turn_rate
        else:
            rows = self._wheel_rows
            velocities[rows, 0] = forward * np.cos(heading)
            velocities[rows, 1] = forward * np.sin(heading)
            velocities[rows, 2] = turn_rate
        pymunk.batch.set_space_bodies(self.space, _VELOCITY_FIELDS, self._velocity_batch)

    def _read_bodies(self, fields: pymunk.batch.BodyFields, width: int) -> np.ndarray:
        """(bodies, width) copy of ``fields`` for every body in the space, in the space's body order."""
        self._batch.clear()
        pymunk.batch.get_space_bodies(self.space, fields, self._batch)
        values = np.frombuffer(self._batch.float_buf(), dtype=float).reshape(-1, width).copy()
        if len(values) != self._body_count:
            raise RuntimeError("bodies were added to or removed from the space after the world was built")
        return values

    # --- state ----------------------------------------------------------------------------------------
    def robot_poses(self) -> np.ndarray:
        """(N, 3) true x, y, yaw of every robot."""
        return np.ascontiguousarray(self._read_bodies(_POSE_FIELDS, 3)[self._robot_rows])

    def odometry(self) -> np.ndarray:
        """(N, 2) cumulative commanded (left, right) wheel distances, as the encoders count them."""
        return self._odometry.copy()

    def alive(self) -> np.ndarray:
        return self._alive.copy()

    def object_pose(self) -> Optional[np.ndarray]:
        """True x, y, yaw of the object's centroid (ground truth: never given to behaviours)."""
        if self.object_body is None:
            return None
        b = self.object_body
        return np.array([b.position.x, b.position.y, b.angle])

    def _object_outline(self):
        """The object's segments (K, 4) and circles (M, 3) in its own frame; fixed, so computed once."""
        if self._outline is None:
            circles = np.asarray(self.geometry.circles, dtype=float).reshape(-1, 3)
            self._outline = (self.geometry.segments(), circles)
            sizes = [len(ring) for ring in self.geometry.outlines]      # segments() lists each ring's edges in turn
            self._outline_starts = np.cumsum([0] + sizes[:-1]).astype(np.intp) if sizes else None
        return self._outline

    def obstacle_groups(self) -> List[ObstacleGroup]:
        """The object (at its current pose) and the walls, in world coordinates, for the IR model."""
        groups = []
        if self.geometry is not None:
            x, y, yaw = self.object_pose()
            c, s = math.cos(yaw), math.sin(yaw)
            rot = np.array([[c, -s], [s, c]])
            segs, circ = self._object_outline()
            world_segs = np.hstack([segs[:, :2] @ rot.T + (x, y), segs[:, 2:] @ rot.T + (x, y)])
            world_circ = np.column_stack([circ[:, :2] @ rot.T + (x, y), circ[:, 2]]) if len(circ) else circ
            groups.append(ObstacleGroup(world_circ, world_segs, np.array([x, y]), self.geometry.bounding_radius_m,
                                        self._outline_starts))
        if len(self.wall_segments):
            groups.append(ObstacleGroup(np.zeros((0, 3)), self.wall_segments))
        return groups


@atexit.register
def _free_live_worlds() -> None:
    """pymunk frees a space's bodies, shapes and joints through Python callbacks, which do nothing once the
    interpreter is shutting down; a space freed that late leaves its bodies pointing at freed memory, and
    the process dies of SIGSEGV after the script has finished. A world is that late whenever something
    that lives until the end refers to it: a script's own behaviour class, once registered, keeps the
    script's globals (and the ``Simulation`` in them) alive. So free every world still alive at exit, while
    the interpreter is whole."""
    for world in list(_LIVE_WORLDS):
        world.release()
    gc.collect()
