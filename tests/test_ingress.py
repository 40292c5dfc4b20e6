"""The proof of a way in and a way out of a ditch crossable only in places (ditch_drake/world/ingress.py)."""

import copy
import math

import numpy as np
import pytest

from ditch_drake.common.errors import ConfigError
from ditch_drake.spec import robot
from ditch_drake.world.environments import get_environment, validate_environment
from ditch_drake.world.ingress import (
    IngressConfig,
    check_ways_in_and_out,
    check_windows,
    smallest_tip_angle_deg,
    traversable_grid,
)
from ditch_drake.world.terrain import DitchTerrain, SlopeSection

SEARCH = ["wide_search", "wide_search_offset"]


def test_the_limit_is_the_robot_s_smallest_tip_over_angle():
    assert IngressConfig().max_traversable_slope_deg == smallest_tip_angle_deg()
    assert smallest_tip_angle_deg() == pytest.approx(math.degrees(robot.tip_angle_fore_aft_rad()))
    assert 59.0 < smallest_tip_angle_deg() < 60.0
    assert IngressConfig().clearance_m == pytest.approx(robot.CHASSIS_SIZE_M[1] / 2)


@pytest.mark.parametrize("name", SEARCH)
def test_every_task_of_a_search_environment_has_a_way_in_and_out_through_its_windows(name):
    environment = get_environment(name)
    terrain = DitchTerrain(environment.terrain)
    grid = traversable_grid(terrain)
    for task in environment.tasks:
        check_ways_in_and_out(terrain, task.start[:2], task.goal, grid)  # raises without one
    # The walls are crossable only in the windows: at 70 deg no cell of them is free.
    labels, free = grid.labels, grid.labels > 0
    ny, nx = labels.shape
    x = grid.origin[0] + grid.resolution_m * np.arange(nx)
    y = grid.origin[1] + grid.resolution_m * np.arange(ny)
    on_the_wall = (np.abs(y) > terrain.toe_distance_m + 0.5) & (np.abs(y) < 4.5)  # the 70 deg wall ends at 5.16 m
    for side, rows in (("right", on_the_wall & (y < 0)), ("left", on_the_wall & (y > 0))):
        window = next(s for s in terrain.slope_sections(side) if s.slope_deg == 50.0)
        start = terrain.course_xy[0, 0]
        columns_free = free[rows].any(axis=0)
        inside = (x > start + window.from_m + 0.5) & (x < start + window.to_m - 0.5)
        outside = ((x < start + window.from_m - 0.5) | (x > start + window.to_m + 0.5)) & (np.abs(x) < -start)
        assert columns_free[inside].all() and not columns_free[outside].any(), side


@pytest.mark.parametrize("side, way", [("right", "no way in"), ("left", "no way out")])
def test_a_ditch_with_no_window_on_a_wall_is_refused_naming_the_task(side, way):
    environment = copy.deepcopy(get_environment("wide_search"))
    setattr(environment.terrain.wall_slopes, side, [SlopeSection(0.0, 60.0, 70.0)])
    with pytest.raises(ConfigError, match=rf"task 'straight_across': {way}: .*max_traversable_slope_deg=59.6 .*"
                                          rf"wall_slopes.{side}"):
        validate_environment(environment)


def test_a_window_just_under_the_limit_lets_the_robot_in_and_one_over_it_does_not():
    environment = copy.deepcopy(get_environment("wide_search"))
    for slope, accepted in ((59.0, True), (60.0, False)):
        environment.terrain.wall_slopes.right[1].slope_deg = slope
        environment.terrain.wall_slopes.left[1].slope_deg = slope
        if accepted:
            validate_environment(environment)
        else:
            with pytest.raises(ConfigError, match="no way in"):
                validate_environment(environment)


def test_a_step_blocks_the_way_though_both_sides_are_crossable():
    """Two gentle sections meet in a step of more than a wheel's radius: the cells at it are steep."""
    environment = copy.deepcopy(get_environment("wide_search"))
    # The right wall's window at 50 deg, then 35 deg: a step of up to 1.2 m, both sides under the limit.
    environment.terrain.wall_slopes.right[1:] = [SlopeSection(5.0, 25.0, 50.0), SlopeSection(25.0, 60.0, 35.0)]
    terrain = DitchTerrain(environment.terrain)
    grid = traversable_grid(terrain)
    x_step = terrain.course_xy[0, 0] + 25.0
    on_step = [grid.label_at([x_step, -y]) for y in np.arange(3.5, 5.5, 0.1)]
    beside = [grid.label_at([x_step + 1.0, -y]) for y in np.arange(3.5, 5.5, 0.1)]
    assert not any(on_step) and all(beside)


def test_a_window_narrower_than_the_robot_is_refused_naming_the_section():
    environment = copy.deepcopy(get_environment("wide_search"))
    terrain = DitchTerrain(environment.terrain)
    check_windows(terrain)
    environment.terrain.wall_slopes.left = [SlopeSection(0.0, 20.0, 70.0), SlopeSection(20.0, 20.3, 45.0),
                                            SlopeSection(20.3, 20.6, 50.0), SlopeSection(20.6, 60.0, 70.0)]
    with pytest.raises(ConfigError, match=r"terrain.wall_slopes.left\[1..2\]: a window .* from 20 to 20.6 m is "
                                          r"0.60 m wide; expected at least the robot's width, 0.67 m"):
        validate_environment(environment)
    environment.terrain.wall_slopes.left[2].to_m = environment.terrain.wall_slopes.left[3].from_m = 21.0
    check_windows(DitchTerrain(environment.terrain))  # 1 m: wide enough to be checked by the search
