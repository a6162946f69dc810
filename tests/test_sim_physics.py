"""Real physics: sensing, driving, pushing, range-and-bearing, determinism."""
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from onboard.behaviour import _REGISTRY, Behaviour, register
from onboard.geometry import neighbour_mask, pairwise_range_bearing
from sim_backend.object_spec import ObjectSpec
from sim_backend.runner import Simulation
from sim_backend.sensing import ProximityModel, ir_response
from sim_backend.shapes import build_geometry
from sim_backend.world import World

R = 0.0704


def place(world, index, x, y, yaw):
    body = world.robots[index].body
    body.position = (x, y)
    body.angle = yaw
    world.robots[index].wheels.position = (x, y)
    world.space.reindex_shapes_for_body(body)


@pytest.mark.parametrize("sensor", range(8))
def test_ir_reads_about_0_7_at_5_cm_from_a_wall_in_every_direction(make_scenario, sensor):
    scenario = make_scenario(robots={"count": 1, "spawn": {"x": [0, 0], "y": [0, 0]}},
                             arena={"walls": [-1, -1, 1, 1]}, sensors={"proximity_noise": 0.0})
    sim = Simulation(scenario)
    # Turn the robot so that this sensor faces the east wall (x = 1), with its rim 5 cm from it.
    sensor_angle = sensor * math.pi / 4
    place(sim.world, 0, 1.0 - R - 0.05, 0.0, -sensor_angle)
    sim.step()
    values = sim.frame.proximity[0]
    assert values[sensor] == pytest.approx(0.7, abs=0.03)
    others = [v for k, v in enumerate(values) if k != sensor]
    assert max(others) < values[sensor]


def test_ir_curve_matches_argos():
    assert ir_response(np.array([0.0, 0.039]))[0] == 1.0
    assert ir_response(np.array([0.08]))[0] == pytest.approx(4.14 * math.exp(-33 * 0.08) - 0.085)
    assert ir_response(np.array([0.13, np.inf])).tolist() == [0.0, 0.0]


def test_ir_sees_other_robots_and_the_object_but_not_itself(make_scenario):
    scenario = make_scenario(robots={"count": 2, "spawn": {"x": [-3, -2], "y": [-3, -2]}},
                             object={"shape": "circle", "radius": 0.2, "static": True},
                             sensors={"proximity_noise": 0.0})
    sim = Simulation(scenario)
    place(sim.world, 0, 0.0, -(0.2 + R + 0.03), math.pi / 2)   # facing the object, 3 cm away
    place(sim.world, 1, 2.0, 2.0, 0.0)                          # alone
    sim.step()
    assert sim.frame.proximity[0][0] == 1.0          # saturated below 4 cm
    assert sim.frame.proximity[1].max() == 0.0       # nothing near robot 1, and never itself
    place(sim.world, 0, 0.0, -(0.2 + R + 0.03), math.pi / 2)   # (it turned away during the step)
    place(sim.world, 1, 0.0, -(0.2 + R + 0.03) - (2 * R + 0.05), math.pi / 2)   # 5 cm behind robot 0
    sim.step()
    assert sim.frame.proximity[1][0] == pytest.approx(0.7, abs=0.03)
    assert sim.frame.proximity[0][4] == pytest.approx(0.7, abs=0.03)   # robot 0 sees it behind


L_SHAPE = [[0, 0], [0.4, 0], [0.4, 0.1], [0.1, 0.1], [0.1, 0.4], [0, 0.4]]


@pytest.mark.parametrize("into_mm", [0.0, 0.2, 2.0])
@pytest.mark.parametrize("obj", [{"shape": "box", "size": [0.285, 0.435]}, {"shape": "polygon", "vertices": L_SHAPE}])
def test_a_sensor_pressed_into_the_objects_outline_reads_touching(make_scenario, obj, into_mm):
    """pymunk lets a pushing robot overlap the box by its slop, and then its front sensor, inside the outline,
    found only the far side (or nothing) and read 0, "nothing there", in 171 of lab-6's first 924 steps."""
    world = World(make_scenario(robots={"count": 1, "spawn": {"x": [-3, -2], "y": [-3, -2]}},
                                object={**obj, "position": [0, 0], "static": True}), np.random.default_rng(0))
    outline = world.geometry.outlines[0]
    bottom = outline[:, 1].min()                                  # the face at the bottom, y = bottom
    x = outline[:, 0].min() + 0.75 * (outline[:, 0].max() - outline[:, 0].min())
    xy = np.array([[x, bottom + into_mm / 1000.0 - R]])           # facing +y: sensor 0 on the rim, into the face
    distances = ProximityModel(R).distances(xy, np.array([math.pi / 2]), np.zeros((1, 1)), np.ones(1, bool),
                                            world.obstacle_groups())
    assert distances[0, 0] == 0.0 and ir_response(distances[0, :1])[0] == 1.0
    assert np.isinf(distances[0, 4])                              # the sensor behind it sees nothing
    xy[0, 1] -= 0.03                                              # 3 cm off the face: as before
    distances = ProximityModel(R).distances(xy, np.array([math.pi / 2]), np.zeros((1, 1)), np.ones(1, bool),
                                            world.obstacle_groups())
    assert distances[0, 0] == pytest.approx(0.03 - into_mm / 1000.0, abs=1e-9)


def test_robot_at_0_1_m_s_covers_1_m_in_about_10_s(make_scenario):
    world = World(make_scenario(robots={"count": 1, "spawn": {"x": [0, 0], "y": [0, 0]}}), np.random.default_rng(0))
    place(world, 0, 0.0, 0.0, 0.3)
    world.command(0, 0.1, 0.1)
    world.step(1000)
    x, y, yaw = world.robot_poses()[0]
    assert math.hypot(x, y) == pytest.approx(1.0, abs=0.02)
    assert yaw == pytest.approx(0.3, abs=1e-3)
    assert world.robots[0].left_odo == pytest.approx(1.0)


def test_wheel_commands_turn_the_robot_at_the_differential_drive_rate(make_scenario):
    world = World(make_scenario(robots={"count": 1, "spawn": {"x": [0, 0], "y": [0, 0]}}), np.random.default_rng(0))
    place(world, 0, 0.0, 0.0, 0.0)
    world.command(0, -0.05, 0.05)
    world.step(100)
    omega = 0.1 / 0.1054
    assert world.robot_poses()[0][2] == pytest.approx(omega * 1.0, rel=0.03)


def push_box(make_scenario, pushers):
    """Line `pushers` robots up behind a 4.3 kg box and drive them forward for 5 s."""
    scenario = make_scenario(robots={"count": pushers, "spawn": {"x": [-3, -1], "y": [-3, -1]}},
                             object={"shape": "box", "size": [0.435, 0.285], "mass": 4.3, "friction": 0.3})
    world = World(scenario, np.random.default_rng(0))
    for i in range(pushers):
        place(world, i, -0.0705 * (pushers - 1) + 0.141 * i, -0.1425 - R - 0.001, math.pi / 2)
        world.command(i, 0.1, 0.1)
    world.step(500)
    return world.object_pose()


def test_one_robot_cannot_move_the_loaded_box_but_four_can(make_scenario):
    # 4.3 kg at mu 0.3 needs 12.7 N; one KheperaIV grips with at most 0.9 * 0.54 * 9.81 = 4.8 N.
    assert np.hypot(*push_box(make_scenario, 1)[:2]) < 0.005
    moved = push_box(make_scenario, 4)
    assert moved[1] > 0.3


def test_a_static_object_never_moves(make_scenario):
    scenario = make_scenario(robots={"count": 3, "spawn": {"x": [-3, -1], "y": [-3, -1]}},
                             object={"shape": "clover", "static": True})
    world = World(scenario, np.random.default_rng(0))
    for i in range(3):
        place(world, i, -0.3 + 0.15 * i, -1.2, math.pi / 2)
        world.command(i, 0.2, 0.2)
    world.step(500)
    assert np.allclose(world.object_pose(), 0.0)


@pytest.mark.parametrize("spec, area, centroid", [
    (ObjectSpec(shape="box", size=(7.2, 12.0)), 86.4, (0.0, 0.0)),
    (ObjectSpec(shape="box", size=(0.285, 0.435)), 0.123975, (0.0, 0.0)),
    # a right triangle: area 6, centroid a third of each leg from the right angle
    (ObjectSpec(shape="polygon", vertices=[(0.0, 0.0), (3.0, 0.0), (0.0, 4.0)]), 6.0, (1.0, 4.0 / 3.0)),
])
def test_an_objects_origin_is_its_true_centroid(spec, area, centroid):
    """The body's origin is the footprint's centroid: the object's position, the evaluator's reference and
    the behaviour's target all mean that point. (Sampling the bounding box's corners once put the 12 m box's
    centroid 2.5 cm off, more than the position tolerance.)"""
    geometry = build_geometry(spec)
    outline = np.concatenate(geometry.outlines)
    # The outline was moved by minus the centroid it found: the mean of its vertices says by how much.
    given = spec.vertices if spec.shape == "polygon" else [(0.0, 0.0)]     # a box's corners average to 0
    found = np.mean(given, axis=0) - outline.mean(axis=0)
    assert geometry.area_m2 == pytest.approx(area, rel=2e-3)
    assert np.allclose(found, centroid, atol=1e-9 if spec.shape == "box" else 0.005)


def test_range_and_bearing_match_geometry_and_respect_d_c():
    xy = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 2.0], [5.0, 5.0]])
    yaw = np.array([math.pi / 2, 0.0, -math.pi, 0.0])
    ranges, bearings = pairwise_range_bearing(xy, yaw)
    assert ranges[0, 1] == pytest.approx(1.0)
    assert bearings[0, 1] == pytest.approx(-math.pi / 2)   # robot 0 faces +y: robot 1 is on its right
    assert bearings[1, 0] == pytest.approx(math.pi)        # robot 1 faces +x: robot 0 is behind
    assert bearings[2, 0] == pytest.approx(math.pi / 2)    # robot 2 faces -x: robot 0 (below) is on its left
    mask = neighbour_mask(ranges, 2.5)
    assert mask[0].tolist() == [False, True, True, False]
    assert not mask[:, 3].any()


def test_simulated_range_and_bearing_sensor_reports_only_robots_within_range(make_scenario):
    scenario = make_scenario(robots={"count": 3, "spawn": {"x": [-1, 1], "y": [-1, 1]}},
                             comm={"range_m": 1.0, "range_noise_m": 0.0, "bearing_noise_rad": 0.0})
    sim = Simulation(scenario)
    place(sim.world, 0, 0.0, 0.0, 0.0)
    place(sim.world, 1, 0.0, 0.8, 0.0)
    place(sim.world, 2, 1.5, 0.0, 0.0)
    sim.step()
    seen = sim.robots[0].range_and_bearing.neighbours()
    assert [n.id for n in seen] == [1]
    assert seen[0].range_m == pytest.approx(0.8)
    assert seen[0].bearing_rad == pytest.approx(math.pi / 2)


def test_same_scenario_and_seed_give_the_same_run(make_scenario):
    scenario = make_scenario(robots={"count": 10, "spawn": {"x": [-1, 1], "y": [-1, 1]}},
                             comm={"drop": 0.2}, time_limit_s=8)
    runs = []
    for _ in range(2):
        sim = Simulation(scenario, seed=7)
        sim.run()
        runs.append(sim.trajectory_arrays()["robot_pose"])
    assert np.array_equal(runs[0], runs[1])
    other = Simulation(scenario, seed=8)
    other.run()
    assert not np.array_equal(runs[0], other.trajectory_arrays()["robot_pose"])


def test_aggregate_reduces_the_spread_of_the_swarm(make_scenario):
    scenario = make_scenario(robots={"count": 12, "spawn": {"x": [-2, 2], "y": [-2, 2]}},
                             arena={"walls": [-3, -3, 3, 3]}, time_limit_s=60)
    result = Simulation(scenario).run()
    assert result["final_spread_m"] < 0.5 * result["initial_spread_m"]


def test_an_object_across_the_walls_at_its_start_or_at_a_waypoint_is_refused(make_scenario):
    from onboard.config import ConfigError

    walls = {"walls": [-2, -2, 2, 2]}
    box = {"shape": "box", "size": [0.6, 0.6], "mass": 1.0}
    with pytest.raises(ConfigError) as caught:      # pymunk would push it out of the wall at the first step
        World(make_scenario(arena=walls, object=dict(box, position=[1.9, 0])), np.random.default_rng(1))
    assert caught.value.field == "object.position" and "covers x [1.60, 2.20]" in caught.value.problem
    turned = dict(box, position=[0, 0], size=[1.0, 0.2])
    with pytest.raises(ConfigError) as caught:      # fits lengthwise along x, not once turned by 90 degrees
        World(make_scenario(arena=walls, object=turned, behaviour="transport",
                            path=[[0, 1.0, 0], [0, 1.6, 90]]), np.random.default_rng(1))
    assert caught.value.field == "path[1]" and "would be at this waypoint" in caught.value.problem
    World(make_scenario(arena=walls, object=dict(box, position=[1.65, 0])), np.random.default_rng(1))


@pytest.mark.parametrize("obj, field", [({"shape": "box", "size": [50, 30]}, "object.size"),
                                        ({"shape": "circle", "radius": 25}, "object.radius"),
                                        ({"shape": "clover", "scale": 40}, "object.scale")])
def test_an_object_larger_than_the_arena_is_blamed_on_its_size(make_scenario, obj, field):
    """`size: [50, 30]` (centimetres for metres) was said to start `across the arena walls` at object.position,
    which is where the user would look last."""
    from onboard.config import ConfigError

    with pytest.raises(ConfigError) as caught:
        World(make_scenario(arena={"walls": [-2, -2, 2, 2]}, object=dict(obj, position=[0, 0])),
              np.random.default_rng(1))
    assert caught.value.field == field and "larger than the arena (4 x 4 m inside arena.walls)" in \
        caught.value.problem and caught.value.problem.endswith("sizes are in metres"), caught.value


def test_a_spawn_area_covered_by_an_object_says_how_large_the_object_is(make_scenario):
    """Without walls, `size: [500, 500]` was only `most tries landed on the object`: the size is said too."""
    from onboard.config import ConfigError

    with pytest.raises(ConfigError, match=r"move the area off the object \(object.size makes it 500 x 500 m; sizes"):
        World(make_scenario(object={"shape": "box", "size": [500, 500]}), np.random.default_rng(1))
    # Said only when the object is the cause: with no object at all, a spawn area on a wall gave an
    # AttributeError while the message for the object was being built.
    with pytest.raises(ConfigError, match="most tries landed on the walls"):
        World(make_scenario(robots={"count": 6, "spawn": {"x": [-2.0, -1.95], "y": [-1.5, 1.5]}},
                            arena={"walls": [-2, -2, 2, 2]}), np.random.default_rng(1))


@pytest.mark.parametrize("spawn, count, message", [
    # The area as the user wrote it, beside the room the placement counts (it said "gives 0.116 m²" for 0.04).
    ({"x": [1.0, 1.2], "y": [1.0, 1.2]}, 40, "x [1.0, 1.2], y [1.0, 1.2] is 0.04 m² (0.13 m² with a robot's width "
                                             "round it): make the area larger"),
    ({"x": [-1.0, 1.0], "y": [-1.0, 1.0]}, 10 ** 11, "robots.count: must be <= 5000"),
    ({"x": [-0.3, 0.3], "y": [-0.3, 0.3]}, 6, "most tries landed on the object): move the area off the object"),
])
def test_a_spawn_area_that_cannot_hold_the_robots_is_refused_at_once(make_scenario, spawn, count, message):
    from onboard.config import ConfigError

    with pytest.raises(ConfigError, match=re.escape(message)):
        World(make_scenario(robots={"count": count, "spawn": spawn},
                            object={"shape": "box", "size": [0.6, 0.6]}), np.random.default_rng(1))


def test_a_spawn_area_on_a_wall_is_blamed_on_the_wall_and_robots_start_clear_of_it(make_scenario):
    """The object's query hit the wall segments too: an area on a wall was said to land `on the object`. And
    without an object, robots started up to a half wall thickness inside the wall."""
    from onboard.config import ConfigError
    from sim_backend.world import WALL_THICKNESS_M

    on_wall = {"x": [-2.0, -1.95], "y": [-1.5, 1.5]}
    with pytest.raises(ConfigError, match="most tries landed on the walls"):
        World(make_scenario(robots={"count": 6, "spawn": on_wall}, arena={"walls": [-2, -2, 2, 2]},
                            object={"shape": "box", "size": [0.5, 0.5]}), np.random.default_rng(1))
    near_wall = {"x": [-1.93, -1.90], "y": [-1.9, 1.9]}        # centres 0.07-0.10 m from the wall at x = -2
    world = World(make_scenario(robots={"count": 6, "spawn": near_wall}, arena={"walls": [-2, -2, 2, 2]}),
                  np.random.default_rng(1))
    clear = world.spec.radius_m + WALL_THICKNESS_M / 2.0
    assert all(robot.body.position.x + 2.0 >= clear for robot in world.robots)


def test_a_run_whose_robots_have_all_failed_ends_there(make_scenario):
    scenario = make_scenario(robots={"count": 2}, faults=[{"robot": 0, "at_s": 1.0}, {"robot": 1, "at_s": 2.0}],
                             time_limit_s=60)
    result = Simulation(scenario).run()
    assert result["stop_reason"] == "every robot failed" and result["sim_time_s"] <= 2.2


def test_a_robot_whose_agent_restarts_stops_hears_nothing_and_starts_a_new_behaviour(make_scenario):
    """faults[].restart_after_s: the robot's agent is down that long (wheels stopped, no telemetry, the radio's
    messages lost), then a new behaviour object runs on it, as a restarted agent process would."""
    scenario = make_scenario(robots={"count": 3, "spawn": {"x": [-0.5, 0.5], "y": [-0.5, 0.5]}},
                             faults=[{"robot": 1, "at_s": 1.0, "restart_after_s": 0.5}], time_limit_s=5)
    sim = Simulation(scenario, seed=2)
    first = sim.behaviours[1]
    while sim.step_index * sim.period < 1.2:
        sim.step()
    assert sim.telemetry[1] is None and sim.telemetry[0] is not None       # down: reports nothing
    assert sim.frame.inboxes[1] == []                                      # what was sent to it is lost
    assert sim.behaviours[1] is first and not sim.done()
    while sim.step_index * sim.period < 1.5:
        sim.step()
    assert np.hypot(*sim.world.robots[1].body.velocity) < 0.01             # stopped by the end of the outage
    sim.step()
    assert sim.behaviours[1] is not first and sim.telemetry[1] is not None
    result = sim.run()
    assert result["stop_reason"] != "every robot failed" and sim.world.alive().all()


@pytest.fixture
def drives_only_at_first():
    """A behaviour that commands the wheels in its first half second of simulated time, never after; registered
    for the test only (test_suite_isolation.py)."""
    class DrivesOnlyAtFirst(Behaviour):
        def step(self):
            if self.robot.clock.now() < 0.5:
                self.robot.wheels.set_speeds(0.1, 0.1)

    register("drives_only_at_first")(DrivesOnlyAtFirst)
    yield "drives_only_at_first"
    _REGISTRY.pop("drives_only_at_first", None)


def test_a_restarted_agents_new_behaviour_starts_with_its_wheels_stopped(make_scenario, drives_only_at_first):
    """The robot's HAL kept the old behaviour's last command, and the runner drove it again once the new
    behaviour ran, though that one had commanded nothing: a new agent's wheels start stopped."""
    scenario = make_scenario(behaviour=drives_only_at_first, robots={"count": 1},
                             faults=[{"robot": 0, "at_s": 2.0, "restart_after_s": 1.0}], time_limit_s=6)
    sim = Simulation(scenario, seed=1)
    while sim.step_index * sim.period < 3.1:
        sim.step()
    back = sim.world.robot_poses()[0, :2].copy()
    sim.run()
    assert np.hypot(*(sim.world.robot_poses()[0, :2] - back)) < 0.005


@pytest.mark.parametrize("down_s", [1.0, 0.0])
def test_a_restarted_agents_odometry_counts_from_zero_as_the_kheperaiv_drivers_does(make_scenario,
                                                                                   drives_only_at_first, down_s):
    """The KheperaIV driver counts the encoders from the agent's start; the simulator carried the old agent's
    counts over to the new behaviour (and, restarted at once, counted from the step before)."""
    scenario = make_scenario(behaviour=drives_only_at_first, robots={"count": 1},
                             faults=[{"robot": 0, "at_s": 2.0, "restart_after_s": down_s}], time_limit_s=6)
    sim = Simulation(scenario, seed=1)
    while sim.step_index * sim.period < 2.0:                       # it drives at 0.1 m/s until its agent stops
        sim.step()
    before = sim.robots[0].odometry.read()
    assert before.left_m > 0.15 and before.right_m > 0.15
    while sim.step_index * sim.period < 2.0 + down_s + 0.1:
        sim.step()
    after = sim.robots[0].odometry.read()
    assert (after.left_m, after.right_m) == (0.0, 0.0)
    assert (sim.world.odometry()[0] >= [before.left_m, before.right_m]).all()     # the world's counts run on


SCRIPT_WITH_ITS_OWN_BEHAVIOUR = """
from onboard.behaviour import _REGISTRY, Behaviour, register
from sim_backend.runner import Simulation
from sim_backend.scenario import load_scenario

@register("hold-still")
class HoldStill(Behaviour):
    def step(self):
        self.robot.wheels.set_speeds(0.0, 0.0)

sim = Simulation(load_scenario("lab-6").with_overrides(behaviour="hold-still", params={}))
sim.run(time_limit_s=0.5)
print("finished", sim.step_index)
"""


def test_a_script_that_registers_its_own_behaviour_exits_cleanly(tmp_path):
    # The registry keeps the script's class, hence its globals and the Simulation in them, alive until the
    # interpreter's last moments, when pymunk can no longer free its space safely: this used to end in SIGSEGV.
    script = tmp_path / "mine.py"
    script.write_text(SCRIPT_WITH_ITS_OWN_BEHAVIOUR)
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, str(script)], cwd=root, capture_output=True, text=True, timeout=120,
                          env={"PYTHONPATH": str(root), "PATH": "/usr/bin:/bin"})
    assert done.returncode == 0, done.stderr[-2000:]
    assert "finished 5" in done.stdout


def test_a_robot_flooded_with_messages_keeps_what_a_real_one_would(make_scenario):
    """The agent keeps Radio.INBOX_LIMIT messages between two steps; the simulator's radio did not, so a
    behaviour that flooded its neighbours worked in simulation and lost messages in the lab."""
    from onboard.behaviour import Behaviour, register
    from onboard.hal import Radio

    @register("flood-test")
    class Flood(Behaviour):
        most_received = 0

        def step(self):
            received = self.robot.radio.receive()
            Flood.most_received = max(Flood.most_received, len(received))
            if received:
                assert [m.payload["n"] for m in received[-3:]] == [197, 198, 199]   # the newest are kept
            for n in range(200):
                self.robot.radio.broadcast({"n": n})

    scenario = make_scenario(behaviour="flood-test", robots={"count": 3, "spawn": {"x": [-0.3, 0.3], "y": [-0.3, 0.3]}},
                             time_limit_s=1.0)
    result = Simulation(scenario).run()
    assert "error" not in result, result.get("error")
    radio = result["radio"]
    assert Flood.most_received == Radio.INBOX_LIMIT
    assert radio["dropped_overflow"] > 0
    in_flight = 2 * 600        # the last step's 600 broadcasts, each to the two others
    assert radio["delivered"] + radio["dropped_overflow"] == 2 * radio["sent"] - in_flight


def test_a_behaviour_asking_for_more_than_the_top_speed_drives_at_it_keeping_its_turn(make_scenario):
    """The world drives any speed it is given: the HAL's set_speeds is what holds a behaviour to a KheperaIV's
    0.81 m/s, scaling both wheels together. Every simulated behaviour in the tests asked for less, so a HAL
    that passed 2 m/s on went unnoticed (only the kh4 driver's own clamp was tested)."""

    class FloorIt(Behaviour):
        def step(self):
            self.robot.wheels.set_speeds(2.0, -1.0)

    register("test-floor-it")(FloorIt)
    sim = Simulation(make_scenario(behaviour="test-floor-it", robots={"count": 1, "spawn": {"x": [0, 0],
                                                                                            "y": [0, 0]}}))
    sim.step()
    top = sim.world.spec.max_wheel_speed_m_s
    assert top == pytest.approx(0.81)
    assert (sim.world.robots[0].left_cmd, sim.world.robots[0].right_cmd) == pytest.approx((top, -top / 2))


def test_the_simulated_radio_delays_loses_and_spares_the_dead_as_the_scenario_asks():
    """comm.latency_s, comm.drop and the dead: the radio's docstring promises them, and no test looked. With the
    delay fixed at one step, no loss, or messages handed to dead robots, this file and the equivalence tests
    still passed (their scenarios have no latency or loss; the one with comm.drop compares two runs alike)."""
    from sim_backend.radio import RadioNetwork

    alive = np.array([True, True, False])
    late = RadioNetwork(3, drop=0.0, latency_s=0.25, period_s=0.1, rng=np.random.default_rng(0))
    late.send(5, 0, {"k": 1}, 0.5, np.array([1, 2]))
    inboxes = [[], [], []]
    for step in (6, 7, 8):                   # 0.25 s is three control periods (rounded up), after the next step
        late.deliver(step, inboxes, alive)
        assert inboxes == [[], [], []], step
    late.deliver(9, inboxes, alive)
    assert [[m.payload for m in inbox] for inbox in inboxes] == [[], [{"k": 1}], []]       # robot 2 is dead
    assert late.stats()["delivered"] == 1

    lossy = RadioNetwork(2, drop=0.3, latency_s=0.0, period_s=0.1, rng=np.random.default_rng(2))
    heard = 0
    for step in range(2000):
        inboxes = [[], []]
        lossy.send(step, 0, {"n": step}, step * 0.1, np.array([1]))
        lossy.deliver(step + 1, inboxes, np.array([True, True]))         # no latency: at the next step
        heard += len(inboxes[1])
    assert heard / 2000 == pytest.approx(0.7, abs=0.04)
    assert lossy.stats()["dropped"] + heard == 2000


def test_the_simulated_motion_capture_is_late_noisy_and_lossy_as_the_scenario_asks(make_scenario):
    """sensors.pose_latency_s, pose_noise_m and pose_dropout: what a behaviour's positioning.pose() gets. No test
    ran a scenario with any of them, and a simulator that served every robot its exact, current pose passed."""

    class Driver(Behaviour):
        seen: list = []

        def step(self):
            Driver.seen.append(self.robot.positioning.pose())
            self.robot.wheels.set_speeds(0.1, 0.1)

    register("test-pose-reader")(Driver)

    def run(**sensors):
        Driver.seen = []
        sim = Simulation(make_scenario(behaviour="test-pose-reader", sensors=sensors, robots={
            "count": 1, "spawn": {"x": [0, 0], "y": [0, 0]}}, time_limit_s=60), seed=3)
        truth = []
        for _ in range(300):
            truth.append(sim.world.robot_poses()[0].copy())
            sim.step()
        return sim.period, np.array(truth), Driver.seen

    period, truth, seen = run(pose_latency_s=0.3, pose_noise_m=0.0, pose_noise_rad=0.0, pose_dropout=0.0)
    lag = round(0.3 / period)
    for k in range(lag, 300):                        # three steps late, stamped when it was measured
        assert (seen[k].x, seen[k].y) == pytest.approx(tuple(truth[k - lag][:2]), abs=1e-12), k
        assert seen[k].age_s == pytest.approx(0.3) and seen[k].stamp_s == pytest.approx((k - lag) * period)

    _, truth, seen = run(pose_latency_s=0.0, pose_noise_m=0.05, pose_noise_rad=0.0, pose_dropout=0.0)
    errors = [pose.x - true[0] for pose, true in zip(seen, truth)]
    assert np.std(errors) == pytest.approx(0.05, rel=0.2)

    _, _, seen = run(pose_latency_s=0.0, pose_noise_m=0.0, pose_noise_rad=0.0, pose_dropout=0.5)
    fresh = sum(pose is not None and pose.age_s == 0.0 for pose in seen)
    assert fresh / len(seen) == pytest.approx(0.5, abs=0.1)         # the others: the last pose that came, older


def test_the_simulated_range_and_bearing_is_as_noisy_as_the_scenario_asks(make_scenario):
    """comm.range_noise_m and bearing_noise_rad: the only simulator test of the sensor sets both to 0, and one
    that served exact ranges and bearings passed every test here (the hub's own noise is tested apart)."""

    class Listener(Behaviour):
        heard: list = []

        def step(self):
            if self.robot.id == 0:
                table = self.robot.range_and_bearing.neighbours()
                Listener.heard.append((float(table.ranges_m[0]), float(table.bearings_rad[0])))

    register("test-range-listener")(Listener)
    Listener.heard = []
    sim = Simulation(make_scenario(behaviour="test-range-listener", robots={"count": 2, "spawn": {
        "x": [-0.5, 0.5], "y": [-0.5, 0.5]}}, comm={"range_m": 3.0, "range_noise_m": 0.05, "bearing_noise_rad": 0.1}))
    poses = sim.world.robot_poses()
    true_range = math.hypot(*(poses[1, :2] - poses[0, :2]))
    for _ in range(400):
        sim.step()
    ranges, bearings = np.array(Listener.heard).T
    assert np.mean(ranges) == pytest.approx(true_range, abs=0.01)
    assert np.std(ranges) == pytest.approx(0.05, rel=0.2) and np.std(bearings) == pytest.approx(0.1, rel=0.2)


def test_the_simulated_ir_is_as_noisy_as_the_scenario_asks(make_scenario):
    """sensors.proximity_noise: the IR tests set it to 0, and readings without any noise passed every test here."""

    class Still(Behaviour):
        def step(self):
            pass

    register("test-still")(Still)
    scenario = make_scenario(behaviour="test-still", robots={"count": 1, "spawn": {"x": [0, 0], "y": [0, 0]}},
                             arena={"walls": [-1, -1, 1, 1]}, sensors={"proximity_noise": 0.05})
    sim = Simulation(scenario)
    place(sim.world, 0, 1.0 - R - 0.05, 0.0, 0.0)          # the front sensor's rim 5 cm from the east wall
    readings = []
    for _ in range(300):
        sim.step()
        readings.append(sim.frame.proximity[0][0])
    assert np.mean(readings) == pytest.approx(0.7, abs=0.03) and np.std(readings) == pytest.approx(0.05, rel=0.2)
