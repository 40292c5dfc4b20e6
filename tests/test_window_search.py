"""The search for a way in and out of a ditch crossable only in places: the map logic on synthetic
and analytic walls, the block's ports, and the block wired into the mppi baseline."""

import math

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.systems.analysis import Simulator

from ditch_drake.common.config_yaml import config_to_yaml
from ditch_drake.common.errors import ConfigError
from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.diagrams.rollout import MakeRolloutDiagram, MppiBaselineConfig, RolloutConfig
from ditch_drake.planning import crossing_windows as windows
from ditch_drake.planning.elevation_map import ElevationGrid
from ditch_drake.systems.window_search import SearchPhase, WindowSearch, WindowSearchConfig
from ditch_drake.world.environments import get_environment
from ditch_drake.world.terrain import DitchTerrain

RESOLUTION_M = 0.1
STEEP_HINGE_Y = -2.0  # The steep wall's hinge; the ditch lies at larger y.
WINDOW_DEG = 50.0
WINDOW_SET_BACK_M = 1.5  # The window's hinge lies this much further from the ditch.
SEEN_DEPTH_M = 1.5  # The lidar sees the window's wall down to this depth; the rest is in shadow.


def _map_of_a_ditch(window_x: tuple[float, float], robot_xy=(0.0, -4.0), size_m: float = 16.0):
    """What the lidar leaves of a straight ditch (along x, the robot's side at y below it) in a
    map: the top known, the steep wall in shadow (unknown), a window's gentle wall between x
    `window_x` set back and seen down to `SEEN_DEPTH_M`. Returns (origin_xy, heights)."""
    n = round(size_m / RESOLUTION_M)
    origin = np.asarray(robot_xy) - size_m / 2
    xs, ys = windows.cell_centres(np.zeros((n, n)), origin, RESOLUTION_M)
    in_window = (xs >= window_x[0]) & (xs <= window_x[1])
    hinge_y = np.where(in_window, STEEP_HINGE_Y - WINDOW_SET_BACK_M, STEEP_HINGE_Y)
    depth = np.where(ys > hinge_y, (ys - hinge_y) * math.tan(math.radians(WINDOW_DEG)), 0.0)
    heights = np.where(ys <= hinge_y, 0.0, np.where(in_window & (depth <= SEEN_DEPTH_M), -depth, np.nan))
    return origin, heights


def _search_window(window_x):
    origin, heights = _map_of_a_ditch(window_x)
    robot_xy = np.array([0.0, -4.0])
    frame = windows.find_edge(heights, origin, RESOLUTION_M, robot_xy, math.pi / 2, 0.0)
    assert frame is not None
    np.testing.assert_allclose(np.abs(frame.along), [1.0, 0.0], atol=0.02)
    np.testing.assert_allclose(frame.across, [0.0, 1.0], atol=0.02)  # Into the ditch.
    assert frame.origin_xy[1] == pytest.approx(STEEP_HINGE_Y, abs=0.15)
    edges = np.arange(-40, 41) * 0.5
    slopes = windows.wall_slopes(heights, origin, RESOLUTION_M, frame, edges, 0.0, (-3.0, 3.0), rising=False)
    found = windows.crossable_windows(edges, slopes, 55.0, 1.5)
    assert len(found) == 1
    s_robot, _ = frame.coordinates(robot_xy)
    window = windows.nearest_window(found, s_robot)
    direction = math.copysign(1.0, (window[0] + window[1]) / 2 - s_robot)
    target = frame.point(windows.along_target(window, s_robot, direction, 5.0, 0.5), 4.0)
    return frame, slopes, edges, window, target


@pytest.mark.parametrize("window_x", [(-7.0, -3.0), (3.0, 7.0)], ids=["window_left", "window_right"])
def test_the_map_logic_finds_the_window_and_aims_inside_it(window_x):
    frame, slopes, _, window, target = _search_window(window_x)
    x_ends = sorted(frame.point(s, 0.0)[0] for s in window)
    assert x_ends[0] == pytest.approx(window_x[0], abs=0.6)
    assert x_ends[1] == pytest.approx(window_x[1], abs=0.6)
    assert window_x[0] < target[0] < window_x[1]
    assert target[1] > STEEP_HINGE_Y  # Across the edge: into the ditch.
    inside = np.isfinite(slopes)
    assert np.all(np.abs(slopes[inside] - WINDOW_DEG) < 2.0)  # Only the window is seen, at its slope.


def test_an_unseen_wall_is_no_window_and_nothing_is_no_edge():
    origin, heights = _map_of_a_ditch((30.0, 31.0))  # The window out of the map.
    frame = windows.find_edge(heights, origin, RESOLUTION_M, (0.0, -4.0), math.pi / 2, 0.0)
    edges = np.arange(-20, 21) * 0.5
    slopes = windows.wall_slopes(heights, origin, RESOLUTION_M, frame, edges, 0.0, (-3.0, 3.0), rising=False)
    assert np.isnan(slopes).all()
    assert windows.crossable_windows(edges, slopes, 55.0, 1.5) == []
    flat = np.zeros_like(heights)
    assert windows.find_edge(flat, origin, RESOLUTION_M, (0.0, -4.0), math.pi / 2, 0.0) is None


def test_crossable_windows_need_length_and_known_slopes():
    edges = np.arange(11) * 0.5
    slopes = np.array([70, 50, 50, np.nan, 50, 50, 50, 50, 70, 54, 56.0])
    assert windows.crossable_windows(edges, slopes, 55.0, 1.5) == [(2.0, 4.0)]
    assert windows.crossable_windows(edges, slopes, 55.0, 0.5) == [(0.5, 1.5), (2.0, 4.0), (4.5, 5.0)]
    assert windows.along_target((2.0, 4.0), 0.0, 1.0, 5.0, 0.5) == 3.5
    assert windows.along_target((2.0, 4.0), 3.0, -1.0, 5.0, 0.5) == 2.5


def test_a_crossing_travels_the_way_the_window_has_room_for():
    window = (0.0, 10.0)
    assert windows.crossing_direction(window, 2.0, 1.0, 3.5) == 1.0  # Room ahead.
    assert windows.crossing_direction(window, 8.0, 1.0, 3.5) == -1.0  # Near its end: back along it.
    assert windows.crossing_direction(window, 12.0, 1.0, 3.5) == -1.0  # Past its end: back into it.
    assert windows.crossing_direction(window, -3.0, 1.0, 3.5) == 1.0  # Short of it: on into it.
    assert windows.crossing_direction((0.0, 2.0), 0.5, 1.0, 3.5) == 1.0  # Short both ways: the roomier.
    assert windows.crossing_direction((0.0, 2.0), 1.5, 1.0, 3.5) == -1.0  # ... chosen anew past the middle.


def test_a_crossing_under_way_keeps_its_way_to_the_windows_end():
    window = (0.0, 10.0)
    assert windows.crossing_direction(window, 8.0, 1.0, 3.5, under_way=True, turn_m=0.5) == 1.0
    assert windows.crossing_direction(window, 9.7, 1.0, 3.5, under_way=True, turn_m=0.5) == -1.0
    assert windows.crossing_direction(window, 12.0, 1.0, 3.5, under_way=True, turn_m=0.5) == -1.0
    assert windows.crossing_direction((0.0, 2.0), 1.5, 1.0, 3.5, under_way=True, turn_m=0.5) == 1.0
    assert windows.crossing_direction((0.0, 2.0), 0.4, -1.0, 3.5, under_way=True, turn_m=0.5) == 1.0


@pytest.mark.parametrize("x, slope_deg", [(-15.0, 50.0), (15.0, 70.0)])
def test_slope_estimates_of_the_analytic_walls_are_within_two_degrees(x, slope_deg):
    terrain = DitchTerrain(get_environment("wide_search").terrain)
    n = 120
    origin = np.array([x - 6.0, -6.0])
    xs, ys = windows.cell_centres(np.zeros((n, n)), origin, RESOLUTION_M)
    heights = terrain.height(np.stack([xs, ys], axis=-1).reshape(-1, 2)).reshape(n, n)
    top = float(terrain.height(np.array([[x, -11.0]]))[0])
    floor = float(terrain.height(np.array([[x, 0.0]]))[0])
    for across, reference, rising, band in ((np.array([0.0, 1.0]), top, False, (-6.0, 0.0)),
                                            (np.array([0.0, -1.0]), floor, True, (-6.0, 0.0))):
        # Near wall (y < 0, falling toward the ditch) from the top; the same wall seen as a far
        # wall from the floor (rising away from it).
        along = np.array([across[1], -across[0]])
        frame = windows.EdgeFrame(np.array([x, 0.0]), along, across)
        edges = np.array([-2.0, -1.0, 0.0, 1.0, 2.0])
        band_c = band if not rising else (0.0, 6.0)
        slopes = windows.wall_slopes(heights, origin, RESOLUTION_M, frame, edges, reference, band_c, rising)
        np.testing.assert_allclose(slopes, slope_deg, atol=2.0)


def test_the_ditchs_rounded_end_reads_steep_not_as_a_window():
    """At wide_search's west end (x about -33 m) the wall turns across the edge line: heights
    fall along it, and the plane fit reads its steepest slope, the end's 70 deg."""
    terrain = DitchTerrain(get_environment("wide_search").terrain)
    n = 120
    origin = np.array([-37.0, -6.0])
    xs, ys = windows.cell_centres(np.zeros((n, n)), origin, RESOLUTION_M)
    heights = terrain.height(np.stack([xs, ys], axis=-1).reshape(-1, 2)).reshape(n, n)
    frame = windows.EdgeFrame(np.array([0.0, -3.3]), np.array([-1.0, 0.0]), np.array([0.0, 1.0]))
    edges = np.arange(28, 36) * 1.0  # x from -28 to -36 m.
    slopes = windows.wall_slopes(heights, origin, RESOLUTION_M, frame, edges, 0.0, (-3.0, 3.0), rising=False)
    assert windows.crossable_windows(edges, slopes, WindowSearchConfig().crossable_slope_deg, 1.5) == []
    assert np.nanmin(slopes) > 65.0


def test_the_ends_of_the_way_along_are_seen_ahead():
    origin, heights = _map_of_a_ditch((30.0, 31.0))
    frame = windows.EdgeFrame(np.array([0.0, STEEP_HINGE_Y]), np.array([-1.0, 0.0]), np.array([0.0, 1.0]))
    ahead = (1.0, 3.0)
    assert not windows.edge_ended(heights, origin, RESOLUTION_M, frame, ahead, (0.5, 3.0), 0.0)  # In shadow.
    level = np.where(np.isfinite(heights), heights, 0.0)  # The ditch ended: level ground beyond the line.
    assert windows.edge_ended(level, origin, RESOLUTION_M, frame, ahead, (0.5, 3.0), 0.0)
    floor = np.full_like(heights, -4.0)
    assert not windows.floor_ended(floor, origin, RESOLUTION_M, frame, ahead, (1.0, 2.0), -4.0)
    xs, _ = windows.cell_centres(floor, origin, RESOLUTION_M)
    floor[xs < -2.0] = -3.0  # A wall across the floor 2 m ahead (along is -x).
    assert windows.floor_ended(floor, origin, RESOLUTION_M, frame, ahead, (1.0, 2.0), -4.0)


def _search_block(config=None) -> WindowSearch:
    return WindowSearch([0.0, 11.0], 0, ElevationGrid(), config)


def test_window_search_ports_and_its_first_target_is_the_goal():
    block = _search_block()
    assert [block.get_input_port(i).get_name() for i in range(block.num_input_ports())] == \
        ["elevation_map", "body_poses"]
    assert block.GetInputPort("elevation_map").size() == 2 + 120 * 120
    assert block.GetOutputPort("target_xy").size() == 2
    assert block.GetOutputPort("phase").size() == 1
    context = block.CreateDefaultContext()
    np.testing.assert_allclose(block.GetOutputPort("target_xy").Eval(context), [0.0, 11.0])
    assert block.GetOutputPort("phase").Eval(context)[0] == SearchPhase.APPROACH


def test_window_search_goes_along_the_edge_then_commits_to_the_window_it_sees():
    block = _search_block()
    grid = ElevationGrid()
    context = block.CreateDefaultContext()
    origin, heights = _map_of_a_ditch((-30.0, -29.0), size_m=12.0)  # The window out of sight.
    pose = RigidTransform(RollPitchYaw(0, 0, math.pi / 2), [0.0, -4.0, 0.3])
    block.GetInputPort("body_poses").FixValue(context, [pose])
    block.GetInputPort("elevation_map").FixValue(context, grid.pack(origin, heights))
    simulator = Simulator(block, context)
    simulator.AdvanceTo(0.15)
    assert block.GetOutputPort("phase").Eval(context)[0] == SearchPhase.SEARCH_IN
    target = block.GetOutputPort("target_xy").Eval(context)
    assert target[0] == pytest.approx(-3.0, abs=0.2)  # To the left facing the ditch: the goal lies square across.
    assert target[1] == pytest.approx(STEEP_HINGE_Y - WindowSearchConfig().edge_standoff_m, abs=0.2)  # Short of the edge.
    origin, heights = _map_of_a_ditch((-7.0, -3.0), size_m=12.0)
    block.GetInputPort("elevation_map").FixValue(context, grid.pack(origin, heights))
    simulator.AdvanceTo(0.25)
    assert block.GetOutputPort("phase").Eval(context)[0] == SearchPhase.GOING_IN
    target = block.GetOutputPort("target_xy").Eval(context)
    # Still facing the ditch, not along the way in: first turned along the top, toward the window.
    assert target[0] == pytest.approx(-3.0, abs=0.2) and target[1] < STEEP_HINGE_Y
    pose = RigidTransform(RollPitchYaw(0, 0, math.pi), [0.0, -4.0, 0.3])
    block.GetInputPort("body_poses").FixValue(context, [pose])
    simulator.AdvanceTo(0.35)
    target = block.GetOutputPort("target_xy").Eval(context)
    assert -7.0 < target[0] < -3.0 and target[1] > STEEP_HINGE_Y  # Heading along: into the window.


def test_window_search_turns_back_twice_as_far_out_each_time():
    """No window anywhere: the search goes `first_leg_m` (8 m) to its left facing the ditch
    (the goal lies square across), then back to 16 m the other side of its start, then 32 m."""
    block = _search_block()
    grid = ElevationGrid()
    context = block.CreateDefaultContext()
    simulator = Simulator(block, context)
    turns = []
    for x in [0.0, *np.arange(-1.0, -9.0, -1.0), *np.arange(-8.0, 17.0, 1.0), *np.arange(16.0, -33.0, -2.0)]:
        origin, heights = _map_of_a_ditch((-90.0, -89.0), robot_xy=(x, -4.0), size_m=12.0)
        yaw = math.pi / 2 if x == 0.0 else 0.0
        block.GetInputPort("body_poses").FixValue(context, [RigidTransform(RollPitchYaw(0, 0, yaw), [x, -4.0, 0.3])])
        block.GetInputPort("elevation_map").FixValue(context, grid.pack(origin, heights))
        simulator.AdvanceTo(context.get_time() + 0.1)
        assert block.GetOutputPort("phase").Eval(context)[0] == SearchPhase.SEARCH_IN
        heading = math.copysign(1.0, block.GetOutputPort("target_xy").Eval(context)[0] - x)
        if not turns or heading != turns[-1][1]:
            turns.append((x, heading))
    assert [heading for _, heading in turns] == [-1.0, 1.0, -1.0, 1.0]
    assert [x for x, _ in turns[1:]] == [-8.0, 16.0, -32.0]


def test_window_search_turned_at_the_ditchs_end_searches_the_other_side():
    """The ditch ends at x -5 (beyond it, level ground; the hinge recedes over its last 3 m, a
    rounded end), on the first leg's side. The search turns back there; the robot, turning, carries
    on 2 m past the end, where the ground 1-3 m ahead the new way is still the end's level ground.
    That is no end of the new side: the search goes on along it instead of giving up."""
    block = _search_block()
    grid = ElevationGrid()
    context = block.CreateDefaultContext()
    simulator = Simulator(block, context)
    end_x, taper_m = -5.0, 3.0

    def map_at(x):
        origin, heights = _map_of_a_ditch((-90.0, -89.0), robot_xy=(x, -4.0), size_m=12.0)
        xs, ys = windows.cell_centres(heights, origin, RESOLUTION_M)
        hinge_y = STEEP_HINGE_Y + np.clip(end_x + taper_m - xs, 0.0, None)
        return origin, np.where((xs < end_x) | (ys <= hinge_y), 0.0, heights)

    phases, headings = [], []
    for x in [0.0, *np.arange(-1.0, -8.0, -1.0), *np.arange(-6.0, 4.0, 1.0)]:
        yaw = math.pi / 2 if x == 0.0 else 0.0
        block.GetInputPort("body_poses").FixValue(context, [RigidTransform(RollPitchYaw(0, 0, yaw), [x, -4.0, 0.3])])
        block.GetInputPort("elevation_map").FixValue(context, grid.pack(*map_at(x)))
        simulator.AdvanceTo(context.get_time() + 0.1)
        phases.append(SearchPhase(int(block.GetOutputPort("phase").Eval(context)[0])))
        headings.append(math.copysign(1.0, block.GetOutputPort("target_xy").Eval(context)[0] - x))
    assert phases == [SearchPhase.SEARCH_IN] * len(phases)
    turned = headings.index(1.0)
    assert headings[:turned] == [-1.0] * turned and headings[turned:] == [1.0] * (len(headings) - turned)
    assert turned <= 5  # At x -4 or before: the end seen ahead, not reached by the reach of the leg (-8).


@pytest.mark.parametrize("hold_way_m, turned_at_x", [(None, -7.0), (0.5, -12.0)])
def test_window_search_on_the_top_turns_back_at_the_windows_end_only_when_holding_its_way(hold_way_m, turned_at_x):
    """Committed to the window from x -12 to -2 m and driving along the top toward -x: chosen
    anew, the way turns back at x -7, where the window leaves less than the descent's lead and
    margin (5.5 m) ahead and more behind; held, only past the window's usable end."""
    block = _search_block(WindowSearchConfig(hold_way_m=hold_way_m))
    grid = ElevationGrid()
    context = block.CreateDefaultContext()
    simulator = Simulator(block, context)
    ways = []
    for x in [-2.0, *np.arange(-3.0, -13.0, -1.0)]:
        origin, heights = _map_of_a_ditch((-12.0, -2.0), robot_xy=(x, -4.0), size_m=12.0)
        yaw = math.pi / 2 if x == -2.0 else math.pi
        block.GetInputPort("body_poses").FixValue(context, [RigidTransform(RollPitchYaw(0, 0, yaw), [x, -4.0, 0.3])])
        block.GetInputPort("elevation_map").FixValue(context, grid.pack(origin, heights))
        simulator.AdvanceTo(context.get_time() + 0.1)
        if x != -2.0:
            assert block.GetOutputPort("phase").Eval(context)[0] == SearchPhase.GOING_IN
            ways.append((x, math.copysign(1.0, block.GetOutputPort("target_xy").Eval(context)[0] - x)))
    first_turn = next(x for x, way in ways if way > 0)
    assert first_turn == turned_at_x
    assert all(way < 0 for x, way in ways if x > turned_at_x)


# Where a window's wall has fallen 0.3 m below the top (`nearest_drop`'s least drop), across from the edge line.
WINDOW_DROP_C_M = -WINDOW_SET_BACK_M + 0.3 / math.tan(math.radians(WINDOW_DEG))


@pytest.mark.parametrize("keep_off_seen_drops, target_y", [(False, STEEP_HINGE_Y - 0.8),
                                                            (True, STEEP_HINGE_Y + WINDOW_DROP_C_M - 0.8)])
def test_window_search_keeps_off_a_set_back_hinge_it_sees_only_when_asked(keep_off_seen_drops, target_y):
    """A gentle section too short to cross (1 m) has its hinge set back 1.5 m from the edge
    line, where the search's target along the top lies 3 m ahead: kept off the drops seen, the
    target stays the standoff short of where that wall is seen to fall, not of the line."""
    block = _search_block(WindowSearchConfig(keep_off_seen_drops=keep_off_seen_drops))
    grid = ElevationGrid()
    context = block.CreateDefaultContext()
    origin, heights = _map_of_a_ditch((-3.5, -2.5), size_m=12.0)
    block.GetInputPort("body_poses").FixValue(context, [RigidTransform(RollPitchYaw(0, 0, math.pi / 2),
                                                                       [0.0, -4.0, 0.3])])
    block.GetInputPort("elevation_map").FixValue(context, grid.pack(origin, heights))
    Simulator(block, context).AdvanceTo(0.15)
    assert block.GetOutputPort("phase").Eval(context)[0] == SearchPhase.SEARCH_IN
    target = block.GetOutputPort("target_xy").Eval(context)
    assert target[0] == pytest.approx(-3.0, abs=0.2)
    assert target[1] == pytest.approx(target_y, abs=0.2)


def test_the_nearest_drop_is_the_set_back_hinge_where_one_is_seen():
    origin, heights = _map_of_a_ditch((-6.0, -3.0), size_m=12.0)
    frame = windows.EdgeFrame(np.array([0.0, STEEP_HINGE_Y]), np.array([-1.0, 0.0]), np.array([0.0, 1.0]))
    beside = windows.nearest_drop(heights, origin, RESOLUTION_M, frame, (4.0, 5.0), (-3.0, 3.0), 0.0)
    assert beside == pytest.approx(WINDOW_DROP_C_M, abs=0.15)
    assert math.isnan(windows.nearest_drop(heights, origin, RESOLUTION_M, frame, (0.0, 1.0), (-3.0, 3.0), 0.0))


def test_window_search_config_rejects_bad_values():
    with pytest.raises(ConfigError, match="keep_off_seen_drops"):
        WindowSearchConfig(keep_off_seen_drops="yes").validate()
    with pytest.raises(ConfigError, match="hold_way_m"):
        WindowSearchConfig(hold_way_m=0.0).validate()
    WindowSearchConfig(hold_way_m=None).validate()
    with pytest.raises(ConfigError, match="crossable_slope_deg"):
        WindowSearchConfig(crossable_slope_deg=95.0).validate()
    with pytest.raises(ConfigError, match="min_window_m"):
        WindowSearchConfig(min_window_m=-1.0).validate()


def test_mppi_with_search_builds_the_block_in_the_diagram():
    config = RolloutConfig(SceneConfig(environment="wide_search", task=0),
                           MppiBaselineConfig(search=WindowSearchConfig()))
    diagram, _ = MakeRolloutDiagram(config)
    search = diagram.GetSubsystemByName("window_search")
    mppi = diagram.GetSubsystemByName("mppi")
    assert mppi.HasInputPort("target_xy")
    context = diagram.CreateDefaultContext()
    np.testing.assert_allclose(search.GetOutputPort("target_xy").Eval(search.GetMyContextFromRoot(context)),
                               [0.0, 11.0])
    plain, _ = MakeRolloutDiagram(RolloutConfig(SceneConfig(environment="wide_search", task=0),
                                                MppiBaselineConfig()))
    assert not plain.HasSubsystemNamed("window_search")
    assert "search" not in config_to_yaml(MppiBaselineConfig())  # Recorded rollouts keep their keys.
    assert not plain.GetSubsystemByName("mppi").HasInputPort("target_xy")


@pytest.mark.slow
def test_mppi_with_search_follows_the_edge_to_the_window_in_wide_search():
    """Task 0 goes square across; the windows lie west (x from -25 to -5 m): the search goes
    along the edge to its left, sees the window and aims into it (about 12 s simulated)."""
    from ditch_drake.diagrams.rollout import RunEpisode

    config = RolloutConfig(SceneConfig(environment="wide_search", task=0),
                           MppiBaselineConfig(search=WindowSearchConfig()))
    diagram, scene = MakeRolloutDiagram(config)
    search = diagram.GetSubsystemByName("window_search")
    trace = []

    def watch(root):
        context = search.GetMyContextFromRoot(root)
        trace.append((int(search.GetOutputPort("phase").Eval(context)[0]),
                      search.GetOutputPort("target_xy").Eval(context).copy()))

    RunEpisode(Simulator(diagram), diagram, scene, 0, watch=watch, watch_period_s=0.5, end_time_s=12.0)
    phases = [phase for phase, _ in trace]
    assert phases == sorted(phases)  # Phases only move on.
    assert SearchPhase.SEARCH_IN in phases and phases[-1] == SearchPhase.GOING_IN
    along_edge = [target for phase, target in trace if phase == SearchPhase.SEARCH_IN]
    assert along_edge[-1][0] < along_edge[0][0] < 0.0  # Along the edge, westward.
    going_in = [target for phase, target in trace if phase == SearchPhase.GOING_IN]
    assert all(-25.0 < target[0] < -5.0 and target[1] > -4.5 for target in going_in)  # Into the window.
