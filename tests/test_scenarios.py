"""Built-in scenarios load with the documented numbers; bad ones give one-line errors naming the field."""
from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import pytest
import yaml

from onboard.behaviour import behaviour_names
from onboard.config import ConfigError
from sim_backend.scenario import BUILTIN_DIR, builtin_names, load_scenario, parse_scenario

DOCS = Path(__file__).resolve().parents[1] / "docs" / "scenarios.md"

PAPER = {   # robots -> (box size, mass, spawn x, spawn y, time limit)
    25: ((2.0, 2.0), 5.56, (-4.0, -2.0), (-4.0, -2.0), 1500.0),
    50: ((3.6, 6.0), 30.024, (-6.0, -2.0), (-7.0, -4.0), 3000.0),
    100: ((7.2, 12.0), 120.096, (-10.0, -5.0), (-10.0, -6.0), 6000.0),
}
PATHS = ("straight", "zigzag", "straight_rot")
ZIGZAG_Y = [0, -2, 0, -2, 0, 0, -2, 0, -2, 0, -2]
IRREGULAR = ("cloud", "box_rotation", "clover")
BOX = {"shape": "box", "size": [1.0, 1.0]}


def error_of(data) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        parse_scenario(data, "test")
    return info.value


# --- built-ins --------------------------------------------------------------------------------------

def test_builtin_list_is_complete():
    expected = {f"paper-{n}-{p}" for n in PAPER for p in PATHS}
    expected |= {f"irregular-{s}" for s in IRREGULAR} | {"lab-6", "lab-6-payload", "aggregate-20"}
    expected |= {"paper-25-straight-lossy", "paper-25-straight-faults"}
    assert set(builtin_names()) == expected


@pytest.mark.parametrize("name", builtin_names())
def test_builtin_loads_with_description(name):
    scenario = load_scenario(name)
    assert scenario.name == name
    assert scenario.description.strip()
    assert "\n" not in scenario.description.strip()   # folded, one paragraph


@pytest.mark.parametrize("robots", sorted(PAPER))
@pytest.mark.parametrize("kind", PATHS)
def test_paper_scenarios(robots, kind):
    size, mass, spawn_x, spawn_y, limit = PAPER[robots]
    s = load_scenario(f"paper-{robots}-{kind}")
    assert s.behaviour == "transport"
    assert s.robots.count == robots
    assert (s.robots.spawn.x, s.robots.spawn.y) == (spawn_x, spawn_y)
    assert s.object is not None
    assert (s.object.shape, s.object.size, s.object.mass) == ("box", size, mass)
    assert s.object.position == (0.0, 0.0) and s.object.yaw_deg == 0.0 and not s.object.static
    # 0.3 is the default; the 50/100-robot boxes need less to move at all (see their scenario files).
    assert s.object.friction == {25: 0.3, 50: 0.1, 100: 0.05}[robots]
    assert s.comm.range_m == 7.0
    assert s.time_limit_s == limit
    assert len(s.path) == 10
    assert [x for x, _, _ in s.path] == [-float(k) for k in range(1, 11)]
    ys = [y for _, y, _ in s.path]
    yaws = [yaw for _, _, yaw in s.path]
    if kind == "straight":
        assert ys == [0.0] * 10 and yaws == [0.0] * 10
    elif kind == "zigzag":
        assert ys == [float(v) for v in ZIGZAG_Y[1:]] and yaws == [0.0] * 10
    else:
        assert ys == [0.0] * 10
        assert yaws == [0.0] + [90.0] * 4 + [180.0] * 5


def test_paper_robots_start_clear_of_the_box():
    """Read from the scenario files (every paper one, the lossy and faults variants too): checked on this
    module's PAPER table, as it was, it held whatever the files said."""
    names = [name for name in builtin_names() if name.startswith("paper-")]
    assert len(names) == len(PAPER) * len(PATHS) + 2
    for name in names:
        s = load_scenario(name)
        (x, y), (width, height) = s.object.position, s.object.size
        assert s.object.yaw_deg == 0.0, name
        assert s.robots.spawn.x[1] < x - width / 2 or s.robots.spawn.y[1] < y - height / 2, name


@pytest.mark.parametrize("shape", IRREGULAR)
def test_irregular_scenarios(shape):
    s = load_scenario(f"irregular-{shape}")
    assert s.robots.count == 30
    assert s.object is not None
    assert (s.object.shape, s.object.static, s.object.mass) == (shape, True, 5.56)
    assert s.path == []
    assert (s.robots.spawn.x, s.robots.spawn.y) == ((-4.0, -2.0), (-4.0, -2.0))
    assert s.comm.range_m == 7.0 and s.time_limit_s == 1500.0
    assert "our choice" in s.description


@pytest.mark.parametrize(("name", "mass"), [("lab-6", 0.3), ("lab-6-payload", 4.3)])
def test_lab_scenarios(name, mass):
    s = load_scenario(name)
    assert s.robots.count == 6
    assert s.object is not None
    assert (s.object.shape, s.object.size, s.object.mass) == ("box", (0.285, 0.435), mass)
    assert s.path == [(0.0, 0.3, 0.0), (0.0, 0.6, 0.0), (0.0, 0.9, 0.0)]
    assert (s.robots.spawn.x, s.robots.spawn.y) == ((-1.2, -0.6), (-1.2, -0.6))
    assert s.comm.range_m == 3.0
    assert s.arena.walls == (-2.0, -2.0, 2.0, 2.0)
    assert s.time_limit_s == 600.0 and s.seed == 1


def test_aggregate_demo():
    s = load_scenario("aggregate-20")
    assert s.behaviour == "aggregate"
    assert s.robots.count == 20 and s.object is None and s.path == []
    assert (s.robots.spawn.x, s.robots.spawn.y) == ((-2.0, 2.0), (-2.0, 2.0))
    assert s.arena.walls == (-3.0, -3.0, 3.0, 3.0)
    assert s.time_limit_s == 120.0


def test_yaml_path_works_like_a_builtin_name(tmp_path):
    copy = tmp_path / "my-copy.yaml"
    shutil.copy(BUILTIN_DIR / "lab-6-payload.yaml", copy)
    from_file = load_scenario(str(copy))
    assert from_file.with_overrides(name="lab-6-payload") == load_scenario("lab-6-payload")
    assert from_file.name == "my-copy"   # the file's stem when the file sets no name


def test_name_in_file_wins_over_stem(tmp_path):
    path = tmp_path / "whatever.yaml"
    path.write_text("name: mine\nbehaviour: aggregate\n")
    assert load_scenario(str(path)).name == "mine"


def test_docs_full_example_loads():
    text = DOCS.read_text()
    block = re.search(r"## A full example.*?```yaml\n(.*?)```", text, re.S)
    assert block is not None
    scenario = parse_scenario(yaml.safe_load(block.group(1)))
    assert scenario.name == "my-run" and scenario.object is not None and scenario.faults


def test_docs_list_every_builtin():
    text = DOCS.read_text()
    for name in builtin_names():
        assert f"| `{name}` |" in text, name


# --- validation errors ------------------------------------------------------------------------------

SIMPLE = ": the outline must be a simple polygon, not meeting itself (split such a shape into compound parts)"


@pytest.mark.parametrize(("data", "field", "message"), [
    ({"robots": {"count": 0}}, "robots.count", "robots.count: must be >= 1 (got 0)"),
    ({"robots": {"count": True}}, "robots.count", "robots.count: must be an integer (got true)"),   # YAML's, not True
    ({"robots": {"count": 2.5}}, "robots.count", "robots.count: must be an integer (got 2.5)"),
    ({"robot": {"count": 6}}, "robot", "robot: unknown key (known: arena, behaviour, comm, description, "
     "faults, name, object, params, path, physics, robots, seed, sensors, time_limit_s)"),
    ({"params": {"inter_robot_distance": 0.65}}, "params.inter_robot_distance", None),
    ({"behaviour": "aggregate", "params": {"inter_robot_distance_m": 0.65}}, "params.inter_robot_distance_m",
     "params.inter_robot_distance_m: unknown key (known: gather_distance_m, k_aggregate, k_avoid, speed_m_s, "
     "turn_gain)"),
    ({"params": {"barrier_fraction": 0}}, "params.barrier_fraction",
     "params.barrier_fraction: must be > 0 (got 0)"),
    ({"behaviour": "dance"}, "behaviour",
     "behaviour: unknown behaviour 'dance' (known: " + ", ".join(behaviour_names()) + "; a behaviour of your own "
     "needs @register and, outside onboard/behaviours/, --import)"),
    ({"object": {"shape": "triangle"}}, "object.shape", "object.shape: must be one of box, circle, polygon, "
     "compound, cloud, box_rotation, clover (got 'triangle')"),
    ({"object": {"shape": "box"}}, "object.size", "object.size: a box needs size: [width, height] in metres"),
    ({"object": {"shape": "box", "size": [1, 2, 3]}}, "object.size",
     "object.size: a box needs size: [width, height] in metres (got [1.0, 2.0, 3.0])"),
    # A circle's size is one number: a list of one was said to need 2 items.
    ({"object": {"shape": "circle", "size": [0.3]}}, "object.size",
     "object.size: a circle's size is its radius, one number in metres (got [0.3]); or give radius: <metres>"),
    ({"object": {"shape": "box", "size": [1, -2]}}, "object.size[1]", "object.size[1]: must be > 0 (got -2)"),
    ({"object": {"shape": "circle"}}, "object.radius", "object.radius: a circle needs radius: <metres>"),
    ({"object": {"shape": "polygon", "vertices": [[0, 0], [1, 0]]}}, "object.vertices",
     "object.vertices: a polygon needs at least 3 vertices [[x, y], ...]"),
    ({"object": {"shape": "polygon", "vertices": [[0, 0], [1, 0], [2, 0]]}}, "object.vertices",
     "object.vertices: the polygon has no area (collinear or repeated points)"),
    ({"object": {"shape": "polygon", "vertices": [[0, 0], [1, 1], [1, 0], [0, 1]]}}, "object.vertices",
     "object.vertices: edges 0 and 2 cross: the outline must be a simple polygon, not meeting itself (split such "
     "a shape into compound parts)"),
    # Outlines that meet themselves without crossing: they used to build an object of two pieces, or a spike.
    ({"object": {"shape": "polygon", "vertices": [[0, 0], [2, 0], [2, 2], [1, 0], [0, 2]]}}, "object.vertices",
     "object.vertices: edges 0 and 2 touch" + SIMPLE),
    ({"object": {"shape": "polygon", "vertices": [[0, 0], [0.001, 0], [0, 0.001]]}}, "object.vertices",
     "object.vertices: the polygon's area is 5e-07 m², under 1 mm x 1 mm: too small for an object (are the vertices "
     "in metres?)"),
    ({"object": {"mass": 1e300}}, "object.mass", "object.mass: must be <= 1e+06 (got 1e+300)"),
    ({"robots": {"mass_kg": 1e200}}, "robots.mass_kg", "robots.mass_kg: must be <= 1000 (got 1e+200)"),
    ({"params": {"k_t_push": -60}}, "params.k_t_push", "params.k_t_push: must be >= 0 (got -60)"),
    ({"physics": {"dt_s": 1e-7}}, "physics.dt_s", "physics.dt_s: must be >= 0.0001 (got 1e-07)"),
    ({"object": {"shape": "polygon", "vertices": [[0, 0], [1, 0], [1, 1], [1, 3], [1, 1], [0, 1]]}},
     "object.vertices", "object.vertices: the outline turns back on itself at vertex 3 (a spike of no width)"),
    ({"object": {"shape": "polygon", "vertices": [[0, 0], [1, 0], [1, 0], [1, 1]]}}, "object.vertices",
     "object.vertices: vertices 1 and 2 are the same point (0 m apart): leave one out"),
    # Split into compound parts would not mend a repeated vertex: only a crossing or touching outline is told so.
    ({"object": {"shape": "polygon", "vertices": [[0, 0], [1, 0], [1, 1e-7], [1, 1]]}}, "object.vertices",
     "object.vertices: vertices 1 and 2 are the same point (1e-07 m apart): leave one out"),
    ({"object": {"shape": "polygon", "vertices": [[0, 0], [1, 0], [1, 1], [0, 0]]}}, "object.vertices",
     "object.vertices: the last vertex repeats the first (leave it out: the outline closes by itself)"),
    ({"object": {"shape": "cloud", "size": [3, 3]}}, "object.size", "object.size: not used by shape: cloud"),
    ({"object": {**BOX, "scale": 2}}, "object.scale",
     "object.scale: only for shapes cloud, box_rotation, clover (shape is box)"),
    ({"object": {**BOX, "parts": [BOX]}}, "object.parts",
     "object.parts: only for shape: compound (shape is box)"),
    ({"object": {"shape": "compound"}}, "object.parts",
     "object.parts: a compound object needs at least one part"),
    ({"object": {"shape": "compound", "parts": [BOX, {"shape": "circle"}]}}, "object.parts[1].radius",
     "object.parts[1].radius: a circle needs radius: <metres>"),
    ({"object": {"shape": "compound", "parts": [BOX, {**BOX, "offset": [1.5, 0]}]}}, "object.parts[1]",
     "object.parts[1]: does not touch the rest of the object: it lies 0.5 m from part 0. A compound object is "
     "one rigid piece; move its parts so they touch or overlap"),
    ({"object": {"shape": "compound", "parts": [BOX, {**BOX, "offset": [1.0, 0]},
                                                {"shape": "circle", "radius": 0.2, "offset": [0.0, 0.9]}]}},
     "object.parts[2]", "object.parts[2]: does not touch the rest of the object: it lies 0.2 m from part 0. A "
                        "compound object is one rigid piece; move its parts so they touch or overlap"),
    ({"object": {"shape": "compound", "parts": [{"shape": "clover"}]}}, "object.parts[0].shape",
     "object.parts[0].shape: must be one of box, circle, polygon (got 'clover')"),
    ({"object": {**BOX, "static": "yes please"}}, "object.static",
     "object.static: must be true or false (got 'yes please')"),
    ({"object": {**BOX, "mass": 0}}, "object.mass", "object.mass: must be > 0 (got 0)"),
    ({"comm": {"drop": 1.5}}, "comm.drop", "comm.drop: must be <= 1 (got 1.5)"),
    ({"sensors": {"pose_dropout": -0.1}}, "sensors.pose_dropout",
     "sensors.pose_dropout: must be >= 0 (got -0.1)"),
    ({"robots": {"count": 6}, "faults": [{"robot": 6, "at_s": 30}]}, "faults[0].robot",
     "faults[0].robot: no robot 6 (robots are 0..5)"),
    ({"robots": {"count": 6}, "faults": [{"robot": 2, "at_s": 30}, {"robot": 2, "at_s": 60}]}, "faults[1].robot",
     "faults[1].robot: robot 2 already has a fault in faults[0]"),
    ({"robots": {"count": 6}, "faults": [{"robot": 2, "at_s": 30, "restart_after_s": -1}]},
     "faults[0].restart_after_s", "faults[0].restart_after_s: must be >= 0 (got -1)"),
    ({"faults": [{"robot": 1}]}, "faults[0].at_s", "faults[0].at_s: is required"),
    ({"object": {"shape": "clover", "static": True}, "path": [[-1, 0, 0]]}, "path",
     "path: a static object cannot follow a path (object.static is true)"),
    ({"path": [[-1, 0, 0]]}, "path", "path: a path needs an object to move"),
    ({"object": BOX, "path": [[-1, 0]]}, "path[0]", "path[0]: must have 3 items (got 2)"),
    ({"object": BOX, "path": [[-1, 0, float("nan")]]}, "path[0][2]",
     "path[0][2]: must be a finite number (got nan)"),
    ({"physics": {"control_hz": 1e-300}}, "physics.control_hz", "physics.control_hz: must be >= 0.1 (got 1e-300)"),
    ({"physics": {"dt_s": 0.03}}, "physics.control_hz",
     "physics.control_hz: the control period must be a whole "
     "number of physics steps (dt_s=0.03 gives 3.33333)"),
    ({"arena": {"walls": [1, 1, 0, 0]}}, "arena.walls",
     "arena.walls: must be [xmin, ymin, xmax, ymax] with min < max"),
    ({"robots": {"spawn": {"x": [2, 1]}}}, "robots.spawn.x",
     "robots.spawn.x: must be [min, max] with min <= max (got [2.0, 1.0])"),
    ({"seed": -1}, "seed", "seed: must be >= 0 (got -1)"),
    # 300 digits named an output folder too long to make ("--out: ... File name too long")
    ({"seed": 10 ** 300}, "seed", "seed: must be <= 9223372036854775807 (got an integer of 301 digits)"),
    # Lengths and coordinates beyond MAX_EXTENT_M: they used to overflow in the geometry (tracebacks) or run.
    ({"object": {"shape": "box", "size": [1e308, 1.0]}}, "object.size[0]",
     "object.size[0]: must be <= 1000 (got 1e+308)"),
    ({"object": {"shape": "circle", "size": 1e200}}, "object.size", "object.size: must be <= 1000 (got 1e+200)"),
    ({"object": {"shape": "polygon", "vertices": [[0, 0], [1e300, 0], [0, 1]]}}, "object.vertices[1].x",
     "object.vertices[1].x: must be <= 1000 (got 1e+300)"),
    ({"object": {**BOX, "position": [0, -1e300]}}, "object.position.y",
     "object.position.y: must be >= -1000 (got -1e+300)"),
    ({"object": {"shape": "compound", "parts": [{**BOX, "offset": [1e250, 0]}]}}, "object.parts[0].offset.x",
     "object.parts[0].offset.x: must be <= 1000 (got 1e+250)"),
    ({"object": {"shape": "cloud", "scale": 1e200}}, "object.scale", "object.scale: must be <= 100 (got 1e+200)"),
    # Yaws past ten turns: 1e308 degrees was taken, as whatever its remainder of a turn happens to be.
    ({"object": {**BOX, "yaw_deg": 1e308}}, "object.yaw_deg", "object.yaw_deg: must be <= 3600 (got 1e+308)"),
    ({"object": {"shape": "compound", "parts": [{**BOX, "yaw_deg": -4000}]}}, "object.parts[0].yaw_deg",
     "object.parts[0].yaw_deg: must be >= -3600 (got -4000)"),
    ({"object": BOX, "path": [[-1, 0, 1e308]]}, "path[0][2]", "path[0][2]: must be <= 3600 (got 1e+308)"),
    ({"robots": {"spawn": {"x": [-1e300, 1e300]}}}, "robots.spawn.x[0]",
     "robots.spawn.x[0]: must be >= -1000 (got -1e+300)"),
    ({"object": BOX, "path": [[1, 1e300, 0]]}, "path[0].y", "path[0].y: must be <= 1000 (got 1e+300)"),
    ({"arena": {"walls": [-1e300, -2, 2, 2]}}, "arena.walls[0]", "arena.walls[0]: must be >= -1000 (got -1e+300)"),
    ({"object": {**BOX, "position": [5, 5]}, "arena": {"walls": [-2, -2, 2, 2]}}, "object.position",
     "object.position: (5, 5) is outside the arena walls [-2, -2, 2, 2]"),
    ({"object": BOX, "path": [[0, 1, 0], [0, 2.5, 0]], "arena": {"walls": [-2, -2, 2, 2]}}, "path[1]",
     "path[1]: (0, 2.5) is outside the arena walls [-2, -2, 2, 2]"),
    ({"robots": {"spawn": {"x": [-4, -2]}}, "arena": {"walls": [-2, -2, 2, 2]}}, "robots.spawn",
     "robots.spawn: x [-4.0, -2.0], y [-1.2, -0.6] lies outside the arena walls [-2, -2, 2, 2]"),
    ({"time_limit_s": 0}, "time_limit_s", "time_limit_s: must be > 0 (got 0)"),
    # Accepted before, and the run did nothing: no cage, the object never moved.
    ({"sensors": {"pose_latency_s": 1e9}}, "sensors.pose_latency_s",
     "sensors.pose_latency_s: must be <= 10 (got 1e+09)"),
    ({"sensors": {"pose_noise_m": 1e300}}, "sensors.pose_noise_m", "sensors.pose_noise_m: must be <= 10 (got 1e+300)"),
    ({"sensors": {"proximity_noise": 1e6}}, "sensors.proximity_noise",
     "sensors.proximity_noise: must be <= 1 (got 1e+06)"),
    ({"comm": {"range_noise_m": 1e300}}, "comm.range_noise_m", "comm.range_noise_m: must be <= 10 (got 1e+300)"),
    ({"comm": {"bearing_noise_rad": 7}}, "comm.bearing_noise_rad", None),
    ({"name": "../../etc/evil"}, "name",
     "name: names the output folder: no / or \\, no control characters, and not only dots (got '../../etc/evil')"),
    ({"name": ".."}, "name", None),
    # A NUL ended `sim run` in a traceback ("embedded null byte"); a newline made a folder named across lines.
    ({"name": "x\x00y"}, "name", "name: names the output folder: no / or \\, no control characters, and not only "
                                  "dots (got 'x\\x00y')"),
    ({"name": "a\nb"}, "name", None),
    ({"name": "n" * 101}, "name", "name: names the output folder: at most 100 characters (got 101)"),
    ({"behaviour": "aggregate", "object": BOX, "path": [[1, 0, 0]]}, "path",
     "path: the aggregate behaviour does not follow a path (its params have no 'path'): the path would be ignored"),
    ({"object": {"shape": "circle", "radius": 0.2, "size": 0.3}}, "object.size",
     "object.size: a circle takes radius or size (its radius), not both"),
    ({"object": {"shape": "circle", "size": [0.2, 0.2]}}, "object.size",
     "object.size: a circle's size is its radius, one number in metres (got [0.2, 0.2]); or give radius: <metres>"),
])
def test_validation_error_names_the_field(data, field, message):
    err = error_of(data)
    assert err.field == field
    assert str(err).startswith(f"{field}: ")
    assert "\n" not in str(err) and "Traceback" not in str(err)
    if message is not None:
        assert str(err) == message


@pytest.mark.parametrize(("text", "field", "problem"), [
    ("1: 2\n", "", "top-level key 1 is a number, not a name"),
    ("object: {shape: box, size: [1, 1], true: 1}\n", "object", "key true is a boolean (YAML reads true, false, "
                                                                "yes, no, on and off so), not a name"),
    ("robots: {null: 3}\n", "robots", "key null is null (YAML reads null, ~ and an empty key so), not a name"),
    ("robots: {spawn: {1.5: [0, 1]}}\n", "robots.spawn", "key 1.5 is a number, not a name"),
    ("behaviour: aggregate\nparams: {on: 1}\n", "params", "key true is a boolean (YAML reads true, false, yes, no, "
                                                          "on and off so), not a name"),
])
def test_a_key_yaml_reads_as_a_number_a_boolean_or_null_is_said_to_be_no_name(text, field, problem):
    """Such keys gave paths like `[1]: unknown key`, `object[True]: ...` and `robots.None: ...`."""
    err = error_of(yaml.safe_load(text))
    assert (err.field, err.problem.split(": keys must")[0]) == (field, problem)
    assert "keys must be names (known: " in err.problem and "\n" not in str(err)
    assert str(err).startswith("top-level key 1 " if not field else f"{field}: key ")


def test_unknown_params_key_lists_the_known_names():
    err = error_of({"params": {"inter_robot_distance": 0.65}})
    assert err.problem.startswith("unknown key (known: allocation_time_s, attach_timeout_s, barrier_fraction, ")
    assert "inter_robot_distance_m" in err.problem and err.problem.endswith("travel_speed_m_s, turn_on_spot_at_object)")


def test_not_a_mapping(tmp_path):
    assert str(error_of([1, 2])) == "a scenario must be a mapping of keys (got list)"
    path = tmp_path / "list.yaml"
    path.write_text("- a\n- b\n")
    with pytest.raises(ConfigError) as info:         # the file is named: one of a study's many, say
        load_scenario(str(path))
    assert str(info.value) == f"{path}: a scenario must be a mapping of keys (got list)"


def test_yaml_syntax_error_names_file_and_line(tmp_path):
    path = tmp_path / "mine.yaml"
    path.write_text("name: demo\nrobots:\n  count: 3\n   spawn: {x: [0, 1]}\n")
    with pytest.raises(ConfigError) as info:
        load_scenario(str(path))
    assert info.value.field == f"{path}:4"      # the path as given, not the bare name of a file in some folder
    assert str(info.value) == f"{path}:4: not valid YAML (mapping values are not allowed here)"
    assert info.value.__cause__ is None and info.value.__suppress_context__


def test_error_in_file_names_the_field(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("robots:\n  count: 0\n")
    with pytest.raises(ConfigError, match=r"^robots\.count: must be >= 1 \(got 0\)$"):
        load_scenario(str(path))


def test_unknown_scenario_name():
    with pytest.raises(ConfigError) as info:
        load_scenario("paper-26-straight")
    assert info.value.field == "scenario"
    assert str(info.value) == ("scenario: unknown scenario 'paper-26-straight': not a file and not built in "
                               "(see `khepri sim list`)")


def test_missing_yaml_file(tmp_path):
    missing = str(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError) as info:
        load_scenario(missing)
    assert str(info.value) == f"scenario: no such file: {missing}"


def test_builtin_name_wins_over_a_folder_of_that_name(tmp_path, monkeypatch):
    """A folder named like a built-in (say, a run's output copied here) must not hide the built-in."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "lab-6").mkdir()
    assert load_scenario("lab-6").name == "lab-6"
    (tmp_path / "not-a-scenario").mkdir()
    with pytest.raises(ConfigError, match="not-a-scenario is a folder, not a file"):
        load_scenario("not-a-scenario")


@pytest.mark.parametrize("make, said", [
    (lambda here: "/dev/null", "scenario: /dev/null is not a regular file"),
    (lambda here: os.mkfifo(here / "pipe.yaml") or "pipe.yaml", "scenario: pipe.yaml is not a regular file"),
    (lambda here: (here / "loop.yaml").symlink_to("loop.yaml") or "loop.yaml",
     "scenario: loop.yaml is a symbolic link to nothing that exists"),
    (lambda here: (here / "gone.yaml").symlink_to("nowhere.yaml") or "gone.yaml",
     "scenario: gone.yaml is a symbolic link to nothing that exists"),
    (lambda here: "", "scenario: is empty (an unset shell variable?): give a built-in name or a YAML file"),
])
def test_a_path_that_is_there_but_no_file_is_said_as_what_it_is(tmp_path, monkeypatch, make, said):
    """Each of these was "no such file" (or, for "", "is a folder"), of something that is there."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError) as info:
        load_scenario(make(tmp_path))
    assert str(info.value) == said


def test_a_file_named_like_a_builtin_is_neither_taken_nor_hidden_silently(tmp_path, monkeypatch):
    """`khepri sim show lab-6 > lab-6` leaves a file called lab-6 here. It used to win over the built-in without
    a word (an empty one: "the file is empty"); taking the built-in instead would ignore a user's edits."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "lab-6").write_text((BUILTIN_DIR / "lab-6.yaml").read_text().replace("count: 6", "count: 7"))
    with pytest.raises(ConfigError) as info:
        load_scenario("lab-6")
    assert str(info.value) == ("scenario: 'lab-6' is both a built-in scenario and a file in this folder: "
                               "write ./lab-6 for the file, or rename the file")
    assert load_scenario("./lab-6").robots.count == 7


@pytest.mark.parametrize("given", ["./lab-6", "./paper-25-straight", "runs/lab-6", ".lab-6", "~/lab-6"])
def test_a_path_to_no_file_is_an_error_not_the_builtin_of_that_name(tmp_path, monkeypatch, given):
    """The docs say to write ./lab-6 for a file named like a built-in: with no such file, `sim run ./lab-6` ran the
    built-in lab-6 without a word (and exited 0), while `sim show subdir/lab-6` was "unknown scenario"."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError) as info:
        load_scenario(given)
    name = given.rsplit("/", 1)[-1]
    hint = f" (the built-in scenario is {name}, without a folder)" if not name.startswith(".") else ""
    assert str(info.value) == f"scenario: no such file: {given}{hint}"
    assert load_scenario("lab-6").name == "lab-6"      # by its name, the built-in as before


@pytest.mark.parametrize("given, hint", [
    ("lab-6.yaml", " (the built-in scenario is lab-6, without .yaml)"),
    ("paper-25-straight.yml", " (the built-in scenario is paper-25-straight, without .yml)"),
    ("runs/lab-6.yaml", " (the built-in scenario is lab-6, without a folder or .yaml)"),
    ("mine.yaml", ""),
])
def test_a_builtin_name_with_its_yaml_suffix_names_the_builtin(tmp_path, monkeypatch, given, hint):
    """`khepri sim run lab-6.yaml` (the file's name in sim_backend/scenarios/) said only `no such file: lab-6.yaml`,
    where `./lab-6` already got the built-in's name: a new user was not told that `lab-6` is the name to give."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError) as info:
        load_scenario(given)
    assert str(info.value) == f"scenario: no such file: {given}{hint}"


def test_a_name_too_long_for_the_file_system_is_an_error_not_a_traceback():
    """Path.is_file raised OSError "File name too long" for a name of 300 characters."""
    with pytest.raises(ConfigError) as info:
        load_scenario("n" * 300)
    assert str(info.value) == f"scenario: '{'n' * 59}...: File name too long"


def test_a_section_with_every_line_commented_out_is_empty_whatever_section_it_is():
    """`comm:` with nothing under it was taken as the defaults, but `params:` or `faults:` was "must be a
    mapping (got None)": commenting out the lines under one section broke the file, under another not."""
    text = "robots: {count: 6}\nobject: {shape: box, size: [0.4, 0.4]}\npath: [[1.0, 0, 0]]\n"
    plain = parse_scenario(yaml.safe_load(text))
    emptied = parse_scenario(yaml.safe_load(text + "params:\nfaults:\ncomm:\n"))
    assert emptied.params == plain.params == {} and emptied.faults == plain.faults == []
    assert emptied.comm == plain.comm


@pytest.mark.parametrize("parts", [
    [BOX, {**BOX, "offset": [1.0, 0.0]}],                                     # face to face
    [BOX, {**BOX, "offset": [0.3, 0.2]}],                                     # overlapping
    [BOX, {"shape": "box", "size": [0.2, 0.2], "offset": [0.1, 0.1]}],        # one inside the other
    [BOX, {"shape": "circle", "radius": 0.3, "offset": [0.0, 0.8]}],          # a disc on a face
    [{"shape": "circle", "radius": 0.3}, {"shape": "circle", "radius": 0.2, "offset": [0.5, 0.0]}],
    [BOX, {**BOX, "offset": [1.0, 0.0]}, {**BOX, "offset": [2.0, 0.0]}],      # a chain: 0 and 2 apart
    [BOX, {"shape": "box", "size": [1.0, 0.2], "yaw_deg": 45, "offset": [0.85, 0.85]}],   # a turned bar
    [BOX, {"shape": "polygon", "vertices": [[0.5, 0.0], [1.2, -0.3], [1.2, 0.3]]}],       # a vertex on a face
])
def test_compound_parts_that_touch_make_one_object(make_scenario, parts):
    assert make_scenario(object={"shape": "compound", "parts": parts}).object.parts


def test_a_compound_part_just_clear_of_the_others_is_named_with_its_gap(make_scenario):
    with pytest.raises(ConfigError) as err:
        make_scenario(object={"shape": "compound", "parts": [BOX, {"shape": "box", "size": [1.0, 0.2],
                                                                   "yaw_deg": 45, "offset": [0.9, 0.9]}]})
    assert err.value.field == "object.parts[1]" and "from part 0" in str(err.value)


def test_a_name_yaml_reads_as_a_date_says_to_quote_it(tmp_path):
    """`name: 2024-01-01` said `must be a string (got datetime.date(2024, 1, 1))`: a Python repr, where a pair
    of quotes is the fix."""
    path = tmp_path / "dated.yaml"
    path.write_text("name: 2024-01-01\nbehaviour: aggregate\nrobots: {count: 3}\n")
    with pytest.raises(ConfigError) as err:
        load_scenario(str(path))
    assert str(err.value) == "name: must be a string (got 2024-01-01, which YAML reads as a date: put it in quotes)"
