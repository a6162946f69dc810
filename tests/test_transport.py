"""The transport behaviour: what works today, and the rule that robots never see the object's true pose."""
import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest

from onboard.behaviour import build_params, get_behaviour
from onboard.behaviours.transport import control as c
from onboard.behaviours.transport.approach import first_travel, seed_heading
from onboard.behaviours.transport.caged import ON_ITS_WAY_WAIT_S
from onboard.behaviours.transport.estimator import (
    encloses,
    median_turn,
    normal_displacement,
    ring_centroid,
    ring_rotation,
    surface_normals,
    surrounds,
)
from onboard.behaviours.transport.params import IMPROVEMENT_FLAGS
from onboard.behaviours.transport.perception import Percept
from onboard.behaviours.transport.tasks import Task
from onboard.config import ConfigError
from onboard.hal.ir_curve import ir_distance_m, ir_response
from sim_backend.runner import Simulation
from sim_backend.scenario import load_scenario


@pytest.fixture(scope="module")
def lab6_run():
    sim = Simulation(load_scenario("lab-6"), seed=1)
    result = sim.run()
    return sim, result


def test_lab6_cages_the_box_and_brings_it_to_the_last_waypoint(lab6_run):
    _, result = lab6_run
    assert result["caged"]
    assert result["cage_size"] >= 4
    assert [w["index"] for w in result["waypoints"]] == [0, 1, 2]
    assert result["completed"], result["failures"]
    assert result["final_position_error_m"] <= 0.05          # issue #3's bar for lab-6 (d_tol is 0.1 m)
    assert result["cage_spacing_m"]["std"] <= 0.05
    for waypoint in result["waypoints"]:
        assert waypoint["centroid_estimation_error_m"] <= 0.05


def test_the_reported_errors_are_the_objects_true_offset_from_its_waypoints(lab6_run):
    """Every bar above is an upper bound on the evaluator's own figures: an error computed from x alone (or 0)
    passed them all. They must be the true object's distance and yaw difference from the waypoint."""
    from sim_backend.metrics import waypoint_error

    sim, result = lab6_run
    truth, (x, y, yaw_deg) = sim.world.object_pose(), sim.scenario.path[-1]
    assert result["final_position_error_m"] == pytest.approx(math.hypot(truth[0] - x, truth[1] - y), abs=1e-9)
    assert result["final_orientation_error_rad"] == pytest.approx(abs(truth[2] - math.radians(yaw_deg)), abs=1e-9)
    assert waypoint_error((1.0, 2.0, 0.1), (1.3, 2.4, 90.0)) == pytest.approx((0.5, math.pi / 2 - 0.1))
    assert waypoint_error((0.0, 0.0, math.radians(179.0)), (0.0, -0.3, -179.0)) == pytest.approx(
        (0.3, math.radians(2.0)))                                  # across +-180 degrees: the short way round


def test_lab6_payload_is_slower_but_reaches_every_waypoint(lab6_run):
    """The 4.3 kg box: same bar as lab-6, and it takes the cage longer than the empty box."""
    result = Simulation(load_scenario("lab-6-payload"), seed=1).run()
    assert result["caged"] and result["completed"], result["failures"]
    assert result["final_position_error_m"] <= 0.05
    assert result["cage_spacing_m"]["std"] <= 0.05
    assert all(w["centroid_estimation_error_m"] <= 0.05 for w in result["waypoints"])
    assert result["time_to_complete_s"] > lab6_run[1]["time_to_complete_s"]


@pytest.mark.parametrize("scenario", ["lab-6", "lab-6-payload"])
@pytest.mark.parametrize("seed", [2, 3, 4, 5])
def test_the_lab_cases_meet_issue_3s_bars_for_seeds_2_to_5(scenario, seed):
    """Issue #3's acceptance for the lab box, the seeds the two tests above do not run (under a second each)."""
    result = Simulation(load_scenario(scenario), seed=seed).run()
    assert result["caged"] and result["completed"], result["failures"]
    assert result["final_position_error_m"] <= 0.05
    assert result["cage_spacing_m"]["std"] <= 0.05


def test_paper25_centroid_estimate_stays_within_3cm_at_every_waypoint():
    """Issue #3's bar for the 25-robot cage (the paper's median error was 0.10-0.61 m): the swarm's filtered
    centroid, from the surface points its IR sees, against the simulator's true centroid at each waypoint."""
    result = Simulation(load_scenario("paper-25-straight"), seed=1).run()
    assert result["caged"] and result["completed"], result["failures"]
    assert len(result["waypoints"]) == 10
    # Issue #3's bar is 0.05 m; the ring centroid of the members' positions alone reaches 0.050 m on this run,
    # the surface points stay under 0.02 m: 0.03 m tells the two apart.
    assert max(w["centroid_estimation_error_m"] for w in result["waypoints"]) <= 0.03


def test_no_task_is_given_twice(lab6_run):
    sim, _ = lab6_run
    space = sim.behaviours[0].space
    owners = {}
    for key, value in space.items("owner/"):
        tid = key[len("owner/"):]
        task = space.get(f"task/{tid}")
        if task and not task["cancelled"] and task["epoch"] == value["epoch"]:
            owners[tid] = value["robot"]
    members = {int(k[len("member/"):]): v["tid"] for k, v in space.items("member/")}
    assert len(set(members.values())) == len(members)                 # one robot per cage slot
    for robot, tid in members.items():
        assert owners[tid] == robot


def reachable_types(root, depth=4):
    seen, found, stack = set(), set(), [(root, 0)]
    while stack:
        obj, level = stack.pop()
        if id(obj) in seen or level > depth:
            continue
        seen.add(id(obj))
        found.add(type(obj).__module__.split(".")[0])
        children = vars(obj).values() if hasattr(obj, "__dict__") else []
        if isinstance(obj, (list, tuple)):
            children = obj
        stack.extend((child, level + 1) for child in children)
    return found


def test_a_robot_hal_holds_no_reference_to_the_world_or_physics():
    sim = Simulation(load_scenario("lab-6"), seed=1)
    modules = reachable_types(sim.robots[0])
    assert "pymunk" not in modules
    assert not any(isinstance(v, type(sim.world)) for v in vars(sim.robots[0]).values())
    assert sim.world not in [getattr(d, "frame", None) for d in vars(sim.robots[0]).values()]


def test_moving_the_true_object_changes_nothing_until_a_sensor_sees_it():
    """Teleport the object 3 m away before any robot is near it: every robot does exactly the same."""
    runs = []
    for teleport in (False, True):
        sim = Simulation(load_scenario("lab-6"), seed=1)
        for _ in range(20):
            sim.step()
        if teleport:
            sim.world.object_body.position = (3.0, 3.0)
            sim.world.space.reindex_shapes_for_body(sim.world.object_body)
        for _ in range(40):
            sim.step()
        assert sim.frame.proximity.max() < 0.1     # nobody's IR has seen anything yet
        runs.append((sim.world.robot_poses(), [b.state for b in sim.behaviours], sim.behaviours[0].space.items()))
    assert np.array_equal(runs[0][0], runs[1][0])
    assert runs[0][1] == runs[1][1]
    assert runs[0][2] == runs[1][2]


def test_profiles_and_bad_parameters():
    cls = get_behaviour("transport")
    faithful = build_params(cls, {"profile": "faithful"})
    assert not faithful.pipeline_allocation and not faithful.equalise_spacing
    assert not any(getattr(faithful, flag) for flag in IMPROVEMENT_FLAGS)
    assert all(isinstance(getattr(faithful, flag), bool) for flag in IMPROVEMENT_FLAGS)
    assert faithful.position_tolerance_m == faithful.push_tolerance_m == 0.1
    assert faithful.attach_timeout_s == math.inf            # the paper's robots never give a task back
    improved = build_params(cls, {})
    assert improved.inter_robot_distance_m == 0.45 and improved.theta_p_deg == 115.0
    with pytest.raises(ConfigError, match=r"^params.profile: must be one of improved, faithful"):
        build_params(cls, {"profile": "fast"})
    with pytest.raises(ConfigError, match=r"^params.barrier_fraction: must be <= 1"):
        build_params(cls, {"barrier_fraction": 1.5})


def test_control_terms_follow_the_paper():
    assert c.u_t((0.0, 0.0), (0.05, 0.0), 60.0, 0.1) == c.ZERO             # within d_tol: no push
    assert c.u_t((0.0, 0.0), (1.0, 0.0), 60.0, 0.1) == pytest.approx((60.0, 0.0))
    behind = (1.0, 0.0)                                                     # object ahead, target ahead
    assert c.is_effective_pusher(behind, (1.0, 0.0), math.radians(115))
    assert not c.is_effective_pusher((-1.0, 0.0), (1.0, 0.0), math.radians(115))
    assert c.u_cp(behind, True, 40, 20) == pytest.approx((40.0, 0.0))
    assert c.u_cp(behind, False, 40, 20) == pytest.approx((20.0, 0.0))
    # u_r is tangential (perpendicular to the radius) and signed by the yaw error.
    assert c.u_r((1.0, 0.0), (0.0, 0.0), 0.5, 600, 0.1) == pytest.approx((0.0, 600.0))
    assert c.u_r((1.0, 0.0), (0.0, 0.0), 0.05, 600, 0.1) == c.ZERO
    # Edge following at I_d: no radial term, pure orbit; too far: pulled in.
    orbit = c.u_edge_follow((0.45, 0.0), 0.45, +1)
    assert orbit[0] == pytest.approx(0.0) and orbit[1] != 0.0
    assert c.u_edge_follow((0.9, 0.0), 0.45, +1)[0] > 0
    # Formation: a neighbour that drifted away is pulled back.
    assert c.u_f({1: (0.6, 0.0)}, {1: (0.45, 0.0)}, 40.0)[0] > 0


def test_centroid_and_rotation_from_the_cage_ring():
    square = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0], [0.7, 0.7]]) + (2.0, 3.0)
    assert ring_centroid(square) == pytest.approx((2.0, 3.0), abs=0.1)
    reference = {i: (math.cos(a), math.sin(a)) for i, a in enumerate((0.0, 1.5, 3.0, 4.5))}
    turned = {i: (math.cos(a + 0.3), math.sin(a + 0.3)) for i, a in enumerate((0.0, 1.5, 3.0, 4.5))}
    assert ring_rotation(turned, reference, (0, 0), (0, 0)) == pytest.approx(0.3)


def test_the_turn_of_an_object_turned_half_round_is_not_read_as_no_turn():
    """Turned about 180 degrees, some edges read +179 and others -179: the median of the sorted values fell
    between them, near 0, and paper-25-straight_rot seed 7 pushed its last legs with the estimate 0.35 m off."""
    reference = {k: 0.0 for k in "abcdef"}
    now = dict(zip("abcdef", map(math.radians, (179.0, -179.5, 178.5, -178.0, 179.5, 0.5))))   # f: an outlier
    assert abs(math.degrees(median_turn((now, reference)))) == pytest.approx(179.75, abs=1.0)
    small = dict(zip("abcd", (0.31, 0.29, 0.30, 0.33)))          # within half a turn: the plain median
    assert median_turn((small, {k: 0.0 for k in "abcd"})) == pytest.approx(0.305, abs=1e-12)


def test_a_reading_turns_back_into_the_distance_it_came_from():
    for distance in (0.045, 0.06, 0.08, 0.11):
        assert ir_distance_m(float(ir_response(np.array([distance]))[0])) == pytest.approx(distance, abs=1e-9)
    assert ir_distance_m(1.0) == ir_distance_m(0.97) == 0.0       # saturated: touching
    assert ir_distance_m(0.0) is None                             # nothing in range


def test_the_surface_estimate_ignores_robots_sliding_along_the_faces():
    """Members see points on a 2 x 2 m box's faces; the box moves and turns a little, and half of the points
    slide along their faces (robots dragged sideways): the translation comes out, the ring centroid drifts."""
    faces = [((1.0, t), (1.0, 0.0)) for t in (-0.6, 0.0, 0.6)] + [((-1.0, t), (-1.0, 0.0)) for t in (-0.6, 0.0, 0.6)] \
        + [((t, 1.0), (0.0, 1.0)) for t in (-0.5, 0.5)] + [((t, -1.0), (0.0, -1.0)) for t in (-0.5, 0.5)]
    reference = {i: point for i, (point, _) in enumerate(faces)}
    yaw, shift = 0.04, (0.3, -0.1)

    def placed(point):
        x, y = c.rotate(point, yaw)
        return (x + shift[0], y + shift[1])

    now = {}
    for i, (point, normal) in enumerate(faces):
        slide = 0.15 if i % 2 else 0.0                             # along the face: perpendicular to its normal
        now[i] = placed((point[0] - normal[1] * slide, point[1] + normal[0] * slide))
    robots = {i: (point[0] + 0.1 * normal[0], point[1] + 0.1 * normal[1]) for i, (point, normal) in enumerate(faces)}
    normals = surface_normals(reference, robots)
    assert normals[1] == pytest.approx((1.0, 0.0)) and normals[6] == pytest.approx((0.0, 1.0))
    moved = normal_displacement(now, reference, normals, (0.0, 0.0), yaw)
    assert moved == pytest.approx(shift, abs=1e-9)
    drifted = np.subtract(ring_centroid(np.asarray(list(now.values()))), shift)
    assert np.hypot(*drifted) > 0.02                              # what the positions' centroid would say
    assert normal_displacement({0: now[0], 3: now[3]}, reference, normals, (0.0, 0.0), yaw) is None  # one axis only



def test_the_surface_estimate_leaves_out_one_point_that_no_longer_sees_its_face():
    """paper-25-zigzag (seed 3 of the grid after the turn-on-the-spot change): one of 18 members' surface points
    jumped off its face, and the least squares put the estimate 0.13 m behind the box for the rest of the run.
    The point farthest off the fit, beyond OUTLIER_M, is left out; points within it count as before."""
    faces = [((1.0, t), (1.0, 0.0)) for t in (-0.6, 0.0, 0.6)] + [((-1.0, t), (-1.0, 0.0)) for t in (-0.6, 0.6)] \
        + [((t, 1.0), (0.0, 1.0)) for t in (-0.5, 0.5)] + [((t, -1.0), (0.0, -1.0)) for t in (-0.5, 0.5)]
    reference = {i: point for i, (point, _) in enumerate(faces)}
    normals = {i: normal for i, (_, normal) in enumerate(faces)}
    shift = (0.3, -0.1)
    now = {i: (x + shift[0], y + shift[1]) for i, (x, y) in reference.items()}
    assert normal_displacement(now, reference, normals, (0.0, 0.0), 0.0) == pytest.approx(shift, abs=1e-9)
    off = {**now, 3: (now[3][0] - 0.4, now[3][1])}                # the robot on the left face sees 0.4 m deeper
    assert normal_displacement(off, reference, normals, (0.0, 0.0), 0.0) == pytest.approx(shift, abs=1e-9)
    near = {**now, 3: (now[3][0] - 0.03, now[3][1])}              # 3 cm: noise, kept in the fit
    moved = normal_displacement(near, reference, normals, (0.0, 0.0), 0.0)
    assert moved[0] == pytest.approx(shift[0] - 0.03 / 5) and moved[1] == pytest.approx(shift[1])

def test_a_branch_skips_a_slot_whose_robot_is_still_attaching():
    """L2's robot is still attaching (no member entry): the branch goes on past it to L3 and L4, and still
    ends at a member more than 2 I_d (0.9 m) from the one before it (L5)."""
    transport = Simulation(load_scenario("lab-6"), seed=1).behaviours[0]
    space = transport.space
    layout = {10: ("S", 0, 0.0), 11: ("L", 1, 0.45), 13: ("L", 3, 1.3), 14: ("L", 4, 1.75), 15: ("L", 5, 5.0)}
    for rid, (branch, index, x) in layout.items():
        space.put(f"member/{rid}", {"tid": f"{branch}{index}", "branch": branch, "index": index})
        space.put(f"pos/{rid}", [x, 0.0, None, None])
    assert transport._chain("L") == [11, 13, 14]
    assert transport._chain("R") == []


def test_a_robot_beside_the_object_slows_down_as_it_gets_ahead_of_its_formation():
    """pace_formation: the way is +y; this robot's formation neighbours (the rear pusher, the robot across the
    object) fell back by the same distance along the way as it slid forward."""
    transport = Simulation(load_scenario("lab-6"), seed=1).behaviours[0]
    transport.formation = {1: (0.2, -0.3), 2: (0.45, 0.0), 3: (-0.2, -0.3)}
    for rid, slot in ((1, "S0"), (2, "L1"), (3, "R1")):
        transport.space.put(f"member/{rid}", {"tid": slot, "branch": slot[0], "index": int(slot[1])})
    transport.space.put("member/4", {"tid": "L2", "branch": "L", "index": 2})
    transport.formation[4] = (0.3, -0.1)
    for rid, normal in ((1, 1.57), (2, 3.14), (4, None)):        # robot 3 died: no heartbeat; 4 lost the object
        transport.space.put(f"pos/{rid}", [0.0, 0.0, normal, None])
    transport.board.refresh_liveness(0.0)
    way = (0.0, 1.0)

    def pace_when_ahead_by(metres: float, rotation: float = 0.0) -> float:
        shifted = {j: c.rotate((r[0], r[1] - metres), rotation) for j, r in transport.formation.items()}
        shifted[3] = transport.formation[3]                        # the dead robot stays where it stopped
        shifted[4] = (0.3, -0.3)                                   # ... and 4 falls back, driving to the object
        transport.percept = SimpleNamespace(neighbours=shifted)
        return transport._pace(way, rotation, 0.0)

    assert pace_when_ahead_by(0.0) == 1.0
    assert pace_when_ahead_by(-0.05) == 1.0                        # behind: catch up at full speed
    assert pace_when_ahead_by(0.02) == pytest.approx(0.6)
    assert pace_when_ahead_by(0.04) == pytest.approx(0.2)
    assert pace_when_ahead_by(0.06) == pytest.approx(0.1)          # farther ahead it slows on ...
    assert pace_when_ahead_by(0.08) == 0.0                         # ... and stops: the object is not coming
    assert pace_when_ahead_by(0.10) == 0.0
    assert pace_when_ahead_by(0.04, rotation=0.3) < 0.3            # the formation turned with the object
    transport.percept = SimpleNamespace(neighbours={})
    assert transport._pace(way, 0.0, 0.0) == 1.0                   # nobody to pace against


def test_a_robot_outside_the_tight_tolerance_arrives_with_the_majority():
    """Six live members hold still at waypoint 0 once arrived; this robot's estimate (a few mm off theirs) is
    outside position_tolerance_m but inside the paper's d_tol. With fewer than half arrived it pushes on;
    with half arrived it arrives too, instead of pushing an object it cannot move alone, forever."""
    transport = Simulation(load_scenario("lab-6"), seed=1).behaviours[0]
    me = transport.robot.id
    for rid in range(6):
        transport.space.put(f"member/{rid}", {"tid": f"L{rid}", "branch": "L", "index": rid})
        transport.space.put(f"pos/{rid}", [float(rid), 0.0, 0.0, None])
    transport.board.refresh_liveness(0.0)
    transport.waypoint, transport.phase = 0, "p"
    others = [rid for rid in range(6) if rid != me]
    for rid in others[:2]:
        transport.board.arrive(0, "p", rid)
    assert transport._waypoint_gate(0.0, False, True) is False      # 2 of 6 arrived: keep pushing
    assert me not in transport.board.arrivals(0, "p")
    assert transport._waypoint_gate(0.0, False, False) is False
    transport.board.arrive(0, "p", others[2])
    assert transport._waypoint_gate(0.0, False, False) is False      # 3 of 6, but outside d_tol too
    assert me not in transport.board.arrivals(0, "p")
    assert transport._waypoint_gate(0.0, False, True) is True        # 3 of 6 and inside d_tol: arrive
    assert me in transport.board.arrivals(0, "p")


def test_a_robot_whose_estimate_disagrees_arrives_once_the_majority_has_waited_barrier_stall_s():
    """Four of five members arrived at a turn and hold still; this robot's yaw estimate is 20 degrees off
    theirs (outside both tolerances), so it would rotate an object it cannot move alone, for ever (a
    14-robot cage sat 750 s like this). After barrier_stall_s of a majority waiting it arrives too."""
    transport = Simulation(load_scenario("lab-6"), seed=1).behaviours[0]
    me = transport.robot.id
    for rid in range(5):
        transport.space.put(f"member/{rid}", {"tid": f"L{rid}", "branch": "L", "index": rid})
        transport.space.put(f"pos/{rid}", [float(rid), 0.0, 0.0, None])
    transport.path = [(0.5, 0.0, 0.0), (0.5, 0.0, 90.0), (0.5, 0.5, 90.0)]
    transport.waypoint, transport.phase = 1, "r"
    stall = transport.params.barrier_stall_s = 3.0      # inside the liveness timeout: no heartbeats needed
    others = [rid for rid in range(5) if rid != me]
    transport.board.arrive(1, "r", others[0])
    transport.board.refresh_liveness(100.0)
    assert transport._waypoint_gate(100.0, False, False) is False          # 1 of 5: no majority yet
    for rid in others[1:]:
        transport.board.arrive(1, "r", rid)
    for now in (101.0, 101.0 + stall / 2, 101.0 + stall - 0.1):
        transport.board.refresh_liveness(now)
        assert transport._waypoint_gate(now, False, False) is False      # held up, but not long enough
        assert me not in transport.board.arrivals(1, "r")
    transport.board.refresh_liveness(101.0 + stall)
    assert transport._waypoint_gate(101.0 + stall, False, False) is True
    assert me in transport.board.arrivals(1, "r")
    assert (transport.waypoint, transport.phase) == (1, "c")   # passed: back onto the waypoint after the turn


def test_only_a_waypoint_that_turns_the_object_has_a_return_phase():
    """After turning at a waypoint the cage pushes the object back onto it (return_after_turning): u_r turns
    a small cage's box about its estimated centroid, but the box also slid, 0.3 m at a 90-degree turn."""
    transport = Simulation(load_scenario("lab-6"), seed=1).behaviours[0]
    path = [(0.5, 0.0, 0.0), (0.5, 0.0, 90.0), (0.5, 0.5, 90.0), (0.5, 0.5, 92.0)]   # lab-6 starts at yaw 0
    assert [transport._final_phase(path, k) for k in range(4)] == ["r", "c", "r", "r"]   # 2 deg: within 4
    transport.params.return_after_turning = False
    assert [transport._final_phase(path, k) for k in range(4)] == ["r"] * 4


@pytest.mark.parametrize("mode, path_turns, expected_deg", [
    ("auto", True, 30.0),                  # a turn asked: the contact normals (they turn with the faces)
    ("auto", False, 45.0),                 # no turn asked: the edges, precise while the yaw is kept
    ("edges", True, 45.0),
    ("contact_normals", False, 30.0),
])
def test_a_small_cage_reads_the_yaw_from_contact_normals_when_its_path_turns(mode, path_turns, expected_deg):
    """Four members round a box: the edges between them say 45 degrees (they slid round the box as they
    turned it), their contact normals say 30 (the faces they press on turned that far)."""
    scenario = load_scenario("lab-6").with_overrides(params={"small_cage_yaw": mode})
    transport = Simulation(scenario, seed=1).behaviours[0]
    ring_then = {0: (1.0, 0.0), 1: (0.0, 1.0), 2: (-1.0, 0.0), 3: (0.0, -1.0)}
    turned = math.radians(45.0)
    ring_now = {k: (x * math.cos(turned) - y * math.sin(turned), x * math.sin(turned) + y * math.cos(turned))
                for k, (x, y) in ring_then.items()}
    for rid in range(4):
        transport.space.put(f"member/{rid}", {"tid": f"L{rid}", "branch": "L", "index": rid})
        transport.space.put(f"pos/{rid}", [*ring_then[rid], round(math.pi + rid * math.pi / 2, 3), None])
    transport.board.refresh_liveness(0.0)
    transport.percept = SimpleNamespace(position=ring_then[transport.robot.id], neighbours={})
    transport.params.path = [(0.0, 0.5, 90.0 if path_turns else 0.0)]     # read at _begin_transport
    transport._begin_transport(0.0)
    for rid in range(4):      # the members slid 45 degrees round the centre; the faces turned 30
        transport.space.put(f"pos/{rid}", [*ring_now[rid], round(math.pi + rid * math.pi / 2 + math.radians(30), 3),
                                           None])
    transport.percept = SimpleNamespace(position=ring_now[transport.robot.id], neighbours={})
    estimate = transport._rotation_since_reference(ring_now, (0.0, 0.0))
    assert math.degrees(estimate) == pytest.approx(expected_deg, abs=0.1)


def test_small_cage_yaw_must_name_a_source():
    from onboard.behaviours.transport.params import TransportParams

    with pytest.raises(ConfigError, match=r"^params.small_cage_yaw: must be one of auto, edges, contact_normals"):
        build_params(get_behaviour("transport"), {"small_cage_yaw": "gyro"})
    assert build_params(get_behaviour("transport"), {"profile": "faithful"}).small_cage_yaw == "edges"
    assert TransportParams().small_cage_yaw == "auto"


def test_a_reinforcer_at_the_object_pushes_straight_on_instead_of_sliding_into_the_rear_member():
    """reinforce_push: behind the cage, 8 cm off the line of travel through the centroid, a spare robot lines
    up sideways while free; once its IR sees the object (beside the rear member) it only pushes forward."""
    transport = Simulation(load_scenario("lab-6-payload"), seed=1).behaviours[0]
    ring = [(0.0, -0.29), (0.21, 0.0), (0.0, 0.36), (-0.21, 0.0)]
    transport.reinforcing = True
    transport.percept = SimpleNamespace(position=(0.08, -0.32), object_peak=0.0)
    free = transport._reinforce_input((0.0, 0.0), (0.0, 1.0), ring)
    assert free[0] < -0.5                                          # slides toward the line
    transport.percept = SimpleNamespace(position=(0.08, -0.32), object_peak=0.9)
    assert transport._reinforce_input((0.0, 0.0), (0.0, 1.0), ring) == (0.0, 1.0)


def _seed_contact_angle(start_deg: float, centre, travel) -> float:
    """Where (the world angle seen from ``centre``, degrees) a seed starting 1.2 m out at ``start_deg``
    touches a 0.2 m disc, driving by seed_heading."""
    start = math.radians(start_deg)
    x, y = centre[0] + 1.2 * math.cos(start), centre[1] + 1.2 * math.sin(start)
    travelled = 0.0
    while math.hypot(x - centre[0], y - centre[1]) > 0.2:
        step = c.scale(c.unit(seed_heading((x, y), centre, travel, 0.8)), 0.01)
        x, y, travelled = x + step[0], y + step[1], travelled + 0.01
        assert travelled < 6.0, "the seed never reached the object"
    return math.degrees(math.atan2(y - centre[1], x - centre[0]))


@pytest.mark.parametrize("start_deg", [0, 45, 90, 135, 180, 225, 300])
def test_the_seed_meets_the_object_behind_its_first_leg(start_deg):
    """seed_from_rear: from any side, the seed circles round and touches a 0.2 m disc on the line of travel
    through the centroid, on the side away from the first waypoint; a robot already behind drives straight in."""
    centre = (1.0, 2.0)
    travel = first_travel(centre, [(1.0, 3.0, 0.0)], 0.0)      # travel +y: the rear is -y
    assert _seed_contact_angle(start_deg, centre, travel) == pytest.approx(-90.0, abs=6.0)
    # No direction of travel (the only waypoint is a turn on the spot): straight at the centroid.
    assert first_travel(centre, [(1.0, 2.0, 90.0)], 0.0) is None
    assert c.unit(seed_heading((2.0, 2.0), centre, None, 0.8)) == pytest.approx((-1.0, 0.0))


@pytest.mark.parametrize("path", [
    [(1.0, 2.0, 0.0), (1.0, 2.9, 0.0)],                        # the path starts where the object lies
    [(1.02, 2.0, 0.0), (1.0, 2.0, 3.0), (1.0, 2.9, 0.0)],      # two waypoints 2 cm off, a 3 degree turn
])
def test_the_seed_meets_the_object_behind_the_first_leg_that_moves_it(path):
    """Waypoints on the object's start only turn it: the seed goes behind the first leg that moves the
    object. (A path starting where the lab box lay let the seed arrive from anywhere: the box spun 10-45
    degrees under a pusher at its corner in 6 of 10 seeds.) A path that first turns the object further
    than ON_LINE_RAD leaves the seed the paper's way, straight at the centroid."""
    centre = (1.0, 2.0)
    travel = first_travel(centre, path, 0.0)
    assert travel == pytest.approx((0.0, 1.0), abs=1e-9)
    assert _seed_contact_angle(200.0, centre, travel) == pytest.approx(-90.0, abs=6.0)
    assert first_travel(centre, [(1.0, 2.0, 90.0), (1.6, 2.0, 90.0)], 0.0) is None
    assert first_travel(centre, [(1.0, 2.0, 0.0), (1.6, 2.0, 0.0)], math.radians(90.0)) is None
    assert first_travel(centre, [(1.0, 2.0, 360.0), (1.6, 2.0, 0.0)], 0.0) == pytest.approx((1.0, 0.0))


def test_a_seed_wedged_on_a_corner_of_the_object_settles_there():
    """paper-25's box moved 4 mm down (as it was before its centroid was fixed), its estimate left at the
    origin: seed 13's seed drives at the corner (-1, -1), where no IR sensor reads contact, and pushed there
    for ever, so the cage never started. It settles after SEED_WEDGED_S still, and the cage grows."""
    from onboard.behaviours.transport.caging import SEED_WEDGED_S

    base = load_scenario("paper-25-straight_rot")
    box = base.object.__class__(**{**vars(base.object), "position": (0.0, -0.0041841)})
    scenario = base.with_overrides(object=box, params={**base.params, "object_estimate": [0.0, 0.0, 0.0]})
    sim = Simulation(scenario, seed=13)
    seed, settled = None, None
    while sim.step_index * sim.period < 80.0:
        sim.step()
        for robot, behaviour in enumerate(sim.behaviours):
            if behaviour.state == "seed" and seed is None:
                seed = robot
        if seed is not None and settled is None and sim.behaviours[seed].state == "caged":
            settled = sim.step_index * sim.period, sim.behaviours[seed].percept.object_peak
    assert seed is not None and settled is not None, "the seed never settled"
    when, peak = settled
    params = sim.behaviours[seed].params
    # Still a wedge (else this scenario no longer tests the rule): it settled without reading contact,
    # having taken its task at about 7 s.
    assert 0.0 < peak < params.proximity_threshold and when >= 7.0 + SEED_WEDGED_S
    members = [b for b in sim.behaviours if b.state == "caged"]
    assert len(members) >= 3                                  # and the branches grow from it


def test_a_ring_that_does_not_enclose_the_estimate_is_not_a_cage():
    """The closure guard's geometry: a ring round the object encloses C_o(0); a folded branch (all members on
    one side of the object) does not, however close its two tips are."""
    around = [(1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0)]
    folded = [(-1.5, -0.3), (-1.2, -0.9), (-0.6, -1.3), (-1.3, -0.5)]
    assert encloses(around, (0.0, 0.0)) and encloses(around, (0.3, 0.2))
    assert not encloses(folded, (0.0, 0.0))
    assert not encloses(around, (2.0, 0.0))


def test_a_robot_stuck_attaching_gives_its_task_back_and_leaves_it_to_others():
    """attach_timeout_s: after that long in attach the robot re-opens its task as a new epoch, cancels the
    successor target it opened (its robot has not joined), goes idle and does not bid for the task again for
    as long -- the next nearest open task gets its bid instead."""
    transport = Simulation(load_scenario("lab-6"), seed=1).behaviours[0]
    board, me = transport.board, transport.robot.id
    task = Task("L2", 1.0, 0.0, "L", 2, 11, 0)
    board.put_task(task)
    board.take(task, me, 0.3)
    board.put_task(Task("L3", 1.4, 0.0, "L", 3, me, 0))
    board.put_task(Task("R1", 3.0, 0.0, "R", 1, 11, 0))
    transport.task, transport.spawned, transport.state, transport.attach_since = task, "L3", "attach", 0.0
    transport.percept = Percept(1.0, 0.1, 0.0, {}, (0.0, -1.0), 0.9, (0.0, 0.0))
    timeout = transport.params.attach_timeout_s
    transport._on_attach(timeout + 0.1)
    assert (transport.state, transport.task, transport.spawned) == ("idle", None, None)
    reopened = board.task("L2")
    assert reopened.epoch == 1 and board.is_open(reopened)
    assert board.task("L3").cancelled
    assert transport._nearest_open_task(timeout + 1.0).tid == "R1"      # L2 is nearer, but given back
    assert transport._nearest_open_task(2 * timeout + 1.0).tid == "L2"  # ... for attach_timeout_s only


def test_a_robot_attaching_past_the_timeout_keeps_its_slot_when_the_branch_grew_past_it():
    """Its successor already joined the cage: the branch goes on without it (_chain), and a fresh robot in
    this slot would open a second L3 behind the settled one, so the robot keeps attaching."""
    transport = Simulation(load_scenario("lab-6"), seed=1).behaviours[0]
    board, me = transport.board, transport.robot.id
    task = Task("L2", 1.0, 0.0, "L", 2, 11, 0)
    board.put_task(task)
    board.take(task, me, 0.3)
    board.join_cage(12, Task("L3", 1.4, 0.0, "L", 3, me, 0))
    transport.task, transport.state, transport.attach_since = task, "attach", 0.0
    transport.percept = Percept(1.0, 0.1, 0.0, {}, (0.0, -1.0), 0.9, (0.0, 0.0))
    transport._on_attach(transport.params.attach_timeout_s + 0.1)
    assert transport.state == "attach" and board.task("L2").epoch == 0


@pytest.mark.parametrize("profile", ["improved", "faithful"])
def test_a_robot_far_from_its_branch_target_travels_fast_and_arrives_at_cruise_speed(profile):
    """travel_speed_m_s (0.2 m/s in the paper-50 and paper-100 scenarios): a long trip to a branch target
    (the 100-robot ring's are 5-25 m) goes at the travel speed; the last travel_fast_beyond_m (3 m, or 1 m
    in the irregular scenarios) less the easing, and any stretch where the IR sees the object, go at the
    cruise speed. The faithful profile travels at the cruise speed throughout."""
    transport = Simulation(load_scenario("lab-6"), seed=1).behaviours[0]
    transport.params = build_params(get_behaviour("transport"), {"profile": profile, "travel_speed_m_s": 0.2})
    board, me = transport.board, transport.robot.id
    task = Task("L2", 10.0, 0.0, "L", 2, 11, 0)
    board.put_task(task)
    board.take(task, me, 10.0)
    transport.task, transport.state, transport.progress = task, "travel", (math.inf, 0.0)
    wheels, p = transport.robot.wheels, transport.params

    def forward_speed_at(x: float, object_peak: float = 0.0) -> float:
        # Heading straight at the target (the object, if seen, to the left), nobody around.
        transport.percept = Percept(x, 0.0, 0.0, {}, (0.0, 1.0), object_peak, (0.0, 0.0))
        transport._on_travel(1.0)
        return (wheels.left + wheels.right) / 2.0

    fast = p.travel_speed_m_s if profile == "improved" else p.cruise_speed_m_s
    assert forward_speed_at(0.0) == pytest.approx(fast)                   # 10 m to go
    assert forward_speed_at(8.0) == pytest.approx(p.cruise_speed_m_s)     # 2 m to go: within 3 m, cruise
    transport.params = build_params(get_behaviour("transport"), {"profile": profile, "travel_speed_m_s": 0.2,
                                                                 "travel_fast_beyond_m": 1.0})
    p = transport.params                                                  # the irregular scenarios' setting
    assert forward_speed_at(8.0) == pytest.approx(fast)                   # 2 m to go: still fast
    assert forward_speed_at(9.4) == pytest.approx(p.cruise_speed_m_s)     # 0.6 m to go
    # The object in the way (it slides along it, turning): no faster than cruise, even 10 m out.
    assert 0.0 < forward_speed_at(0.0, object_peak=0.3) <= p.cruise_speed_m_s
    assert p.travel_speed_m_s == (0.2 if profile == "improved" else p.cruise_speed_m_s)


@pytest.mark.parametrize("profile", ["improved", "faithful"])
def test_the_lowest_bidder_for_a_branch_target_sets_off_during_t_a_and_stops_short_of_it(profile):
    """head_start (ours): while T_a runs, the robot whose bid is the lowest stored for a branch target drives
    toward it instead of standing still for the whole bidding window, and stops HEAD_START_STOP_M short
    until it owns it (on in the paper scenarios). A robot outbid, and every robot in the faithful profile (the
    paper's), stays put."""
    from onboard.behaviours.transport.caging import HEAD_START_STOP_M

    transport = Simulation(load_scenario("lab-6"), seed=1).behaviours[0]
    transport.params = build_params(get_behaviour("transport"), {"profile": profile, "head_start": True})
    board, me, wheels = transport.board, transport.robot.id, transport.robot.wheels
    task = Task("L3", 3.0, 0.0, "L", 3, 11, 0)
    board.put_task(task)

    def speed_at(x: float, now: float) -> float:
        # Heading straight at the target, nobody around, nothing in sight.
        transport.percept = Percept(x, 0.0, 0.0, {}, (0.0, 1.0), 0.0, (0.0, 0.0))
        transport._on_idle(now)
        assert transport.state == "idle"                                   # bidding, not yet the owner
        return (wheels.left + wheels.right) / 2.0

    moving = speed_at(0.0, 0.0)                                            # its bid is the only one
    assert board.best_bid(task)["robot"] == me
    assert moving == (pytest.approx(transport.params.cruise_speed_m_s) if profile == "improved" else 0.0)
    assert speed_at(3.0 - HEAD_START_STOP_M + 0.05, 1.0) == 0.0            # short of the target: waits there
    board.bid(task, me + 1, 0.01)                                          # outbid by a robot nearer it
    assert speed_at(0.0, 2.0) == 0.0


def test_a_seed_whose_agent_restarts_bids_no_more_and_another_robot_takes_its_slot():
    """A restarted agent runs a new behaviour that knows nothing of the old one, while the swarm still holds
    its member entry: its bids are void (TaskBoard.busy). It used to bid anyway, for the nearest open task,
    the seed's own slot re-opened, where it stood nearest; its void bid held off the robots that could take
    it (lab-6 seed 1: the seed slot stayed open 12 s and the cage closed without it). Now it stays a spare."""
    from sim_backend.scenario import Fault

    scenario = load_scenario("lab-6").with_overrides(faults=[Fault(robot=4, at_s=30.0, restart_after_s=3.0)])
    sim = Simulation(scenario, seed=1)
    assert sim.behaviours[4].state == "idle"
    while sim.step_index * sim.period < 60.0:
        sim.step()
        if sim.step_index * sim.period == pytest.approx(29.0):
            assert sim.behaviours[4].state == "caged"                        # the seed, in the cage
    restarted, board = sim.behaviours[4], sim.behaviours[0].board
    bids = [key for key in restarted.space.keys("bid/") if restarted.space.entry(key).writer == 4]
    assert bids == ["bid/S/0"]                          # its old incarnation's; none since the restart
    assert restarted.state == "idle" and restarted.task is None
    seed_task = board.task("S")
    assert seed_task.epoch >= 1 and board.owner(seed_task)["robot"] != 4   # re-opened, and taken by another


def test_a_robot_whose_agent_restarts_while_attaching_gives_its_slot_back():
    """lab-6 seed 4, robot 0 restarted at 50 s while it was attaching: the swarm still said it owned its slot,
    its heartbeats kept it alive so nobody re-opened the slot, and its new bids were void while it owned one.
    The branch stalled and the cage never closed. The restarted robot now re-opens the task it never took."""
    from sim_backend.scenario import Fault

    scenario = load_scenario("lab-6").with_overrides(faults=[Fault(robot=0, at_s=50.0, restart_after_s=3.0)])
    sim = Simulation(scenario, seed=4)
    while sim.step_index * sim.period < 49.5:
        sim.step()
    before = sim.behaviours[0]
    assert before.state in ("travel", "attach") and before.task is not None, before.state
    held = before.task.tid
    result = sim.run()
    assert result["caged"] and result["completed"], result["failures"]
    board = sim.behaviours[1].board
    assert board.task(held).epoch > before.task.epoch        # re-opened as a new epoch


def test_i_d_grows_only_when_no_open_target_gets_a_bid():
    """Out of robots: a target this member opened has waited 3 T_a without a bid. While idle robots are
    bidding for another open target (they bid for the nearest one only, so targets wait their turn), that is
    a queue and I_d stays; once no open target has had a bid for 3 T_a, I_d grows one level."""
    transport = Simulation(load_scenario("lab-6"), seed=1).behaviours[0]
    board, me = transport.board, transport.robot.id
    patience = 3 * transport.params.allocation_time_s
    waiting = Task("L3", 1.0, 0.0, "L", 3, me, 0)
    other = Task("R2", -1.0, 0.0, "R", 2, 11, 0)
    board.put_task(waiting)
    board.put_task(other)
    board.bid(other, 5, 2.0)                                  # robot 5 is idle and bidding for R2
    transport.spawned_times[("L3", 0)] = 0.0
    for now in range(1, 60):
        transport._grow_if_out_of_robots(float(now))
    assert board.grow_level() == 0
    board.take(other, 5, 2.0)                                 # R2 taken: nothing is bid for any more
    for now in range(60, 60 + int(patience)):
        transport._grow_if_out_of_robots(float(now))
    assert board.grow_level() == 0                            # not before 3 T_a without any bid
    for now in range(60 + int(patience), 60 + int(patience) + 5):
        transport._grow_if_out_of_robots(float(now) + 0.5)
    assert board.grow_level() >= 1


def test_i_d_does_not_grow_while_a_live_robot_is_on_its_way_to_its_slot():
    """A target nobody bids for, but robot 5 holds another and has not joined yet: its arrival may close the
    cage, so I_d waits, for ON_ITS_WAY_WAIT_S at most (a robot stuck on its way must not hold the swarm)."""
    transport = Simulation(load_scenario("lab-6"), seed=1).behaviours[0]
    board, me = transport.board, transport.robot.id
    patience = 3 * transport.params.allocation_time_s
    waiting, taken = Task("L3", 1.0, 0.0, "L", 3, me, 0), Task("R2", -1.0, 0.0, "R", 2, 11, 0)
    board.put_task(waiting)
    board.put_task(taken)
    board.take(taken, 5, 2.0)
    transport.spawned_times[("L3", 0)] = 0.0
    start = 10.0 + patience
    board.heartbeat(5, -1.0, 0.2, None, now=start)
    board.refresh_liveness(start)
    for now in range(int(start), int(start) + 3):
        transport._grow_if_out_of_robots(float(now))
    assert board.grow_level() == 0                            # robot 5 is alive and still travelling
    late = start + ON_ITS_WAY_WAIT_S + 1.0                    # stuck on its way: the swarm waits no longer
    board.heartbeat(5, -1.1, 0.2, None, now=late)
    board.refresh_liveness(late)
    transport._grow_if_out_of_robots(late)
    assert board.grow_level() == 1
    board.join_cage(5, taken)                                 # a member now: growth goes on as before
    for now in range(int(late) + 2, int(late) + 5):
        transport._grow_if_out_of_robots(float(now))
    assert board.grow_level() >= 2


def test_three_robots_cage_a_small_box_and_deliver_it():
    """Three robots round a 0.3 m box (ring 3.9 I_d) never caged: while the third travelled to its slot, I_d
    grew and the second member slid on round the box past where the third could reach it."""
    scenario = load_scenario("lab-6").with_overrides(robots=dataclasses.replace(load_scenario("lab-6").robots, count=3))
    box = dataclasses.replace(scenario.object, size=(0.3, 0.3), mass=0.3)
    result = Simulation(dataclasses.replace(scenario, object=box, time_limit_s=300.0), seed=1).run()
    assert result["caged"] and result["cage_size"] == 3 and result["completed"], result["failures"]


def test_a_member_shoved_beyond_its_predecessor_slides_back_toward_it():
    """A cage member corrects its distance to its predecessor by sliding along perp(x_o), the branch's way
    as the paper has it when the predecessor is behind. A member shoved past its predecessor (round a corner)
    would slide away for ever that way: it slides toward the predecessor instead."""
    transport = Simulation(load_scenario("lab-6"), seed=1).behaviours[0]
    task = Task("L2", 0.0, 0.0, "L", 2, 11, 0)
    transport.task, transport.state = task, "caged"
    up = (0.0, 1.0)            # on the bottom face: the object is above, L grows toward +x
    too_far = transport._spacing() + 0.2
    wheels = transport.robot.wheels

    def hold_with_predecessor_at(dx: float) -> None:
        # Facing the object (+y), touching it, the predecessor too far away along the face.
        transport.percept = Percept(0.0, 0.0, math.pi / 2, {11: (dx, 0.0)}, up, 0.9, (0.0, 0.0))
        transport._hold_position(equalise=False)

    hold_with_predecessor_at(-too_far)                 # behind (-x): the paper's case
    assert transport._slide_sign(up) == 1 and wheels.left < wheels.right      # turns left, toward -x
    hold_with_predecessor_at(too_far)                  # beyond it (+x)
    assert transport._slide_sign(up) == -1 and wheels.right < wheels.left     # turns right, toward +x


def test_the_centre_guess_waits_until_the_members_lie_all_round_the_estimate():
    """Before the cage closes, tangents and pipelined targets are taken about _centre_guess(). Members along
    one face of a 7.2 x 12 m object (paper-100) do not surround its centre: their ring centroid lies on that
    face, so the guess stays C_o(0). Once members lie all round it, the ring centroid is used (it follows an
    object that is not where C_o(0) said)."""
    transport = Simulation(load_scenario("lab-6"), seed=1).behaviours[0]
    transport.hint = (0.0, 0.0)
    board = transport.board

    def member(rid: int, x: float, y: float) -> None:
        board.join_cage(rid, Task(f"L{rid}", x, y, "L", rid, None, 0))
        transport.space.put(f"pos/{rid}", [x, y, None, None])

    for k in range(6):                                   # the left face, near its bottom end
        member(k + 1, -3.7, -5.5 + 0.45 * k)
    assert transport._centre_guess() == (0.0, 0.0)
    for k, (x, y) in enumerate([(3.7, -3.0), (3.7, 3.0), (0.0, 6.3)]):    # now all round, shifted by +0.5 m
        member(k + 10, x + 0.5, y)
    guess = transport._centre_guess()
    assert guess != (0.0, 0.0) and -3.7 < guess[0] < 3.7 and -6.0 < guess[1] < 6.0
    assert surrounds([(1, 0), (0, 1), (-1, 0), (0, -1)], (0.0, 0.0))
    assert not surrounds([(1, 0), (0, 1), (-1, 0.1)], (0.0, 0.0))          # a half turn open below


def test_a_robot_that_gets_no_nearer_its_target_gives_the_task_back():
    """A traveller wedged behind a member, or led past its target round the cage, held its slot for good
    (paper-100-zigzag: one held R9 for 5000 s while 60 robots waited without an open task). After
    attach_timeout_s without getting 2 cm nearer, it re-opens the task and goes idle; the faithful profile
    (no timeout) travels for as long as it takes."""
    for profile in ("improved", "faithful"):
        transport = Simulation(load_scenario("lab-6"), seed=1).behaviours[0]
        transport.params = build_params(get_behaviour("transport"), {"profile": profile})
        board, me = transport.board, transport.robot.id
        task = Task("R9", 5.0, 0.0, "R", 9, 11, 0)
        board.put_task(task)
        board.take(task, me, 5.0)
        transport.task, transport.state, transport.progress = task, "travel", (math.inf, 0.0)
        transport.percept = Percept(0.0, 0.0, 0.0, {}, (0.0, 1.0), 0.0, (0.0, 0.0))
        transport._on_travel(0.0)                        # 5 m to go: progress noted at t = 0
        transport._on_travel(60.0)                       # stuck where it was
        assert transport.state == "travel"
        transport._on_travel(1000.0)                     # far past attach_timeout_s (120 s improved)
        if profile == "faithful":
            assert transport.state == "travel"
            continue
        assert (transport.state, transport.task) == ("idle", None)
        assert board.task("R9").epoch == 1 and board.is_open(board.task("R9"))


def test_a_spare_robot_out_of_reach_of_the_mission_counts_as_finished():
    """A spare robot that heard no news of the mission (anything but position heartbeats) for LEFT_BEHIND_S
    is out of reach of it and will never hear `done`: it counts as finished, so a simulation ends with the
    mission instead of at its time limit, whether or not it heard the cage close. Heartbeats alone do not
    count: they say that a robot is alive, not that the mission moved on. It keeps keeping clear, and news
    makes it unfinished again."""
    from onboard.behaviours.transport.behaviour import LEFT_BEHIND_S

    for closed in (True, False):
        transport = Simulation(load_scenario("lab-6"), seed=1).behaviours[0]
        if closed:
            transport.space.put("closed", {"pair": [1, 2]})
        transport.state = "idle"
        transport.percept = Percept(0.0, 0.0, 0.0, {}, (0.0, 1.0), 0.0, (0.0, 0.0))
        for now in range(0, int(LEFT_BEHIND_S) - 1, 5):
            transport._on_idle(float(now))
            if now % 10 == 0:
                transport.space.put(f"arrive/0/p/{now}", 1)                     # news of the mission
        assert not transport.finished
        for now in range(int(LEFT_BEHIND_S), int(3 * LEFT_BEHIND_S), 5):
            transport.space.put("pos/7", [1.0, float(now), None, None])        # only a heartbeat
            transport._on_idle(float(now))
        assert transport.finished and transport.state == "idle", closed
        transport.space.put("arrive/1/p/7", 1)                                 # the cage comes back in range
        transport._on_idle(3 * LEFT_BEHIND_S)
        assert not transport.finished


def test_robots_that_start_out_of_radio_range_of_the_seed_regroup_and_cage(tmp_path):
    """Twelve robots start 3.2-4.3 m from the lab box with a 3 m radio. The seed drives to the box and opens
    its branch tasks where nobody hears them. With regroup_when_cut_off (ours) the others, hearing no robot
    at work for REGROUP_AFTER_S, move toward the object estimate until they hear one: the cage closes and the
    box reaches its waypoints. The faithful profile (the paper's behaviour) waits at the start for ever."""
    scenario = tmp_path / "far-start.yaml"
    scenario.write_text("""
robots: {count: 12, spawn: {x: [-3.6, -3.0], y: [-2.4, -1.2]}}
object: {shape: box, size: [0.285, 0.435], mass: 0.3, position: [0, 0]}
path: [[0, 0.3, 0], [0, 0.6, 0]]
time_limit_s: 400
""")
    result = Simulation(load_scenario(str(scenario)), seed=1).run()
    assert result["caged"] and result["completed"], result["failures"]
    assert result["stop_reason"] == "behaviour finished"
    faithful = load_scenario(str(scenario))
    faithful = faithful.with_overrides(params={"profile": "faithful"})
    assert not Simulation(faithful, seed=1).run()["caged"]


def test_a_run_ends_with_the_mission_when_spare_robots_started_out_of_radio_range(tmp_path):
    """Fourteen robots start 2.4-4.2 m from an L-shaped object with a 3 m radio: the robots the cage needs
    drive to it, and the spares left at the start never hear the mission end. The run still stops soon after
    the object reaches its last waypoint (once the spares heard no news for LEFT_BEHIND_S), not at the time
    limit."""
    from onboard.behaviours.transport.behaviour import LEFT_BEHIND_S

    scenario = tmp_path / "far-spares.yaml"
    scenario.write_text("""
robots: {count: 14, spawn: {x: [-2.5, -1.5], y: [-2.5, -1.0]}}
object: {shape: polygon, vertices: [[0, 0], [1, 0], [1, 0.3], [0.3, 0.3], [0.3, 0.9], [0, 0.9]],
         mass: 0.8, position: [0.5, 0.5]}
path: [[0.8, 0.8, 0], [1.1, 1.1, -45]]
time_limit_s: 900
""")
    # Seed 2 completes (9 of seeds 1-10 do; the L's last turn ends just outside the tolerance in the other).
    result = Simulation(load_scenario(str(scenario)), seed=2).run()
    assert result["completed"], result["failures"]
    assert result["stop_reason"] == "behaviour finished"
    # The spares last heard news as the cage closed or started pushing, so they finish up to LEFT_BEHIND_S
    # later; the mission's end is what they wait out, not the 900 s limit.
    assert result["sim_time_s"] <= result["time_to_cage_s"] + result["time_to_complete_s"] + LEFT_BEHIND_S


def test_a_disc_is_judged_by_its_position_alone(tmp_path):
    """Eight robots move a 0.3 m disc two waypoints. Pushing spins it, and nothing the robots sense tells how
    a disc turned, so result.json reports its orientation error but completion depends on position only."""
    scenario = tmp_path / "disc.yaml"
    scenario.write_text("""
robots: {count: 8, spawn: {x: [-1.5, -0.5], y: [0.8, 1.6]}}
object: {shape: circle, radius: 0.3, mass: 0.4, position: [0.2, -0.1]}
path: [[0.6, -0.1, 0], [0.6, 0.4, 0]]
time_limit_s: 600
""")
    result = Simulation(load_scenario(str(scenario)), seed=1).run()
    assert result["caged"] and result["completed"], result["failures"]
    assert all(w["position_error_m"] <= 0.1 for w in result["waypoints"])
    assert max(w["orientation_error_rad"] for w in result["waypoints"]) > math.radians(5.72)   # spun: reported


HEAVY_BOX = """
robots: {count: 8, spawn: {x: [-1.4, -0.6], y: [-1.4, -0.6]}}
object: {shape: box, size: [0.4, 0.4], mass: 4.3, friction: 0.4, position: [0, 0]}
path: [[0.3, 0, 0], [0.6, 0, 0]]
time_limit_s: 200
"""


def test_a_cage_that_cannot_move_its_object_says_why(tmp_path):
    """A 4.3 kg box with friction 0.4 (16.9 N) and eight robots, four of them in the cage and none of the others
    pushing (reinforce_when_stalled_s: 0): the box stays put, and the failures say so, with the force and what
    to change."""
    scenario = tmp_path / "heavy.yaml"
    scenario.write_text(HEAVY_BOX + "params: {reinforce_when_stalled_s: 0}\n")
    result = Simulation(load_scenario(str(scenario)), seed=1).run()
    assert result["caged"] and not result["completed"]
    stuck = [f for f in result["failures"] if "after the cage closed" in f]
    assert len(stuck) == 1 and "16.9 N" in stuck[0] and "reinforce_push: true" in stuck[0], result["failures"]


def test_the_robots_left_out_push_a_box_too_heavy_for_the_cage_once_it_stalls(tmp_path):
    """The same box with the default parameters: the cage's pushers cannot move it, the four spares see the
    cage stall (reinforce_when_stalled_s) and push from behind, and it reaches both waypoints. The swarm does
    not know the object's mass; a light object never stalls, so lab-6 runs as before."""
    scenario = tmp_path / "heavy.yaml"
    scenario.write_text(HEAVY_BOX)
    sim = Simulation(load_scenario(str(scenario)), seed=1)
    result = sim.run()
    assert result["caged"] and result["completed"], result["failures"]
    assert result["final_position_error_m"] <= 0.1
    spares = [b for b in sim.behaviours if not b.board.is_member(b.robot.id)]
    assert spares and all(b.push_stalled for b in spares)


@pytest.mark.parametrize("seed", [1, 7])
def test_a_stalled_cage_does_not_spin_a_wide_heavy_box_on_a_noisy_yaw_estimate(make_scenario, seed):
    """A new user's 4 kg 0.6 m box with 10 robots: 6 members, one behind it. While it stood still, the members
    shuffling along its faces swung the yaw estimate from the edges between them (most cross a corner) by up
    to 30 degrees. hold_yaw_while_pushing turned the box 17.5 degrees in 2 s to correct it (seed 1: 0.94 m
    and 51 degrees off); it now holds the yaw only while the push gets somewhere, and a cage this sparse
    reads the yaw from its members' contact normals and the edges together (seed 7 ended 7 degrees off on
    the edges alone). The four spares push too once the cage stalls: they stopped 0.13 m short of each
    waypoint, where the members' bare ring centroid, which leads the box, said the cage had arrived (seed 1:
    0.115 m off at the end); they now judge by the members' estimate, and the box arrives, square."""
    scenario = make_scenario(behaviour="transport", robots={"count": 10, "spawn": {"x": [-2, -1], "y": [-2, -1]}},
                             object={"shape": "box", "size": [0.6, 0.6], "mass": 4.0, "position": [0, 0]},
                             path=[[0.6, 0, 0], [1.2, 0, 0]], arena={"walls": [-3, -3, 3, 3]},
                             comm={"range_m": 3.0}, time_limit_s=400)
    sim = Simulation(scenario, seed=seed)
    result = sim.run()
    assert result["caged"] and result["completed"], result["failures"]
    assert result["final_position_error_m"] <= 0.1, result["failures"]
    assert abs(result["final_orientation_error_rad"]) < math.radians(5.0), result["failures"]
    assert all(b.push_stalled for b in sim.behaviours if not b.board.is_member(b.robot.id))


def test_the_side_members_of_a_sparse_cage_hold_beside_a_box_its_pushers_cannot_move(make_scenario):
    """A new user's 1.0 x 0.8 m box of 4 kg with 16 robots, an 8-member cage with one member behind it: while
    the box stood still, the side members slid round its front corners, the estimate 0.2 m ahead with them,
    and the spares that joined once the push stalled shoved the box 0.4-0.8 m past the waypoint (0 of 6 runs).
    They now keep pace with the members that push from behind, and the box arrives."""
    robots = {"count": 16, "spawn": {"x": [-3.0, -1.2], "y": [-2.0, 0.0]}}
    scenario = make_scenario(behaviour="transport", robots=robots,
                             object={"shape": "box", "size": [1.0, 0.8], "mass": 4.0, "friction": 0.5,
                                     "position": [0, 0]},
                             path=[[1.0, 0.0, 0]], arena={"walls": [-3.5, -3.0, 3.5, 3.5]}, time_limit_s=500)
    result = Simulation(scenario, seed=1).run()
    assert result["caged"] and result["completed"], result["failures"]
    assert result["final_position_error_m"] <= 0.1, result["failures"]
    assert 6 <= result["cage_size"] < 10       # a sparse cage: the pacing this test is about


def test_the_stuck_hint_offers_reinforce_push_only_when_the_spares_did_not_push(make_scenario):
    from sim_backend.transport_metrics import TransportEvaluator

    def hint_with(params, robots=8):
        scenario = make_scenario(behaviour="transport", robots={"count": robots}, params=params,
                                 object={"shape": "box", "size": [0.4, 0.4], "mass": 4.3, "friction": 0.4},
                                 path=[[0.5, 0, 0]])
        evaluator = TransportEvaluator.__new__(TransportEvaluator)
        evaluator.scenario, evaluator.pose_at_closure, evaluator.members = scenario, (0.0, 0.0, 0.0), [0, 1, 2, 3]
        (hint,) = evaluator._stuck_hint((0.0, 0.0, 0.0))
        return hint

    assert "pushed too once the push stalled for 15 s" in hint_with({})
    assert "a smaller params.inter_robot_distance_m (more members behind it)" in hint_with({})
    assert "reinforce_push: true" in hint_with({"reinforce_when_stalled_s": 0})
    assert "reinforce_push: true" in hint_with({"profile": "faithful"})
    assert "reinforce_push" not in hint_with({"reinforce_push": True})
    # Every robot a member: there were none left out to push (a 6-robot cage of a heavy disc was told they had).
    alone = hint_with({}, robots=4)
    assert "left out" not in alone and "reinforce_push" not in alone and "more robots" in alone, alone


def test_a_run_stopped_soon_after_its_cage_closed_is_not_blamed_on_friction():
    """`khepri sim run lab-6 --time-limit 68` (seed 1 cages at 63.6 s, then settles for 10 s) said `the object
    moved 0.00 m after the cage closed: 4 members against 0.9 N of floor friction ...; more robots, less
    friction`: the cage had not pushed yet. Now the failures say the run ended too soon to judge the push."""
    scenario = load_scenario("lab-6").with_overrides(time_limit_s=68.0)
    result = Simulation(scenario, seed=1).run()
    assert result["caged"] and not result["completed"], result["failures"]
    assert not any("floor friction" in f for f in result["failures"]), result["failures"]
    (soon,) = [f for f in result["failures"] if "too soon to judge the push" in f]
    assert soon.startswith("the run ended 4.") and "settles for 10 s" in soon and "--time-limit" in soon


def test_a_run_that_ended_before_its_time_limit_is_not_told_to_take_a_longer_one():
    """A sil run whose agent was killed 0.6 s after closure said `give it a longer time limit` of a run whose
    limit was 250 s. A run that stopped early (crashed, killed, Ctrl-C) is not judged, and says so."""
    scenario = load_scenario("lab-6")
    result = Simulation(scenario, seed=1).run(time_limit_s=68.0)    # as if stopped at 68 s
    (soon,) = [f for f in result["failures"] if "after the cage closed" in f]
    assert soon.endswith(f"of its {scenario.time_limit_s:g} s time limit (see its stop_reason): the push was not "
                         "judged") and "--time-limit" not in soon


def test_sil_says_an_agent_killed_by_a_signal_by_its_name():
    from hub.sil import exit_text

    assert exit_text(-9) == "was killed by SIGKILL (exit code -9)" and exit_text(1) == "exited with code 1"
    assert exit_text(-200) == "exited with code -200"


def test_the_stuck_hint_does_not_offer_reinforce_push_when_all_the_robots_are_too_weak(make_scenario):
    from sim_backend.transport_metrics import TransportEvaluator

    scenario = make_scenario(behaviour="transport", robots={"count": 6},
                             object={"shape": "box", "size": [0.3, 0.4], "mass": 20.0, "friction": 0.3},
                             path=[[0.5, 0, 0]])
    evaluator = TransportEvaluator.__new__(TransportEvaluator)
    evaluator.scenario, evaluator.pose_at_closure, evaluator.members = scenario, (0.0, 0.0, 0.0), [0, 1, 2, 3]
    (hint,) = evaluator._stuck_hint((0.0, 0.0, 0.0))
    assert "58.9 N" in hint and "all 6 robots together push at most 28.6 N" in hint
    assert "reinforce_push" not in hint


def test_the_stuck_hint_names_a_wall_beside_the_object_not_the_floor_friction(make_scenario):
    """A 0.4 kg box stuck 0.4 m from a wall was said to be held by `1.2 N of floor friction`: its members had
    caged the wall too. Beside a wall the hint says so; 1 m from it, it blames the friction as before."""
    from sim_backend.transport_metrics import TransportEvaluator
    from sim_backend.world import World

    def hint_at(y):
        scenario = make_scenario(behaviour="transport", robots={"count": 10, "spawn": {"x": [-1, 0], "y": [0, 1]}},
                                 object={"shape": "box", "size": [0.5, 0.5], "mass": 0.4, "position": [0, -1]},
                                 path=[[1.0, -1, 0]], arena={"walls": [-2, -2, 2, 2]})
        evaluator = TransportEvaluator(scenario, World(scenario, np.random.default_rng(1)))
        evaluator.pose_at_closure, evaluator.members = (0.0, y, 0.0), [0, 1, 2, 3]
        (hint,) = evaluator._stuck_hint((0.0, y, 0.0))
        return hint

    beside = hint_at(-1.35)
    assert beside.startswith("the object moved 0.00 m after the cage closed, 0.40 m from an arena wall where robots "
                             "need about 0.54 m") and "caged the wall" in beside and "friction" not in beside
    assert "floor friction" in hint_at(-0.75)


def test_a_small_cage_turning_a_box_in_place_leaves_it_on_the_waypoint(make_scenario):
    """A 5-member cage turned a 0.8 x 0.5 m box by 90 degrees at its first waypoint and left it 0.30 m off
    (seed 1); its own estimate knew (0.03 m). Now it pushes the box back before the next leg."""
    scenario = make_scenario(behaviour="transport", robots={"count": 12, "spawn": {"x": [-2.2, -1.0],
                                                                                   "y": [-2.2, -1.0]}},
                             object={"shape": "box", "size": [0.8, 0.5], "mass": 0.6},
                             path=[[0.5, 0, 0], [0.5, 0, 90], [0.5, 0.6, 180]],
                             arena={"walls": [-2.5, -2.5, 2.5, 2.5]}, time_limit_s=160)
    result = Simulation(scenario, seed=1).run()
    turned = result["waypoints"][1]
    assert turned["position_error_m"] < 0.05 and turned["orientation_error_rad"] < math.radians(5.72)


LAB_BOX = """
robots: {count: 6, spawn: {x: [-1.2, -0.6], y: [-1.2, -0.6]}}
object: {shape: box, size: [0.285, 0.435], mass: 0.3, position: [0, 0]}
path: [[0, 0.3, 0], [0, 0.6, 0], [0, 0.9, 0]]
comm: {range_m: 3.0}
arena: {walls: [-2.0, -2.0, 2.0, 2.0]}
"""


def lab_box_with_a_death(path, robot: int, at_s: float, time_limit_s: float, seed: int) -> Simulation:
    """The lab-6 setup (6 robots, the paper's foam box, three waypoints to (0, 0.9)) with one robot dead."""
    path.write_text(LAB_BOX + f"time_limit_s: {time_limit_s}\nfaults: [{{robot: {robot}, at_s: {at_s}}}]\n")
    return Simulation(load_scenario(str(path)), seed=seed)


def test_a_seed_that_dies_before_closure_is_replaced_and_the_box_still_arrives(tmp_path):
    """lab-6 with robot 4, the elected seed of seed 1 (behind the box), dead at 40 s, before the cage closed.
    The cage used to close through the dead seed with its three live members beside and ahead of the box:
    nobody pushed, their ring centroid slid along with them and the box never moved (final error 0.90 m).
    Now the seed's successors declare it dead, task S is re-opened, a spare becomes the new seed behind the
    box and the cage closes through it."""
    sim = lab_box_with_a_death(tmp_path / "dead-seed.yaml", robot=4, at_s=40, time_limit_s=200, seed=1)
    result = sim.run()
    assert result["caged"] and result["completed"], result["failures"]
    # 0.045 m until side robots far ahead of their formation stopped (PACE_STOP_M, 2026-11-22): 0.058 m since,
    # and 0.065 m since I_d waits for a robot on its way to its slot (ON_ITS_WAY_WAIT_S); this new seed settles
    # behind the dead one, so the sides look ahead of it (docs/behaviour.md section 8).
    assert result["final_position_error_m"] <= 0.07
    board = sim.behaviours[0].board
    seed = board.seed_member()
    assert seed is not None and seed != 4 and 4 not in board.members()    # the dead seed no longer counts
    assert board.task("S").epoch == 1


HEXAGON = """
robots: {count: 10, spawn: {x: [0.8, 1.8], y: [-0.8, 0.8]}}
object: {shape: polygon, vertices: [[0.3031, 0.175], [0, 0.35], [-0.3031, 0.175], [-0.3031, -0.175], [0, -0.35],
                                    [0.3031, -0.175]], mass: 0.8}
path: [[-0.6, 0, 0], [-1.2, 0, 0]]
time_limit_s: 300
faults: [{robot: 2, at_s: 5}]
"""


def test_a_bidder_that_dies_holding_the_lowest_bid_does_not_hold_the_task_for_ever(tmp_path):
    """Robot 2, the lowest bidder for the seed's task on seed 2, dies 5 s into the 7 s bidding window. Its bid
    stayed the lowest, nobody took the task, and every robot idled until the run ended as "behaviour finished"
    at 60 s with no cage. The task opens again when the winner has not taken it liveness_timeout_s after T_a."""
    path = tmp_path / "hexagon.yaml"
    path.write_text(HEXAGON)
    sim = Simulation(load_scenario(str(path)), seed=2)
    result = sim.run()
    assert result["caged"] and result["completed"], result["failures"]
    task = sim.behaviours[0].board.task("S")
    assert task.epoch == 1 and sim.behaviours[0].board.seed_member() != 2


def test_a_winner_gets_its_whole_window_from_when_this_robot_first_saw_it_win():
    """Timed from the first bid of the task instead, a winner whose bid came late (it was busy, or its bid came
    over several slow radio hops) lost its task before its own take could come back: in a line of 25 robots
    with 1-2 s of radio latency the seed's task re-opened every 11 s and the cage never closed."""
    sim = Simulation(load_scenario("lab-6"), seed=1)
    sim.step()
    robot0 = sim.behaviours[0]
    board, t0 = robot0.board, 100.0
    board.bid(board.task("S"), 4, 0.9)
    assert not robot0._take_won_task(t0)
    board.bid(board.task("S"), 5, 0.5)                 # robot 5 bids lower 8 s later: it wins from here
    assert not robot0._take_won_task(t0 + 8.0)
    assert not robot0._take_won_task(t0 + 11.5) and board.task("S").epoch == 0
    assert not robot0._take_won_task(t0 + 8.0 + 10.9) and board.task("S").epoch == 0
    robot0._take_won_task(t0 + 8.0 + 11.0)             # T_a + liveness_timeout_s without its take: gone
    assert board.task("S").epoch == 1


def test_a_branch_member_that_dies_before_closure_still_cages_and_the_box_still_arrives(tmp_path):
    """lab-6 with robot 2, the first of the right branch in seed 1 (beside the box), dead at 45 s, before the
    cage closed. It stays in its place and cages, but neither pushes nor reports: the ring centroid of the
    three live members alone was 0.09 m off, and the cage pushed that point to the waypoints (final error
    0.16 m, the box 10 degrees off). The estimate now counts the dead member where it stopped."""
    sim = lab_box_with_a_death(tmp_path / "dead-branch-member.yaml", robot=2, at_s=45, time_limit_s=200, seed=1)
    result = sim.run()
    assert result["caged"] and result["completed"], result["failures"]
    assert result["final_position_error_m"] <= 0.05
    board = sim.behaviours[0].board
    assert board.members()[2]["tid"] == "R1"          # still a link of the chain: it was not replaced
    assert sim.behaviours[0].ring_offset is not None   # ... and the estimate counted it


def test_a_member_that_dies_while_pushing_leaves_a_cage_that_still_delivers_the_box(tmp_path):
    """lab-6 seed 2 cages the box with three members (robots 0 and 1 beside it, 3 behind); robot 1 dies at
    76.7 s, after the first waypoint. Two live members were too few for the estimate: it ran on at the
    filter's last velocity, the cage followed it and the box ended 0.74 m off. Now the estimate adds to the
    two live members' centroid its offset to the object's when transport began, and holds the yaw."""
    sim = lab_box_with_a_death(tmp_path / "dead-while-pushing.yaml", robot=1, at_s=76.7, time_limit_s=160, seed=2)
    result = sim.run()
    assert result["completed"], result["failures"]
    assert result["final_position_error_m"] <= 0.05
    assert sim.behaviours[0].offset_members == {0, 3}      # the estimate no longer counts robot 1


def light_triangle(make_scenario, time_limit_s: float):
    """A 0.5 kg triangle whose first waypoint lies 0.5 m from it (a user's scenario, docs/behaviour.md section 8)."""
    return make_scenario(behaviour="transport",
                         robots={"count": 8, "spawn": {"x": [-2.0, -0.8], "y": [-2.0, -0.8]}},
                         object={"shape": "polygon", "vertices": [[0, 0], [0.3, 0.6], [0.6, 0]],
                                 "mass": 0.5, "position": [0.3, 0.2]},
                         path=[[0.3, 0.7, 0], [-0.3, 0.7, 0]],
                         arena={"walls": [-2.5, -2.5, 2.5, 2.5]}, time_limit_s=time_limit_s)


def test_a_robot_attaching_on_a_corner_its_ir_barely_sees_does_not_shove_the_object(make_scenario):
    """The robot attaching at R1 meets a 60-degree corner of the triangle between two of its IR rays, reads
    0.1-0.6 (below the 0.7 of contact) and drove on into it: it shoved the object 0.47 m before the cage had
    formed, and the ring went on forming round where the object had been. Now, having driven 0.12 m toward
    the object (the IR's range) without touching it, it knows it pushes it, and slides instead."""
    sim = Simulation(light_triangle(make_scenario, time_limit_s=100), seed=1)
    sim.run()
    x, y, _ = sim.world.object_pose()
    assert math.hypot(x - 0.3, y - 0.2) < 0.15


def test_a_cage_with_nobody_behind_its_object_does_not_chase_it_away_from_the_waypoint(make_scenario,
                                                                                         monkeypatch):
    """Without the corner check above, the triangle drifts 0.5 m while it is caged and the ring closes with
    every member on the waypoint's side of it. Those members lose the object as u_t draws them toward the
    waypoint; keep_contact sends them back into it, which pushed it away from the waypoint: 1.2 m from the
    last one at 330 s, on its way 2.1 m into the wall. The spares now see the cage make no progress toward
    its waypoint (reinforce_when_stalled_s) and push from behind: 0.13 m (section 8). Since I_d waits for a
    robot on its way to its slot (ON_ITS_WAY_WAIT_S), this run's cage closes later (288 s, 6 members) round the
    drifted triangle and delivers it 0.17 m from the last waypoint without stalling; the spares' push on a stall
    is tested on a heavy box (test_the_robots_left_out_push_a_box_too_heavy_for_the_cage_once_it_stalls)."""
    from onboard.behaviours.transport.caging import CagingPhases

    monkeypatch.setattr(CagingPhases, "_shoving", lambda self, now, contact: False)
    sim = Simulation(light_triangle(make_scenario, time_limit_s=330), seed=1)
    sim.run()
    x, y, _ = sim.world.object_pose()
    assert math.hypot(x + 0.3, y - 0.7) < 0.3


@pytest.mark.parametrize("seed", [2, 3])
def test_attaching_robots_settle_with_a_range_and_bearing_five_times_noisier_than_the_default(tmp_path, seed):
    """The lab-6 box with comm.range_noise_m 0.05 and bearing_noise_rad 0.1 (the defaults are 0.01 and 0.02):
    a robot in its place read its predecessor d_tol or more off every few steps, so SETTLE_STEPS readings in a
    row within d_tol took minutes (seed 3 caged at 230 s); seed 2 caged at 58 s, with members settled late, and
    left the box 0.14 rad off its yaw. Now a robot whose mean error over
    AVERAGE_SETTLE_STEPS is within d_tol / 2 settles too: they cage within a minute and complete."""
    scenario = tmp_path / "noisy-rab.yaml"
    scenario.write_text(LAB_BOX.replace("comm: {range_m: 3.0}", "comm: {range_m: 3.0, range_noise_m: 0.05, "
                                        "bearing_noise_rad: 0.1}") + "time_limit_s: 400\n")
    result = Simulation(load_scenario(str(scenario)), seed=seed).run()
    assert result["caged"] and result["time_to_cage_s"] < 90.0
    assert result["completed"], result["failures"]


@pytest.mark.parametrize("seed", [1, 8])
def test_a_path_that_starts_where_the_object_lies_is_pushed_straight(tmp_path, seed):
    """A user's path [[0, 0, 0], [0, 0.9, 0]]: its first waypoint is the object's start. The seed took it
    for "no direction of travel" and drove straight in from wherever it was, so a pusher ended at a corner
    of the rear face and the box spun as it went: seed 1 passed the last waypoint 21 degrees off its yaw,
    seed 8 0.24 m off and 27 degrees. Now the seed goes behind the first leg that moves the object."""
    scenario = tmp_path / "from-start.yaml"
    scenario.write_text(LAB_BOX.replace("[[0, 0.3, 0], [0, 0.6, 0], [0, 0.9, 0]]", "[[0, 0, 0], [0, 0.9, 0]]")
                        + "time_limit_s: 200\n")
    result = Simulation(load_scenario(str(scenario)), seed=seed).run()
    assert result["completed"], result["failures"]
    assert result["final_position_error_m"] < 0.05
    assert result["final_orientation_error_rad"] < math.radians(5.72)


class _StillWorld:
    """A world frozen at one moment: what the evaluator reads of the truth."""

    def __init__(self, object_pose, robot_xy):
        self._object, self._robots = np.asarray(object_pose, float), np.asarray(robot_xy, float)

    def object_pose(self):
        return self._object

    def robot_poses(self):
        return np.column_stack([self._robots, np.zeros(len(self._robots))])


@pytest.mark.parametrize("robot_xy, encloses", [
    ([(0.3, 0.0), (-0.15, 0.26), (-0.15, -0.26)], True),       # round the object
    ([(0.3, 0.2), (0.3, 0.0), (0.3, -0.2)], False),           # a ring closed on one side of it
])
def test_result_json_says_whether_the_closed_cage_really_encloses_the_object(make_scenario, robot_xy, encloses):
    """The swarm decides closure from what it senses; the result checks the truth: a ring that closed on one
    side of the object (a compound of two parts far apart did that, and the run said caged=True) is a failure."""
    from sim_backend.transport_metrics import TransportEvaluator

    scenario = make_scenario(behaviour="transport", robots={"count": 3}, object={"shape": "box", "size": [0.3, 0.3]})
    evaluator = TransportEvaluator(scenario, _StillWorld((0.0, 0.0, 0.0), robot_xy))
    member = {"state": "caged", "member": True, "closed": True, "waypoint": 0}
    evaluator.on_step(10.0, [dict(member) for _ in robot_xy])
    result = evaluator.result()
    assert result["caged"] and result["cage_encloses_object"] is encloses
    assert any("without enclosing the object" in line for line in result["failures"]) is not encloses


def test_a_turn_in_place_cut_short_by_the_time_limit_is_not_blamed_on_friction(make_scenario):
    """A box that had turned 171° of a 180° turn in place when the time limit came was said to be held by
    `1.5 N of floor friction`: the stuck hint measured only how far the centroid moved, which a turn in
    place does not. An object still getting nearer its waypoint was only short of time."""
    from sim_backend.transport_metrics import PUSH_JUDGED_AFTER_S, TransportEvaluator

    scenario = make_scenario(behaviour="transport", robots={"count": 10}, time_limit_s=107,
                             object={"shape": "box", "size": [0.5, 0.8], "mass": 0.5}, path=[[0, 0, 180]])
    evaluator = TransportEvaluator.__new__(TransportEvaluator)
    evaluator.scenario, evaluator.pose_at_closure, evaluator.members = scenario, (0.0, 0.0, 0.0), [0, 1, 2, 3]
    evaluator.reached, evaluator.last_time = {}, 107.0
    truth = (0.02, 0.0, math.radians(-171))
    evaluator.progress_at = 106.9
    (hint,) = evaluator._still_going_hint(truth)
    assert hint.startswith("the object was still on its way when the run reached its 107 s time limit (0.02 m and "
                           "9° from waypoint 1") and "--time-limit" in hint
    evaluator.progress_at = 107.0 - PUSH_JUDGED_AFTER_S     # no nearer for as long as a stall is judged after
    assert evaluator._still_going_hint(truth) == []
    evaluator.progress_at, evaluator.last_time = 50.0, 52.0  # stopped early: the stop_reason says why
    assert evaluator._still_going_hint(truth) == []


def test_a_turn_that_did_not_happen_names_the_rotation_gains_not_the_floor_friction(make_scenario):
    from sim_backend.transport_metrics import TransportEvaluator

    def hint(params, truth=(0.0, 0.0, 0.0)):
        scenario = make_scenario(behaviour="transport", robots={"count": 10}, params=params,
                                 object={"shape": "box", "size": [0.5, 0.8], "mass": 0.5}, path=[[0, 0, 90]])
        evaluator = TransportEvaluator.__new__(TransportEvaluator)
        evaluator.scenario, evaluator.pose_at_closure, evaluator.members = scenario, (0.0, 0.0, 0.0), [0, 1, 2, 3]
        evaluator.reached = {}
        return evaluator._turn_hint(truth, 0.1, math.radians(5.72))    # result()'s defaults

    (zero,) = hint({"k_r": 0, "k_cr": 0})
    assert zero == ("the object stands 0.00 m from waypoint 1 but 90° off its yaw, having turned 0° since the cage "
                    "closed; the members turn it with u_r and u_cr (params.k_r, params.k_cr): params.k_r and "
                    "params.k_cr are 0")
    (weak,) = hint({}, truth=(0.03, 0.0, math.radians(30)))
    assert "60° off its yaw, having turned 30°" in weak and "4 members turning it against its floor friction" in weak
    assert hint({}, truth=(0.5, 0.0, 0.0)) == []       # not at the waypoint: the push is what failed
    assert hint({}, truth=(0.0, 0.0, math.radians(88))) == []     # within the yaw tolerance


def test_spares_keep_helping_a_three_robot_cage_that_lost_a_member_mid_push():
    """lab-6-payload seed 4: the 3-robot cage lost robot 0 at 76 s, mid-push. The spares reinforcing it stopped
    (they helped only a cage of three live members), the two left could not move the 4.3 kg box, and it
    stood 0.28 m short until the time limit. The spares now help a cage that went down to two."""
    from sim_backend.scenario import Fault

    scenario = load_scenario("lab-6-payload").with_overrides(faults=[Fault(robot=0, at_s=76.0)])
    result = Simulation(scenario, seed=4).run()
    # Every waypoint reached where it lies. Not `completed`: two members cannot hold the box's yaw (behaviour.md
    # section 8), and since the IR fix (38c88f8) this run ends 5.9 degrees off, 0.2 over the tolerance.
    assert [w["reached_s"] is not None and w["position_error_m"] < 0.06 for w in result["waypoints"]] == [True] * 3
    assert result["final_position_error_m"] < 0.06 and result["final_orientation_error_rad"] < 0.2, result["failures"]


def test_an_estimate_after_a_long_pause_does_not_run_ahead_at_the_last_velocity():
    """After an 11 s e-stop a member's first estimate jumped 0.3 m ahead of the box for a step: the filter
    predicted over the whole pause at the velocity the box had before it. A pause now forgets the velocity."""
    sim = Simulation(load_scenario("lab-6"), seed=1)
    while sim.step_index * sim.period < 76.0:             # pushing, the box moving at several cm/s
        sim.step()
    member = next(b for b in sim.behaviours if b.state == "push")
    now = sim.step_index * sim.period
    before = member.filter.pose
    moving = math.hypot(member.filter.kf.x[3], member.filter.kf.x[4])
    assert moving > 0.005, moving                         # the case: a box in motion when the robots were held
    after = member._estimate_object(now + 11.0)
    assert math.hypot(after[0] - before[0], after[1] - before[1]) < 0.02, (before, after)
