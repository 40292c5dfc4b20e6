"""Scripted drivers in the simulator: the rollover phenomenon with seeds (short, fast versions).

The 10-trial calibration is `ditch-drake calibrate` / `pytest -m slow`.
"""

import pytest

from ditch_drake.calibration import driven_trials
from ditch_drake.systems.edge_angle_driver import EdgeAngleDriverConfig

HEAD_ON = EdgeAngleDriverConfig(wall_angle_deg=90.0, climb_angle_deg=None)


@pytest.mark.parametrize("environment", ["wide", "sine"])
def test_head_on_rolls_over(environment):
    records = driven_trials(environment, 1, HEAD_ON, seeds=[0, 1], time_step_s=0.02)
    assert [record["status"] for record in records] == ["rolled_over", "rolled_over"]
    assert all(record["time_s"] < 15 for record in records)


@pytest.mark.parametrize("environment", ["crater", "narrow"])
def test_shallow_angle_gets_through(environment):
    (record,) = driven_trials(environment, 0, EdgeAngleDriverConfig(), seeds=[5], time_step_s=0.02)
    assert record["status"] == "reached_goal"
    assert 45 < record["peak_tilt_deg"] < 75  # It did go down a steep wall, and did not tip.


def narrow_driver(replan: bool):
    import numpy as np

    from ditch_drake.environments import get_environment
    from ditch_drake.systems.edge_angle_driver import EdgeAngleDriver
    from ditch_drake.terrain import DitchTerrain

    environment = get_environment("narrow")  # Course along x at y = 0; goal (5, 9) across.
    terrain = DitchTerrain(environment.terrain)
    return EdgeAngleDriver(terrain, np.array([5.0, 9.0]), 0, EdgeAngleDriverConfig(replan_each_step=replan)), terrain


def test_a_replanning_labeller_answers_from_the_current_pose_not_the_latched_plan():
    import math

    import numpy as np

    from ditch_drake.planar import wrap_to_pi
    from ditch_drake.systems.edge_angle_driver import CLIMB, DESCEND

    latched, terrain = narrow_driver(False)
    replanning, _ = narrow_driver(True)
    on_near_wall = np.array([0.0, -0.5 * (terrain.toe_distance_m + terrain.hinge_distance_m)])
    facing_west = math.pi  # The latched plan chose east (+1) before the wall.
    heading, _, phase = latched.desired_heading(on_near_wall, 1.0, DESCEND, heading=facing_west)
    assert abs(wrap_to_pi(heading - facing_west)) > math.radians(120)  # A U-turn on a 55 deg wall.
    heading, sign, phase = replanning.desired_heading(on_near_wall, 1.0, DESCEND, heading=facing_west)
    assert (sign, phase) == (-1.0, DESCEND)
    assert abs(wrap_to_pi(heading - facing_west)) < math.radians(90) and math.sin(heading) > 0  # West and down.
    # Facing the edge square on, either side would do: the approach convention decides (the goal's, east).
    for nearly_square in (math.radians(80), math.radians(100)):
        assert replanning.desired_heading(on_near_wall, -1.0, DESCEND, heading=nearly_square)[1] == 1.0
    # Back on the near wall after reaching the bottom: a latched CLIMB; replanning descends again.
    assert replanning.desired_heading(on_near_wall, 1.0, CLIMB, heading=0.0)[1:] == (1.0, DESCEND)
    on_far_wall = -on_near_wall
    heading, _, phase = replanning.desired_heading(on_far_wall, 0.0, DESCEND, heading=0.0)
    assert phase == CLIMB and math.cos(heading) > 0 and math.sin(heading) > 0  # East and up.


def test_the_replanning_driver_itself_gets_through():
    (record,) = driven_trials("narrow", 1, EdgeAngleDriverConfig(replan_each_step=True), seeds=[5], time_step_s=0.02)
    assert record["status"] == "reached_goal"
