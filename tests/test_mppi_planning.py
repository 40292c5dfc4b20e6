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
                                        ("seed", -1), ("fore_aft_margin_threshold_deg", 90.0),
                                        ("climb_fore_aft_margin_threshold_deg", -1.0)])
def test_planner_config_out_of_range_names_the_key(key, value):
    with pytest.raises(ConfigError, match=key):
        MppiPlanner(MppiPlannerConfig(**{key: value}))


@pytest.mark.parametrize("key, value", [("resolution_m", 0.0), ("size_m", 0.1), ("new_weight", 1.5),
                                        ("reset_jump_m", 0.0)])
def test_map_config_out_of_range_names_the_key(key, value):
    with pytest.raises(ConfigError, match=key):
        ElevationGrid(ElevationMapConfig(**{key: value}))


def test_unknown_cells_next_to_known_ground_are_presumed_to_drop_away():
    from ditch_drake.planning.elevation_map import presume_drops

    heights = np.full((40, 40), np.nan)
    heights[:20] = 0.5  # Known rows 0..19, unknown beyond.
    presumed = presume_drops(heights, 0.1, 55.0, 1.0)
    np.testing.assert_array_equal(presumed[:20], heights[:20])  # Known cells keep their heights.
    drop = 0.5 - presumed[20:30, 7]
    np.testing.assert_allclose(drop, np.arange(1, 11) * 0.1 * math.tan(math.radians(55.0)))
    assert np.isnan(presumed[31:]).all()  # Beyond max_distance_m: still unknown.
    assert np.isnan(presume_drops(np.full((8, 8), np.nan), 0.1, 55.0, 1.0)).all()
    np.testing.assert_array_equal(presume_drops(heights, 0.1, 55.0, 0.0)[20:], heights[20:])  # Off.


def shadowed_map(pose):
    """The wide ditch mapped as the lidar sees it from its near side: the flat field up to the
    hinge is known, the wall below the hinge (in the lidar's shadow) and beyond it unknown."""
    grid = ElevationGrid()
    origin = grid.window_origin(pose[:2])
    cloud = terrain_cloud(TERRAIN, pose[:2])
    cloud = cloud[(cloud[:, 2] > -0.02) & (cloud[:, 1] < 0.0)]
    return grid, grid.fuse(grid.empty(), origin, cloud), origin


def test_a_presumed_drop_lines_up_a_shallow_angle_before_the_hinge():
    planner = MppiPlanner()
    pose = np.array([0.0, -TERRAIN.hinge_distance_m - 3.0, math.pi / 2])  # Head-on, 3 m before the edge.
    goal = np.array([0.0, 11.0])
    nominal, last_w = planner.initial_nominal(), 0.0
    for update in range(80):
        grid, heights, origin = shadowed_map(pose)
        if update == 0:  # Head-on into the shadow: inadmissible, as a presumed 55 deg wall.
            head_on = rollout(pose, np.zeros((1, planner.steps)), 1.0, 0.1)
            assert planner.costs(grid, planner.planning_heights(grid, heights), origin, head_on,
                                 np.zeros((1, planner.steps)), 0.0, goal)[0][0] == np.inf
        result = planner.plan(grid, heights, origin, pose, goal, nominal, last_w, np.random.default_rng(update))
        assert result.admissible
        nominal, last_w = result.next_nominal, result.command[1]
        pose = rollout(pose, np.array([result.command[1]]), 1.0, 0.1)[0, 1]
        if TERRAIN.height(pose[None, :2])[0] < -0.3:  # Over the edge, onto the (unseen) wall.
            break
    else:
        pytest.fail("it never went over the edge")
    assert heading_to_edge_deg(pose[2]) < 30.0  # Already shallow when the wall comes.


def test_with_no_admissible_sample_it_drives_the_least_bad_one_or_stops():
    # On the 55 deg wall heading along the edge: the sideways margin (6.6 deg) is below the
    # threshold from the first step on, so no sample is admissible.
    pose = np.array([0.0, -TERRAIN.hinge_distance_m + 1.4, 0.0])
    grid, heights, origin = mapped(TERRAIN, pose)
    now = predict_attitude(grid, heights, origin, pose[None])
    assert math.degrees(now.side_margin[0]) < 8.0
    for fallback in (True, False):
        planner = MppiPlanner(MppiPlannerConfig(fallback=fallback, margin_threshold_deg=10.0))
        result = planner.plan(grid, heights, origin, pose, np.array([0.0, 11.0]), planner.initial_nominal(), 0.0,
                              np.random.default_rng(0))
        assert not result.admissible and result.fallback == fallback
        if fallback:
            # Driven, not stopped: at the label speed, its margins no worse than going straight on.
            assert result.command[0] == 1.0 and result.label in range(actions.NUM_LABELS)
            straight = rollout(pose, np.zeros((1, planner.steps)), 1.0, 0.1)
            along = predict_attitude(grid, heights, origin, straight[:, 1:])
            assert np.nanmin(result.margins) >= np.nanmin(along.margin) - 1e-9
        else:
            assert result.label == -1 and np.array_equal(result.command, [0.0, 0.0])


def test_turn_then_hold_samples_are_in_every_update():
    from ditch_drake.planning.mppi import HOLD_TURNS

    planner = MppiPlanner(MppiPlannerConfig(samples=128))
    pose = np.zeros(3)
    grid = ElevationGrid()
    result = planner.plan(grid, np.zeros(grid.shape), grid.window_origin(pose[:2]), pose, np.array([5.0, 0.0]),
                          planner.initial_nominal(), 0.0, np.random.default_rng(0))
    final_yaw = np.degrees(result.sample_poses[:, -1, 2])
    for _rate, angle in HOLD_TURNS:  # A sample that turned by about each angle and then held it.
        for sign in (1, -1):
            assert np.min(np.abs(final_yaw - sign * angle)) < 3.0
    assert len(HOLD_TURNS) * 2 + actions.NUM_LABELS + 2 <= 64
    # Fewer samples: as many structured ones as fit, labels first, one noisy sample kept.
    assert len(MppiPlanner(MppiPlannerConfig(samples=40))._fixed) == 40 - 2
    assert len(MppiPlanner(MppiPlannerConfig(samples=40, hold_samples=False))._fixed) == actions.NUM_LABELS


def test_edge_following_samples_hold_an_angle_to_the_contour_of_a_slope():
    # A 30 deg plane falling to +y (its contours run along x); the robot on it heading along +x.
    grid = ElevationGrid()
    pose = np.array([0.0, 0.0, 0.0])
    origin = grid.window_origin(pose[:2])
    _, ys = grid.cell_centers(origin)
    heights = np.broadcast_to(-math.tan(math.radians(30.0)) * ys[:, None], grid.shape).copy()
    planner = MppiPlanner(MppiPlannerConfig(contour_samples=True))
    w = planner.contour_sequences(grid, heights, origin, pose, np.array([0.0, 20.0]))
    final_yaw = np.degrees(rollout(pose, w, 1.0, 0.1)[:, -1, 2])
    # Along +x: down the slope (toward +y) and up it at 12, 20, 28 deg to the contour; the samples
    # along -x are still turning round (from +x) at the horizon's end.
    for angle in (12.0, 20.0, 28.0):
        for target in (angle, -angle):
            assert np.min(np.abs(final_yaw - target)) < 1.0
    assert (np.abs(final_yaw) > 140.0).sum() == 6


def test_drop_ahead_cost_charges_driving_at_an_edge_not_along_it():
    pose_at = np.array([0.0, -TERRAIN.hinge_distance_m - 2.0, math.pi / 2])
    grid, heights, origin = shadowed_map(pose_at)
    steps = MppiPlanner().steps
    at_edge = rollout(pose_at, np.zeros((1, steps)), 1.0, 0.1)[:, :16]  # 1.5 s straight at the edge.
    along = rollout(np.array([0.0, pose_at[1], 0.0]), np.zeros((1, steps)), 1.0, 0.1)[:, :16]
    for poses in (at_edge, along):
        costs = [MppiPlanner(MppiPlannerConfig(drop_ahead_cost=cost, presumed_drop_m=1.5)).costs(
            grid, MppiPlanner().planning_heights(grid, heights), origin, poses, np.zeros((1, 15)), 0.0,
            np.array([0.0, 11.0]))[0][0] for cost in (0.0, 6.0)]
        assert (costs[1] > costs[0]) == (poses is at_edge)


def test_turning_lean_narrows_the_sideways_margin():
    pose = np.array([0.0, -TERRAIN.hinge_distance_m + 1.4, math.radians(10.0)])  # On the wall, 10 deg down.
    grid, heights, origin = mapped(TERRAIN, pose)
    w = np.full((1, 5), 0.85)
    poses = rollout(pose, w, 1.0, 0.1)
    plain, lean = (MppiPlanner(MppiPlannerConfig(turn_lean=flag, margin_threshold_deg=8.0))._costs(
        grid, heights, origin, poses, w, 0.85, np.array([0.0, 11.0]), 0)[2][0] for flag in (False, True))
    assert lean > plain  # The same turn falls further short of the sideways threshold when turning.


def test_a_climb_threshold_admits_a_steeper_climb_but_not_a_steeper_descent():
    # Straight at 35 deg to the edge over the middle of the 55 deg walls: up the far one (nose up),
    # and down the near one (nose down): the same pitch, the fore-aft margin about 12 deg.
    middle = (TERRAIN.toe_distance_m + TERRAIN.hinge_distance_m) / 2
    w = np.zeros((1, 10))
    costs = {}
    for name, y in (("climb", middle - 0.5), ("descent", -middle - 0.5)):
        pose = np.array([0.0, y, math.radians(35.0)])
        grid, heights, origin = mapped(TERRAIN, pose)
        poses = rollout(pose, w, 1.0, 0.1)
        for threshold in (None, 11.0):
            planner = MppiPlanner(MppiPlannerConfig(climb_fore_aft_margin_threshold_deg=threshold))
            cost, attitude = planner.costs(grid, heights, origin, poses, w, 0.0, np.array([5.0, 11.0]))
            assert np.all(np.degrees(attitude.axle_margin) > 11.0) and np.all(np.degrees(attitude.axle_margin) < 16.0)
            costs[name, threshold] = cost[0]
    assert costs["climb", None] == np.inf and np.isfinite(costs["climb", 11.0])
    assert costs["descent", None] == np.inf and costs["descent", 11.0] == np.inf
