"""The regions a failed rollout's end point is named by, on ditches crossable everywhere and only in places."""

import pytest

from ditch_drake.world.environments import get_environment
from ditch_drake.world.regions import ALONG_EDGE, ALONG_EDGE_BAND_M, ditch_region, failure_region
from ditch_drake.world.terrain import DitchTerrain


def _terrain_and_start(name):
    environment = get_environment(name)
    return DitchTerrain(environment.terrain), environment.tasks[0].start[:2]


@pytest.mark.parametrize("y", [-12.0, -10.0, -8.0])
def test_a_ditch_crossable_everywhere_names_its_approach_as_before(y):
    terrain, start = _terrain_and_start("wide_walled")
    assert failure_region(terrain, start, [0.0, y]) == ditch_region(terrain, start, [0.0, y]) == "approach"


def test_near_the_edge_of_a_ditch_crossable_in_places_is_along_the_edge():
    terrain, start = _terrain_and_start("wide_search")
    near = -(terrain.hinge_distance_m + ALONG_EDGE_BAND_M - 0.5)
    far = -(terrain.hinge_distance_m + ALONG_EDGE_BAND_M + 0.5)
    assert failure_region(terrain, start, [-15.0, near]) == ALONG_EDGE
    assert failure_region(terrain, start, [-15.0, far]) == "approach"


def test_the_ditch_and_the_far_side_keep_their_names():
    terrain, start = _terrain_and_start("wide_search")
    assert failure_region(terrain, start, [0.0, 0.0]) == "floor"
    assert failure_region(terrain, start, [0.0, terrain.hinge_distance_m + 1.0]) == "beyond"
