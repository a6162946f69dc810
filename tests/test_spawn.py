"""Where robots start (sim_backend/spawn.py): an area the up-front check accepts is filled in every seed, and
one it refuses, or one the object covers, is said naming robots.spawn."""
import dataclasses

import numpy as np
import pytest

from onboard.config import ConfigError
from sim_backend.scenario import load_scenario
from sim_backend.world import World


def _lab6_with(count: int, **changes):
    scenario = load_scenario("lab-6")
    return dataclasses.replace(scenario, robots=dataclasses.replace(scenario.robots, count=count), **changes)


def _world(scenario, seed: int) -> World:
    return World(scenario, np.random.default_rng(np.random.SeedSequence(seed).spawn(5)[0]))


def test_an_area_the_check_accepts_is_filled_in_every_seed():
    """12 robots in lab-6's 0.6 x 0.6 m area passed the check, but random placement jammed in seeds 2, 3, 4
    and 9 of 1-20 (`cannot place 12 robots ... (placed 11)`): a study over seeds stopped at start-up on seeds
    of a scenario that seed 1 ran. A jammed try now starts again."""
    scenario = _lab6_with(12)
    for seed in range(1, 21):
        world = _world(scenario, seed)
        xy = world.robot_poses()[:, :2]
        gaps = np.linalg.norm(xy[:, None] - xy[None], axis=-1) + np.eye(len(xy))
        assert len(xy) == 12 and gaps.min() > 2 * world.spec.radius_m, f"seed {seed}"
        world.release()


def test_an_area_random_placement_cannot_fill_is_refused_up_front():
    with pytest.raises(ConfigError, match=r"robots\.spawn: 15 robots need about 0\.677 m² to be placed at random"):
        _world(_lab6_with(15), 1)


def test_an_area_under_the_object_is_said_at_once():
    scenario = _lab6_with(3)
    scenario = dataclasses.replace(scenario, object=dataclasses.replace(scenario.object, position=(-0.9, -0.9),
                                                                        size=(1.2, 1.2)))
    with pytest.raises(ConfigError, match="most tries landed on the object"):
        _world(scenario, 1)
