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
