"""What the simulator knows that dooms a transport run is said before it starts (and kept in result.json):
an object too small for the cage spacing, too little room to the walls, too few robots, a radio too short."""
import json

import numpy as np
import pytest

from khepri_cli.main import main
from onboard.config import ConfigError
from sim_backend.object_hull import hull_perimeter
from sim_backend.runner import Simulation
from sim_backend.scenario import builtin_names, load_scenario
from sim_backend.shapes import build_geometry
from sim_backend.transport_preflight import behind_share


def transport(make_scenario, **changes):
    data = {"behaviour": "transport", "robots": {"count": 8, "spawn": {"x": [-1.5, -0.7], "y": [-1.5, -0.7]}},
            "object": {"shape": "box", "size": [0.3, 0.4], "mass": 0.3, "position": [0, 0]},
            "path": [[0.5, 0.0, 0]], "arena": {"walls": [-2.5, -2.5, 2.5, 2.5]}}
    data.update(changes)
    return make_scenario(**data)


def test_no_builtin_scenario_is_warned_about():
    for name in builtin_names():
        assert Simulation(load_scenario(name)).warnings == [], name


@pytest.mark.parametrize("params, warning", [
    ({"inter_robot_distance_m": 1e-9}, "params.inter_robot_distance_m: 1e-09 m is less than a robot is wide "
                                       "(0.14 m): cage members cannot stand that close, so the cage cannot close"),
    ({"closure_factor": 1e-12}, "params.closure_factor: d_T = 1e-12 x I_d = 4.5e-13 m is less than a robot is wide "
                                "(0.14 m): the two ends of the cage never come that close, so it cannot close"),
])
def test_a_spacing_or_closing_distance_narrower_than_a_robot_is_warned_about(make_scenario, params, warning):
    """Both ran 150 s without a word and never caged."""
    assert warning in Simulation(transport(make_scenario, params=params)).warnings


def test_an_object_smaller_than_the_cage_spacing_is_warned_about_with_a_spacing_that_fits(make_scenario):
    small = {"shape": "box", "size": [0.15, 0.15], "mass": 0.2, "position": [0, 0]}
    warnings = Simulation(transport(make_scenario, object=small)).warnings
    assert len(warnings) == 1 and warnings[0].startswith("params.inter_robot_distance_m: only 2 robots fit")
    suggested = float(warnings[0].split("to ")[-1].split(" m")[0])
    fitted = transport(make_scenario, object=small, params={"inter_robot_distance_m": suggested})
    assert Simulation(fitted).warnings == []


@pytest.mark.parametrize("radius, warned", [(0.10, True), (0.12, False)])
def test_a_ring_just_short_of_three_spacings_is_not_a_false_alarm(make_scenario, radius, warned):
    """A 0.12 m disc was said to be uncageable (its ring is 2 % short of 3 x I_d), and every seed caged it."""
    disc = {"shape": "circle", "radius": radius, "mass": 0.3, "position": [0, 0]}
    warnings = Simulation(transport(make_scenario, object=disc)).warnings
    assert bool(warnings) == warned and all("only 2 robots fit" in w for w in warnings), warnings


def test_an_object_near_a_wall_at_its_start_or_a_waypoint_is_warned_about(make_scenario):
    assert Simulation(transport(make_scenario)).warnings == []
    near = transport(make_scenario, path=[[0.0, 1.0, 0], [0.0, 2.2, 0]])      # 0.1 m from the top wall there
    warnings = Simulation(near).warnings
    assert len(warnings) == 1 and warnings[0].startswith("path[1]: the object would be at this waypoint 0.10 m")
    start = transport(make_scenario, object={"shape": "box", "size": [0.3, 0.4], "mass": 0.3,
                                             "position": [-2.2, 0]}, path=[[0.0, 0.0, 0]])
    assert Simulation(start).warnings[0].startswith("object.position: the object starts 0.15 m from an arena wall")
    # 0.30 m: robots get round, but squeezed; the box was delivered 0.11-0.14 m off every waypoint. One warning
    # names every pose so near, not one each.
    squeezed = transport(make_scenario, object={"shape": "box", "size": [0.4, 0.4], "mass": 0.3, "position": [2.0, 0]},
                         path=[[2.0, 0.5, 0]])
    assert [w.split(". ")[0] for w in Simulation(squeezed).warnings] == [
        "object.position: the object starts 0.30 m from an arena wall; also path[0] (0.30 m)"]


@pytest.mark.parametrize("gap, warned", [(0.50, True), (0.55, False)])
def test_an_object_pushed_along_a_wall_half_a_metre_off_is_warned_about(make_scenario, gap, warned):
    """A 0.5 m box pushed along a wall 0.4-0.5 m off it was delivered in 1 of 6 runs, with members caged on the
    wall, and no word: the bar was one body and the IR's reach (0.33 m). Past twice that (0.54 m) it is not."""
    y = -2.5 + gap + 0.25
    along = transport(make_scenario, object={"shape": "box", "size": [0.5, 0.5], "mass": 0.4, "position": [0, y]},
                      path=[[0.6, y, 0], [1.2, y, 0]], robots={"count": 10, "spawn": {"x": [-2, -0.5], "y": [0, 1]}})
    warnings = Simulation(along).warnings
    assert bool(warnings) == warned, warnings
    if warned:
        assert warnings[0].startswith(f"object.position: the object starts {gap:.2f} m from an arena wall; also "
                                      f"path[0] ({gap:.2f} m), path[1] ({gap:.2f} m). Robots need about 0.54 m")


def test_too_few_robots_a_short_radio_a_frictionless_floor_and_no_object_are_warned_about(make_scenario):
    few = transport(make_scenario, robots={"count": 2, "spawn": {"x": [-1.5, -0.7], "y": [-1.5, -0.7]}})
    assert Simulation(few).warnings == ["robots.count: a cage needs at least 3 robots (got 2)"]
    deaf = Simulation(transport(make_scenario, comm={"range_m": 0.3})).warnings
    assert len(deaf) == 1 and deaf[0].startswith("comm.range_m: 0.3 m is shorter than the cage spacing I_d")
    slippery = {"shape": "box", "size": [0.3, 0.4], "mass": 0.3, "position": [0, 0], "friction": 0}
    assert Simulation(transport(make_scenario, object=slippery)).warnings[0].startswith("object.friction: 0")
    silent = Simulation(transport(make_scenario, comm={"drop": 1.0})).warnings
    assert silent == ["comm.drop: 1 loses every message: the robots never hear each other, so no seed is elected "
                      "and no cage closes"]
    lost = Simulation(transport(make_scenario, sensors={"pose_dropout": 1.0})).warnings
    assert len(lost) == 1 and lost[0].startswith("sensors.pose_dropout: 1 loses every pose")
    nothing = Simulation(transport(make_scenario, object=None, path=[])).warnings
    assert nothing == ["object: this scenario has none, and the transport behaviour cages one: no cage will close"]


def test_warnings_are_printed_before_the_run_and_kept_in_result_json(tmp_path, capsys):
    scenario = tmp_path / "small.yaml"
    scenario.write_text("name: small\nbehaviour: transport\nrobots: {count: 4}\n"
                        "object: {shape: circle, radius: 0.05, mass: 0.1, position: [0, 0]}\n"
                        "arena: {walls: [-2, -2, 2, 2]}\n")
    assert main(["sim", "run", str(scenario), "--time-limit", "0.5", "--no-plot", "--out", str(tmp_path / "o")]) == 0
    printed = capsys.readouterr().err
    assert "khepri: warning: params.inter_robot_distance_m: only 1 robot fits" in printed
    result = json.loads((tmp_path / "o" / "result.json").read_text())
    assert result["warnings"] == [line[len("khepri: warning: "):] for line in printed.splitlines()
                                  if line.startswith("khepri: warning: ")]


def test_a_yaw_tolerance_beyond_half_a_turn_is_refused(make_scenario):
    with pytest.raises(ConfigError, match=r"^params.orientation_tolerance_deg: must be <= 180"):
        Simulation(transport(make_scenario, params={"orientation_tolerance_deg": 720}))


def test_the_cage_ring_is_measured_round_the_convex_hull(make_scenario):
    box = transport(make_scenario).object
    assert hull_perimeter(build_geometry(box)) == pytest.approx(1.4)
    u_shape = {"shape": "polygon", "vertices": [[0, 0], [1, 0], [1, 1], [0.8, 1], [0.8, 0.2], [0.2, 0.2],
                                                [0.2, 1], [0, 1]], "mass": 1.0, "position": [0, 0]}
    assert hull_perimeter(build_geometry(transport(make_scenario, object=u_shape).object)) == pytest.approx(4.0)


def test_faults_that_never_happen_or_leave_too_few_robots_are_warned_about(make_scenario):
    late = Simulation(transport(make_scenario, time_limit_s=600, faults=[{"robot": 1, "at_s": 1000}])).warnings
    assert late == ["faults[0].at_s: 1000 s is not before the time limit (600 s): robot 1 never fails"]
    most = [{"robot": r, "at_s": 0} for r in range(6)]
    warnings = Simulation(transport(make_scenario, faults=most)).warnings
    assert warnings == ["faults: 6 of 8 robots fail, leaving 2; a cage needs 3 robots to close and push"]
    assert Simulation(transport(make_scenario, faults=most[:5])).warnings == []


def test_a_restart_that_never_comes_back_within_the_run_is_warned_about(make_scenario):
    never = [{"robot": 1, "at_s": 100, "restart_after_s": 1e300}]
    assert Simulation(transport(make_scenario, time_limit_s=600, faults=never)).warnings == [
        "faults[0].restart_after_s: robot 1's agent is down from 100 s to past the time limit (600 s), so it never "
        "comes back; leave restart_after_s out for a robot that fails for good"]
    back = [{"robot": 1, "at_s": 100, "restart_after_s": 499}]
    assert Simulation(transport(make_scenario, time_limit_s=600, faults=back)).warnings == []


def test_a_control_rate_other_than_the_tuned_10_hz_is_warned_about(make_scenario):
    """lab-6 at 20 Hz completed 9 of 16 runs where 10 Hz completes 16 of 16 (behaviour.md section 8)."""
    (warning,) = Simulation(transport(make_scenario, physics={"control_hz": 20})).warnings
    assert warning.startswith("physics.control_hz: the transport behaviour is tuned and tested at 10 Hz")
    assert warning.endswith("; params.turn_on_spot_at_object: true keeps attaching robots from turning it (31 of "
                            "32 runs of lab-6 and lab-6-payload at 20 Hz completed with it)")
    assert Simulation(transport(make_scenario, physics={"control_hz": 10.0})).warnings == []
    (taken,) = Simulation(transport(make_scenario, physics={"control_hz": 20},
                                    params={"turn_on_spot_at_object": True})).warnings
    assert "turn_on_spot_at_object" not in taken        # the advice is taken already


def test_a_waypoint_where_the_object_already_is_is_warned_about(make_scenario):
    """The object's start written as the path, or a waypoint copied twice, asks the swarm for nothing."""
    (start,) = Simulation(transport(make_scenario, path=[[0, 0, 0]])).warnings
    assert start == ("path[0]: it is the object's start, yaw and all: the object is there already, so it counts as "
                     "reached at once and nothing is pushed or turned for it")
    (twice,) = Simulation(transport(make_scenario, path=[[0.5, 0, 0], [0.5, 0, 360]])).warnings
    assert twice.startswith("path[1]: it is path[0] again, yaw and all")
    turn_in_place = [[0.5, 0, 0], [0.5, 0, 10]]
    assert Simulation(transport(make_scenario, path=turn_in_place)).warnings == []


def test_a_speed_above_the_robots_top_speed_is_warned_about(make_scenario):
    warnings = Simulation(transport(make_scenario, params={"cruise_speed_m_s": 100})).warnings
    assert warnings == ["params.cruise_speed_m_s: 100 m/s is above the robots' top wheel speed (0.81 m/s): "
                        "every command is scaled down to it"]


def test_an_object_heavier_than_every_robot_can_push_is_warned_about(make_scenario):
    """A 20 kg box and 6 robots: no warning, and the failure suggested reinforce_push, which cannot help."""
    heavy = {"shape": "box", "size": [0.3, 0.4], "mass": 20.0, "friction": 0.3, "position": [0, 0]}
    robots = {"count": 6, "spawn": {"x": [-1.5, -0.7], "y": [-1.5, -0.7]}}
    warnings = Simulation(transport(make_scenario, object=heavy, robots=robots)).warnings
    assert warnings == ["object.mass: sliding 20 kg takes 58.9 N (object.friction x mass x g), more than all 6 "
                        "robots push together (28.6 N: 4.8 N each, robots.traction x robots.mass_kg x g): it will "
                        "not move"]
    payload = dict(heavy, mass=4.0)                   # the lab's 4 kg payload: 11.8 N, within reach
    assert Simulation(transport(make_scenario, object=payload, robots=robots)).warnings == []
    strong = dict(robots, traction=3.0, count=8)      # grippier tyres, 8 robots: 8 x 15.9 N is plenty
    assert Simulation(transport(make_scenario, object=heavy, robots=strong)).warnings == []


def test_a_cage_whose_members_behind_and_spares_together_fall_short_is_warned_about(make_scenario):
    """A 0.6 m box of 3.5 kg on friction 0.6 (54 % of what 8 robots push, under _too_heavy's bar): 2 members'
    worth behind it and 2 spares push about 17 N against 20.6 N, and 0 of 3 runs moved it (0 of 2 at 3 kg)."""
    robots = {"count": 8, "spawn": {"x": [-2.0, -0.8], "y": [-2.0, -0.8]}}
    box = {"shape": "box", "size": [0.6, 0.6], "mass": 3.5, "friction": 0.6, "position": [0, 0]}
    (short,) = Simulation(transport(make_scenario, object=box, robots=robots, path=[[0, 0.5, 0]])).warnings
    assert short.startswith("object.mass: a cage of about 6 (params.inter_robot_distance_m 0.45 m apart) pushes")
    assert "with the 2 other robots, which push too once the push stalls, about 17.1 N: it will most likely not " \
           "move" in short
    light = dict(box, mass=2.0)        # 11.8 N: delivered in 2 of 2 runs (2.5 kg, 14.7 N: 0 of 2, not warned)
    assert Simulation(transport(make_scenario, object=light, robots=robots, path=[[0, 0.5, 0]])).warnings == []


def test_an_object_taking_most_of_what_every_robot_pushes_is_warned_about(make_scenario):
    """A 0.5 m box on friction 0.8 with 8 robots: 3 kg (62 % of 8 x 4.8 N) was delivered in 1 of 3 runs, 3.5 kg
    in none, 2.5 kg (52 %) in 2 of 2."""
    robots = {"count": 8, "spawn": {"x": [-1.5, -0.7], "y": [-1.5, -0.7]}}

    def warnings_at(mass):
        box = {"shape": "box", "size": [0.5, 0.5], "mass": mass, "friction": 0.8, "position": [0, 0]}
        return Simulation(transport(make_scenario, object=box, robots=robots, path=[[0, 0.4, 0]])).warnings

    (stalls,) = warnings_at(3.0)
    assert stalls.startswith("object.mass: sliding 3 kg takes 23.5 N (object.friction x mass x g), more than 60 % "
                             "of what all 8 robots push together (38.1 N") and "often stalls" in stalls
    assert warnings_at(2.5) == []


def test_a_path_among_the_params_is_refused_naming_the_key_it_belongs_to(make_scenario):
    """It replaced the path the robots follow while the run was judged against `path`."""
    with pytest.raises(ConfigError) as info:
        transport(make_scenario, params={"path": [[0.0, -0.9, 0]]})
    assert info.value.field == "params.path" and "move it to `path:`" in info.value.problem


def test_the_disc_the_preflight_no_longer_warns_about_does_cage(make_scenario):
    disc = make_scenario(behaviour="transport", robots={"count": 6, "spawn": {"x": [-1.2, -0.6], "y": [-1.2, -0.6]}},
                         object={"shape": "circle", "radius": 0.12, "mass": 0.3}, path=[[0, 0.4, 0]],
                         arena={"walls": [-2, -2, 2, 2]}, time_limit_s=150)
    result = Simulation(disc, seed=2).run()
    assert result["caged"] and result["completed"], result["failures"]


def test_a_small_cage_asked_to_push_across_its_faces_or_to_turn_is_warned_about(make_scenario):
    """4 members round a box completed none of 7 runs on legs 30-45 degrees off its faces, 5 of 12 with a
    30-degree turn (docs/behaviour.md section 8): the user hears it before the run, naming the waypoint."""
    diagonal = Simulation(transport(make_scenario, path=[[0.3, 0.3, 0], [0.6, 0.3, 0]])).warnings
    assert len(diagonal) == 1 and diagonal[0].startswith(
        "path[0]: the object would travel 45 degrees off the normals of its faces with a cage of about 4 robots")
    assert "the swarm's estimate of where the object is slides with them" in diagonal[0]    # not only yaw
    turned_box = {"shape": "box", "size": [0.5, 0.3], "mass": 0.3, "position": [0, 0], "yaw_deg": 30}
    started_turned = Simulation(transport(make_scenario, object=turned_box, path=[[0.5, 0.0, 30]])).warnings
    assert [w[:50] for w in started_turned] == ["path[0]: the object would travel 30 degrees off th"]
    turn = Simulation(transport(make_scenario, path=[[0.5, 0.0, 0], [0.5, 0.0, 30]])).warnings
    assert len(turn) == 1 and turn[0].startswith("path[1]: the object would turn 30 degrees with a cage of about 4")
    assert "params.inter_robot_distance_m" in turn[0] and "behaviour.md" in turn[0]


def test_a_bar_pushed_end_first_is_said_to_travel_end_first(make_scenario):
    """A 1.2 x 0.2 m bar pushed along its length was said to travel `90 degrees off the normals of its faces`,
    which reads wrong to a user who sees it pushed square on its end. Its end is too short to count as a face
    (it ended 0.18-0.21 m short in 3 of 3 runs), and the warning now says so. Pushed across, it is not warned."""
    bar = {"shape": "box", "size": [1.2, 0.2], "mass": 0.5, "position": [0, 0]}
    lengthwise = Simulation(transport(make_scenario, object=bar, path=[[0.6, 0, 0]])).warnings
    assert len(lengthwise) == 1 and lengthwise[0].startswith(
        "path[0]: the object would travel end first (90 degrees off the normals of its long faces; its 0.20 m end "
        "is too narrow a face to push square"), lengthwise
    assert Simulation(transport(make_scenario, object=bar, path=[[0, 0.6, 0]])).warnings == []


def test_small_cages_on_legs_along_their_faces_round_objects_and_large_cages_are_not_warned_about(make_scenario):
    along = transport(make_scenario, path=[[0.5, 0.0, 0], [1.0, 0.0, 0], [1.0, 0.0, 10]])   # a 10-degree touch-up
    disc = transport(make_scenario, object={"shape": "circle", "radius": 0.2, "mass": 0.3, "position": [0, 0]},
                     path=[[0.3, 0.3, 0], [0.3, 0.3, 90]])     # a disc's yaw is not judged: its turn is no risk
    larger = transport(make_scenario, path=[[0.3, 0.3, 0], [0.3, 0.3, 60]], params={"inter_robot_distance_m": 0.2})
    assert [Simulation(s).warnings for s in (along, larger)] == [[], []]
    # The disc's turn in place asks for nothing judged: it is said to be reached at once, and nothing more.
    assert [w[:30] for w in Simulation(disc).warnings] == ["path[1]: it is path[0] again, "]


def test_a_small_cage_asked_to_change_its_push_direction_is_warned_about_once_per_change(make_scenario):
    """Measured: 4-6 members pushing a box one way and then 90 degrees from it completed 7 of 15 runs; a
    1.0 x 0.3 m box pushed across its length and then along it ended 0.2 m short in 3 of 3 (the members that
    held its end had slid onto its long faces). A stop in place (no motion) keeps the last direction."""
    zigzag = transport(make_scenario, path=[[0.0, 0.4, 0], [0.0, 0.4, 0], [0.4, 0.4, 0], [0.8, 0.4, 0]])
    stop, change = sorted(Simulation(zigzag).warnings)
    assert stop.startswith("path[1]: it is path[0] again") and change.startswith(
        "path[2]: the push would change direction by 90 degrees")
    back = transport(make_scenario, path=[[0.5, 0.0, 0], [0.3, 0.0, 0]])     # straight back: 180 degrees
    assert [w.split(" by ")[1][:10] for w in Simulation(back).warnings] == ["180 degree"]
    gentle = transport(make_scenario, path=[[0.5, 0.0, 0], [1.0, 0.07, 0]])   # 8 degrees: not warned
    assert Simulation(gentle).warnings == []


def test_a_ring_of_about_three_spacings_round_corners_is_warned_about_with_a_spacing_that_fits(make_scenario):
    """A 0.2 m box (ring 3.0 I_d) caged in 1 of 4 runs with 4-6 robots at I_d 0.45 m and 6 of 6 at 0.30-0.35
    m; a disc with a ring as short (2.9 I_d) cages, so only cornered objects are warned about."""
    six = {"count": 6, "spawn": {"x": [-1.5, -0.7], "y": [-1.5, -0.7]}}
    box = {"shape": "box", "size": [0.2, 0.2], "mass": 0.3, "position": [0, 0]}
    warnings = Simulation(transport(make_scenario, object=box, robots=six)).warnings
    assert len(warnings) == 1 and "such a cage rarely closes" in warnings[0]
    suggested = float(warnings[0].split("to ")[-1].split(" m")[0])
    assert 0.30 <= suggested <= 0.35
    fitted = transport(make_scenario, object=box, robots=six, params={"inter_robot_distance_m": suggested})
    disc = {"shape": "circle", "radius": 0.12, "mass": 0.3, "position": [0, 0]}
    round_one = transport(make_scenario, object=disc, robots=six)
    assert Simulation(fitted).warnings == [] and Simulation(round_one).warnings == []


def test_a_yaw_written_in_radians_and_a_mass_in_grams_are_pointed_out(make_scenario):
    """A new user's waypoint yaw of 3.14 ran as a 3-degree turn, and a 400 (grams) box was only `it will not
    move`: both are units the scenario does not take, and the warning now names the likely slip."""
    radians = Simulation(transport(make_scenario, path=[[0.5, 0.0, 0], [0.5, 0.0, 3.14]])).warnings
    assert radians == ["path[1]: its yaw is in degrees, and 3.14 looks like radians (180 degrees); write 180 if that "
                       "is meant"]
    turned = {"shape": "box", "size": [0.3, 0.4], "mass": 0.3, "position": [0, 0], "yaw_deg": -1.5708}
    assert any(w.startswith("object.yaw_deg: it is in degrees, and -1.5708 looks like radians (-90 degrees)")
               for w in Simulation(transport(make_scenario, object=turned)).warnings)
    assert Simulation(transport(make_scenario, path=[[0.5, 0.0, 3], [0.5, 0.0, 2]])).warnings == []
    grams = {"shape": "box", "size": [0.3, 0.4], "mass": 400, "position": [0, 0]}
    (heavy,) = Simulation(transport(make_scenario, object=grams)).warnings
    assert heavy.endswith("it will not move (object.mass is in kilograms: 400 g would be 0.4)"), heavy
    tonne_free = {"shape": "box", "size": [0.3, 0.4], "mass": 20, "position": [0, 0]}
    assert "grams" not in " ".join(Simulation(transport(make_scenario, object=tonne_free)).warnings)


def u_shape(notch: float) -> dict:
    """A 0.6 m square U whose notch, ``notch`` wide and 0.45 m deep, opens up."""
    a, b = 0.3 - notch / 2, 0.3 + notch / 2
    return {"shape": "polygon", "mass": 0.5, "position": [0, 0],
            "vertices": [[0, 0], [0.6, 0], [0.6, 0.6], [b, 0.6], [b, 0.15], [a, 0.15], [a, 0.6], [0, 0.6]]}


def test_a_recess_a_robot_fits_into_is_warned_about_and_a_narrower_one_is_not(make_scenario):
    """A 0.6 m U with a 0.3 m notch completed 2 of 8 runs, 0.10-0.16 m off (a member caged in the notch pulls the
    estimate), and an L 5 of 8; with a 0.1 m notch, which no robot enters, 4 of 4. Only objects to be moved."""
    robots = {"count": 12, "spawn": {"x": [-2.4, -1.5], "y": [-1, 1]}}
    wide = Simulation(transport(make_scenario, robots=robots, object=u_shape(0.3), path=[[0, 0.8, 0]])).warnings
    assert len(wide) == 1 and wide[0].startswith("object.vertices: the object has a recess a robot fits into (0.30 m "
                                                  "across): a member that cages inside it pulls"), wide
    ell = {"shape": "polygon", "mass": 0.5, "position": [0, 0],
           "vertices": [[0, 0], [0.6, 0], [0.6, 0.2], [0.2, 0.2], [0.2, 0.6], [0, 0.6]]}
    assert "a recess a robot fits into" in " ".join(
        Simulation(transport(make_scenario, robots=robots, object=ell, path=[[0.8, 0, 0]])).warnings)
    narrow = transport(make_scenario, robots=robots, object=u_shape(0.1), path=[[0, 0.8, 0]])
    static = transport(make_scenario, robots=robots, object={**u_shape(0.3), "static": True}, path=[])
    assert Simulation(narrow).warnings == [] and Simulation(static).warnings == []


def test_an_object_thinner_than_a_robot_is_warned_about_unless_it_stays_put(make_scenario):
    """A 2 m bar 0.05 m thick with 12 robots completed 1 of 9 runs, and no cage closed at 0.2 and 1 kg: the
    robots shoved it about while caging; no warning was printed. 0.2 m thick: 3 of 3."""
    robots = {"count": 12, "spawn": {"x": [-2.5, -1.0], "y": [-2.5, -1.0]}}

    def bar(thickness, **more):
        obj = {"shape": "box", "size": [2.0, thickness], "mass": 0.2, "position": [0, 0], **more}
        return Simulation(transport(make_scenario, robots=robots, object=obj, path=[[0, 0.5, 0]])).warnings

    (thin,) = bar(0.05)
    assert thin.startswith("object.size: the object is 0.05 m across at its narrowest, less than a robot (0.14 m): "
                           "the robots that cage it shove it about before the cage closes"), thin
    assert "narrowest" in " ".join(bar(0.1)) and bar(0.2) == []
    turned = {"shape": "polygon", "mass": 0.3, "position": [0, 0], "yaw_deg": 30,
              "vertices": [[0, 0], [1.5, 0], [1.5, 0.08], [0, 0.08]]}
    assert "object.vertices: the object is 0.08 m across" in " ".join(
        Simulation(transport(make_scenario, robots=robots, object=turned, path=[[0, 0.5, 0]])).warnings)
    static = transport(make_scenario, robots=robots, path=[],
                       object={"shape": "box", "size": [2.0, 0.05], "position": [0, 0], "static": True})
    assert not [w for w in Simulation(static).warnings if "narrowest" in w]


def test_a_cage_whose_members_behind_the_object_cannot_slide_it_is_warned_about(make_scenario):
    """A new user's 4 kg disc with 6 robots (every one a member) never moved in 0 of 2 runs: it passed the 60 %
    share of all robots' push unwarned, as the cage's members behind it are what pushes, and nobody else."""
    disc = {"shape": "circle", "radius": 0.4, "mass": 4.0, "friction": 0.3, "position": [0, 0]}
    six = {"count": 6, "spawn": {"x": [-1.6, -0.8], "y": [-1.6, -0.8]}}
    (alone,) = Simulation(transport(make_scenario, object=disc, robots=six, path=[[0, 1, 0]])).warnings
    assert alone.startswith("object.mass: a cage of about 6 (params.inter_robot_distance_m 0.45 m apart) pushes the "
                            "object along its first leg with about 9.1 N") and "against 11.8 N" in alone, alone
    assert "every robot is a member: it will most likely not move" in alone
    assert Simulation(transport(make_scenario, object=dict(disc, mass=2.0), robots=six, path=[[0, 1, 0]])).warnings \
        == []
    # Spares that join once the push stalls: such runs mostly deliver, and are not warned about...
    box = {"shape": "box", "size": [1.0, 0.8], "mass": 4.0, "friction": 0.5, "position": [0, 0]}
    sixteen = {"count": 16, "spawn": {"x": [-3.0, -1.2], "y": [-2.0, 0.0]}}
    wide = {"object": box, "path": [[1, 0, 0]], "arena": {"walls": [-3.5, -3, 3.5, 3.5]}}
    assert Simulation(transport(make_scenario, robots=sixteen, **wide)).warnings == []
    # ... but are when reinforcing is off (the faithful profile).
    (faithful,) = Simulation(transport(make_scenario, robots=sixteen, params={"profile": "faithful"}, **wide)).warnings
    assert "the other robots do not push (reinforcing is off): it will most likely not move" in faithful, faithful
    # Across the box's long face there are more members behind it: fewer newtons short, still short.
    along = behind_share(np.array([[-0.5, -0.4], [0.5, -0.4], [0.5, 0.4], [-0.5, 0.4]]), 0.07, 0.0)
    across = behind_share(np.array([[-0.5, -0.4], [0.5, -0.4], [0.5, 0.4], [-0.5, 0.4]]), 0.07, 90.0)
    assert across > along


def test_a_position_tolerance_as_long_as_a_leg_is_warned_about(make_scenario):
    """push_tolerance_m 2 with 0.3 m legs: `completed: true`, 0.9 m from the goal, no robot having pushed."""
    legs = [[0.0, 0.3, 0], [0.0, 0.6, 0], [0.0, 0.6, 10]]       # the last one a turn in place: no leg to judge
    assert Simulation(transport(make_scenario, path=legs)).warnings == []
    assert Simulation(transport(make_scenario, path=legs, params={"push_tolerance_m": 0.29})).warnings == []
    (warning,) = Simulation(transport(make_scenario, path=legs, params={"push_tolerance_m": 0.3})).warnings
    assert warning.startswith("params.push_tolerance_m: 0.3 m is as long as the leg to path[0] (0.30 m) or longer")


def test_a_small_cage_pushing_18_degrees_off_a_face_is_warned_about(make_scenario):
    """A pentagon (0.45 m radius, a cage of about 6) pushed 3 m along +x, 18 degrees off its lower face's normal:
    1 of 6 runs completed, its yaw drifting unseen, with no warning (the bar was 20 degrees)."""
    pentagon = {"shape": "polygon", "mass": 1.0, "position": [0, 0],
                "vertices": [[0.0, 0.45], [-0.428, 0.1391], [-0.2645, -0.3641], [0.2645, -0.3641], [0.428, 0.1391]]}
    scenario = make_scenario(behaviour="transport", robots={"count": 12, "spawn": {"x": [-2.2, -1.0],
                                                                                   "y": [-1.6, -0.4]}},
                             object=pentagon, path=[[1.5, 0, 0], [3.0, 0, 0]], arena={"walls": [-3, -2, 4.5, 2]})
    warnings = Simulation(scenario).warnings
    assert [w[:60] for w in warnings] == ["path[0]: the object would travel 18 degrees off the normals ",
                                          "path[1]: the object would travel 18 degrees off the normals "]
