"""The MPPI baseline's planning math (no Drake): elevation map, attitude prediction, MPPI."""

import math

import numpy as np
import pytest

from ditch_drake.common.errors import ConfigError
from ditch_drake.planning.attitude import predict_attitude, stability_margins
from ditch_drake.planning.elevation_map import ElevationGrid, ElevationMapConfig
from ditch_drake.planning.mppi import MppiPlanner, MppiPlannerConfig, rollout
from ditch_drake.spec import actions, robot
from ditch_drake.world.terrain import DitchTerrain, TerrainParams

TERRAIN = DitchTerrain(TerrainParams(bottom_width_m=6.0))


def terrain_cloud(terrain, center, half=6.5, spacing=0.04, noise=0.0, seed=0):
    """Points on the analytic surface around `center`, as a dense lidar would return them."""
    x, y = np.meshgrid(np.arange(center[0] - half, center[0] + half, spacing),
                       np.arange(center[1] - half, center[1] + half, spacing))
    xy = np.c_[x.ravel(), y.ravel()]
    z = terrain.height(xy) + np.random.default_rng(seed).normal(0.0, noise, len(xy))
    return np.c_[xy, z]


def mapped(terrain, pose, spacing=0.04):
    grid = ElevationGrid()
    origin = grid.window_origin(pose[:2])
    return grid, grid.fuse(grid.empty(), origin, terrain_cloud(terrain, pose[:2], spacing=spacing)), origin


def test_map_of_a_ditch_matches_the_analytic_terrain():
    grid = ElevationGrid()
    origin = grid.window_origin([0.0, -4.0])
    heights = grid.empty()
    for seed in range(3):  # Three noisy scans fused.
        heights = grid.fuse(heights, origin, terrain_cloud(TERRAIN, [0.0, -4.0], half=4.0, noise=0.01, seed=seed))
    xs, ys = grid.cell_centers(origin)
    x, y = np.meshgrid(xs, ys)
    truth = TERRAIN.height(np.stack([x, y], axis=-1))
    seen = np.isfinite(heights)
    assert 0.4 < seen.mean() < 0.5  # An 8 m square seen of the 12 m window; the rest unknown.
    error = np.abs(heights[seen] - truth[seen])
    # A cell holds the highest point within it: up to one cell's rise on a 55 deg wall above its centre.
    assert np.median(error) < 0.05 and error.max() < 0.1 * math.tan(math.radians(55)) + 0.05
    samples = np.c_[np.linspace(-3.0, 3.0, 50), np.linspace(-7.0, -1.0, 50)]
    assert np.nanmax(np.abs(grid.sample(heights, origin, samples) - TERRAIN.height(samples))) < 0.2


def test_rolling_keeps_the_overlap_and_unseen_cells_stay_unknown():
    grid, heights, origin = mapped(TERRAIN, np.array([0.0, -4.0, 0.0]))
    moved = grid.window_origin([1.0, -4.0])
    rolled = grid.roll(heights, origin, moved)
    np.testing.assert_array_equal(rolled[:, :-10], heights[:, 10:])
    assert np.isnan(rolled[:, -10:]).all()
    assert np.isnan(grid.fuse(grid.empty(), origin, np.zeros((0, 3)))).all()
    assert np.isnan(grid.fuse(grid.empty(), origin, np.full((5, 3), np.nan))).all()


def test_fusion_keeps_the_highest_point_and_blends_scans():
    grid = ElevationGrid(ElevationMapConfig(new_weight=0.5, reset_jump_m=0.3))
    origin = grid.window_origin([0.0, 0.0])
    one = grid.fuse(grid.empty(), origin, np.array([[0.05, 0.05, 0.0], [0.06, 0.06, 0.1]]))
    iy, ix = grid.shape[0] // 2, grid.shape[1] // 2
    assert one[iy, ix] == pytest.approx(0.1)
    assert grid.fuse(one, origin, np.array([[0.05, 0.05, 0.2]]))[iy, ix] == pytest.approx(0.15)
    assert grid.fuse(one, origin, np.array([[0.05, 0.05, 1.0]]))[iy, ix] == pytest.approx(1.0)  # A jump replaces.


@pytest.mark.parametrize("roll_deg, pitch_deg, yaw_deg", [(0, 0, 0), (20, 0, 30), (0, -25, -60), (15, 10, 120)])
def test_attitude_on_a_tilted_plane_equals_the_plane_angles(roll_deg, pitch_deg, yaw_deg):
    roll, pitch, yaw = np.radians([roll_deg, pitch_deg, yaw_deg])
    # The plane of a chassis with Drake's RollPitchYaw: its normal is R_WB's z column.
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    n = np.array([cy * sp * cr + sy * sr, sy * sp * cr - cy * sr, cp * cr])

    class Plane:
        def height(self, xy):
            return 0.3 - (n[0] * xy[..., 0] + n[1] * xy[..., 1]) / n[2]

    # The per-cell maximum biases a sloped cell by up to half its rise, unevenly by up to the
    # points' spacing times the slope: within half a degree with points 2 cm apart.
    grid, heights, origin = mapped(Plane(), np.array([1.0, 2.0, yaw]), spacing=0.02)
    attitude = predict_attitude(grid, heights, origin, np.array([[1.0, 2.0, yaw]]), clearance_m=0.2)
    assert math.degrees(attitude.roll[0]) == pytest.approx(roll_deg, abs=0.5)
    assert math.degrees(attitude.pitch[0]) == pytest.approx(pitch_deg, abs=0.5)
    assert not attitude.unknown[0] and not attitude.obstructed[0]


def test_margins_come_from_the_robot_dimensions_and_unknown_wheels_are_reported():
    side, axle = stability_margins(np.zeros(1), np.zeros(1))
    assert side[0] == pytest.approx(math.atan2(robot.TRACK_M / 2, robot.COM_HEIGHT_ABOVE_GROUND_M))
    assert axle[0] == pytest.approx(math.atan2(robot.WHEELBASE_M / 2, robot.COM_HEIGHT_ABOVE_GROUND_M))
    grid = ElevationGrid()
    origin = grid.window_origin([0.0, 0.0])
    heights = grid.empty()
    heights[:, : grid.shape[1] // 2] = 0.0  # Known west of x = 0, unknown east of it.
    attitude = predict_attitude(grid, heights, origin, np.array([[-2.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0, 0]]))
    assert attitude.unknown.tolist() == [False, True, True]
    assert attitude.margin[0] == pytest.approx(axle[0]) and np.isnan(attitude.margin[1:]).all()


def test_a_wall_between_the_wheels_obstructs_the_chassis():
    grid = ElevationGrid()
    origin = grid.window_origin([0.0, 0.0])
    heights = np.zeros(grid.shape)
    xs, _ = grid.cell_centers(origin)
    heights[:, np.abs(xs) < 0.1] = 1.0  # A 0.2 m thick, 1 m wall along y.
    attitude = predict_attitude(grid, heights, origin, np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]]), clearance_m=0.23)
    assert attitude.obstructed.tolist() == [True, False]


def heading_to_edge_deg(yaw):
    """Angle between a heading and the wide ditch's edge (along x), 0..90 deg."""
    return np.degrees(np.abs(np.arcsin(np.sin(yaw))))


def test_planner_refuses_head_on_and_crosses_a_55_degree_wall_at_a_shallow_angle():
    planner = MppiPlanner()
    steps = planner.steps
    # The robot on the foreslope's top, heading along the edge, goal straight across the ditch.
    pose = np.array([0.0, -TERRAIN.hinge_distance_m - 0.3, 0.0])
    grid, heights, origin = mapped(TERRAIN, pose)
    goal = np.array([0.0, 11.0])
    head_on = rollout(np.array([0.0, -TERRAIN.hinge_distance_m - 0.5, math.pi / 2]), np.zeros((1, steps)), 1.0, 0.1)
    cost, attitude = planner.costs(grid, heights, origin, head_on, np.zeros((1, steps)), 0.0, goal)
    assert cost[0] == np.inf and np.nanmin(attitude.axle_margin) < math.radians(10)
    nominal, last_w, angles = planner.initial_nominal(), 0.0, []
    for update in range(60):
        result = planner.plan(grid, heights, origin, pose, goal, nominal, last_w, np.random.default_rng(update))
        assert result.admissible and result.label in range(actions.NUM_LABELS)
        nominal, last_w = result.next_nominal, result.command[1]
        pose = rollout(pose, np.array([result.command[1]]), 1.0, 0.1)[0, 1]
        if TERRAIN.height(pose[None, :2])[0] < -0.5:  # On the wall.
            angles.append(heading_to_edge_deg(pose[2]))
        assert np.nanmin(result.margins) >= math.radians(planner.config.margin_threshold_deg) - 1e-9
    assert angles, "it went down the wall within 6 s"
    assert 8.0 < np.median(angles) < 30.0  # Shallow: far from perpendicular (90).


def test_empty_map_is_graceful_and_a_goal_in_the_unknown_is_approached():
    planner = MppiPlanner()
    grid = ElevationGrid()
    pose = np.array([0.0, 0.0, 0.0])
    result = planner.plan(grid, grid.empty(), grid.window_origin(pose[:2]), pose, np.array([5.0, 5.0]),
                          planner.initial_nominal(), 0.0, np.random.default_rng(0))
    assert result.admissible and result.command[1] > 0.0  # Turns left, toward the goal.
    assert result.unknown.all() and np.isnan(result.margins).all()


def test_same_seed_same_plan_and_result_sizes():
    planner = MppiPlanner(MppiPlannerConfig(samples=64))
    pose = np.array([0.0, -TERRAIN.hinge_distance_m - 1.0, math.pi / 2])
    grid, heights, origin = mapped(TERRAIN, pose)
    plans = [planner.plan(grid, heights, origin, pose, np.array([0.0, 11.0]), planner.initial_nominal(), 0.0,
                          np.random.default_rng(seed)) for seed in (7, 7, 8)]
    np.testing.assert_array_equal(plans[0].optimal, plans[1].optimal)
    assert not np.array_equal(plans[0].sample_poses, plans[2].sample_poses)
    assert plans[0].sample_poses.shape == (64, planner.steps + 1, 3) and plans[0].poses.shape == (planner.steps + 1, 3)
    np.testing.assert_array_equal(plans[0].next_nominal[:-1], plans[0].optimal[1:])


@pytest.mark.parametrize("key, value", [("samples", 3), ("horizon_s", 0.0), ("temperature", -1.0),
                                        ("margin_threshold_deg", 95.0), ("noise_sigma_w", float("nan")),
                                        ("seed", -1), ("fore_aft_margin_threshold_deg", 90.0)])
def test_planner_config_out_of_range_names_the_key(key, value):
    with pytest.raises(ConfigError, match=key):
        MppiPlanner(MppiPlannerConfig(**{key: value}))


@pytest.mark.parametrize("key, value", [("resolution_m", 0.0), ("size_m", 0.1), ("new_weight", 1.5),
                                        ("reset_jump_m", 0.0)])
def test_map_config_out_of_range_names_the_key(key, value):
    with pytest.raises(ConfigError, match=key):
        ElevationGrid(ElevationMapConfig(**{key: value}))
