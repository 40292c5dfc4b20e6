"""The windows of a ditch crossable only in places, and the expert's route through them: the
intervals of the packaged search ditches, the planned route's ends inside the windows, the runs
steepened in narrow windows only, the climb steered onto its planned exit, the plain driver kept
where no wall is too steep, and one rollout that crosses through a window."""

import math

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.systems.analysis import Simulator

from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.diagrams.rollout import ExpertConfig, MakeRolloutDiagram, RolloutConfig, RunEpisode
from ditch_drake.spec.schedule import CONTROLLER_OFFSET_S
from ditch_drake.systems.edge_angle_driver import EdgeAngleDriver
from ditch_drake.systems.expert import ExpertDriver, draw_expert_style
from ditch_drake.systems.window_route import HALF_REACH_M, WindowRouteConfig, WindowRouteDriver, WindowRoutePlanner
from ditch_drake.world.environments import get_environment
from ditch_drake.world.terrain import DitchTerrain, SlopeSection, TerrainParams, WallSlopes
from ditch_drake.world.windows import (
    course_frame,
    crossable_windows,
    has_steep_sections,
    smallest_tip_angle_deg,
    windows_by_side,
)

SEARCH_WINDOWS = {  # along-course intervals (m) of the right and the left wall's windows
    "wide_search": {"right": [(5.0, 25.0)], "left": [(5.0, 25.0)]},
    "wide_search_offset": {"right": [(5.0, 25.0)], "left": [(35.0, 55.0)]},
}


def _terrain(name: str) -> DitchTerrain:
    return DitchTerrain(get_environment(name).terrain)


@pytest.mark.parametrize("name", sorted(SEARCH_WINDOWS))
def test_the_search_ditches_windows(name):
    terrain = _terrain(name)
    assert has_steep_sections(terrain)
    found = windows_by_side(terrain)
    for side, expected in SEARCH_WINDOWS[name].items():
        assert [(w.from_m, w.to_m) for w in found[side]] == expected
        for window in found[side]:
            assert window.slope_deg == 50.0
            assert window.first_section == window.last_section == 1
            # At the 50 deg hinge line, on the wall's own side, across from the window's ends.
            hinge = float(terrain.hinge_distance_at(np.array([window.from_xy]))[0])
            assert window.hinge_distance_m == pytest.approx(hinge)
            sign = 1.0 if side == "left" else -1.0
            np.testing.assert_allclose(window.from_xy, [window.from_m - 30.0, sign * hinge])
            np.testing.assert_allclose(window.to_xy, [window.to_m - 30.0, sign * hinge])


def test_adjacent_gentle_sections_merge_into_one_window():
    sections = [SlopeSection(0.0, 4.0, 70.0), SlopeSection(4.0, 6.0, 50.0), SlopeSection(6.0, 9.0, 40.0),
                SlopeSection(9.0, 12.0, 75.0), SlopeSection(12.0, 14.0, 55.0), SlopeSection(14.0, 20.0, 70.0)]
    terrain = DitchTerrain(TerrainParams(length_m=20.0, bottom_width_m=6.0, wall_slopes=WallSlopes(right=sections)))
    right = crossable_windows(terrain, "right")
    assert [(w.from_m, w.to_m, w.first_section, w.last_section, w.slope_deg) for w in right] == [
        (4.0, 9.0, 1, 2, 50.0), (12.0, 14.0, 4, 4, 55.0)]
    # The merged window begins to drop where its gentlest section does.
    assert right[0].hinge_distance_m == pytest.approx(
        float(terrain.hinge_distance_at(np.array([[7.5 - 10.0, -8.0]]))[0]))
    assert [(w.from_m, w.to_m) for w in crossable_windows(terrain, "right", max_slope_deg=52.0)] == [(4.0, 9.0)]
    assert [(w.from_m, w.to_m) for w in crossable_windows(terrain, "left")] == [(0.0, 20.0)]  # 55 deg all along
    assert has_steep_sections(terrain)
    assert not has_steep_sections(terrain, max_slope_deg=80.0)


def test_plain_and_gentle_terrains_have_no_steep_sections():
    for name in ("wide", "narrow", "sine", "crater"):
        assert not has_steep_sections(_terrain(name))
    gentle = WallSlopes(right=[SlopeSection(0.0, 15.0, 45.0), SlopeSection(15.0, 30.0, 55.0)])
    assert not has_steep_sections(DitchTerrain(TerrainParams(bottom_width_m=6.0, wall_slopes=gentle)))
    assert smallest_tip_angle_deg() < 70.0


@pytest.mark.parametrize("name", sorted(SEARCH_WINDOWS))
@pytest.mark.parametrize("seed", [0, 1, 2, 7])
def test_the_planned_route_enters_and_leaves_inside_the_windows(name, seed):
    environment = get_environment(name)
    terrain = DitchTerrain(environment.terrain)
    driver = draw_expert_style(seed).driver
    for task in environment.tasks:
        planner = WindowRoutePlanner(terrain, task.goal, driver)
        route = planner.plan(task.start[:2], driver.wall_angle_deg, driver.climb_angle_deg, driver.approach_margin_m)
        assert route is not None
        assert route.entry.side == "right" and route.exit.side == "left"
        margin = HALF_REACH_M + WindowRouteConfig().window_margin_m
        for along in (route.descend_hinge_m, route.descend_toe_m):
            assert route.entry.holds(along, margin)
        for along in (route.climb_toe_m, route.climb_hinge_m):
            assert route.exit.holds(along, margin)
        # 20 m windows leave room for the style's own angles.
        assert route.descend_angle_deg == driver.wall_angle_deg
        assert route.climb_angle_deg == driver.climb_angle_deg
        # The descent at the wall angle spans the wall from the hinge line to the toe.
        wall_along = (route.entry.hinge_distance_m - terrain.toe_distance_m) / math.tan(
            math.radians(driver.wall_angle_deg))
        assert abs(route.descend_toe_m - route.descend_hinge_m) == pytest.approx(wall_along)
        # Its approach point lies on the flat beyond the approach zone's edge.
        along, offset = course_frame(terrain).along_and_offset(route.approach_xy)
        assert -offset == pytest.approx(terrain.hinge_distance_m + driver.approach_margin_m)


def _narrow_window_terrain(width_m: float) -> DitchTerrain:
    right = [SlopeSection(0.0, 20.0, 72.0), SlopeSection(20.0, 20.0 + width_m, 50.0),
             SlopeSection(20.0 + width_m, 60.0, 72.0)]
    left = [SlopeSection(0.0, 10.0, 72.0), SlopeSection(10.0, 40.0, 50.0), SlopeSection(40.0, 60.0, 72.0)]
    return DitchTerrain(TerrainParams(length_m=60.0, bottom_width_m=6.0, depth_m=4.0,
                                      wall_slopes=WallSlopes(right=right, left=left)))


@pytest.mark.parametrize("width_m", [8.0, 9.0, 10.0])
def test_runs_are_steepened_in_narrow_windows_only(width_m):
    terrain = _narrow_window_terrain(width_m)
    driver = draw_expert_style(0).driver
    planner = WindowRoutePlanner(terrain, [0.0, 12.0], driver)
    config = planner.config
    (narrow,), (wide,) = planner.windows["right"], planner.windows["left"]
    assert planner.run_angle_deg(wide, driver.wall_angle_deg) == driver.wall_angle_deg
    angle = planner.run_angle_deg(narrow, driver.wall_angle_deg)
    drop = narrow.hinge_distance_m - terrain.toe_distance_m
    style_along = drop / math.tan(math.radians(driver.wall_angle_deg))
    room = narrow.width_m - 2.0 * planner.margin_m - config.narrow_room_m
    assert style_along > room  # the style's descent would not fit
    assert driver.wall_angle_deg < angle <= config.steepest_run_deg
    # Steepened until it fits, unless that would take more than the steepest run.
    assert drop / math.tan(math.radians(angle)) == pytest.approx(room) or angle == config.steepest_run_deg
    route = planner.plan([-5.0, -12.0], driver.wall_angle_deg, driver.climb_angle_deg, driver.approach_margin_m)
    assert route.entry == narrow and route.descend_angle_deg == angle
    assert abs(route.descend_toe_m - route.descend_hinge_m) == pytest.approx(drop / math.tan(math.radians(angle)))


def test_the_climb_steers_back_onto_its_planned_exit():
    environment = get_environment("wide_search")
    terrain = DitchTerrain(environment.terrain)
    style = draw_expert_style(0).driver
    task = environment.tasks[0]
    driver = WindowRouteDriver(terrain, task.goal, 0, style)
    planner = WindowRoutePlanner(terrain, task.goal, style)
    route = planner.plan(task.start[:2], style.wall_angle_deg, style.climb_angle_deg, style.approach_margin_m)
    frame = course_frame(terrain)
    far = frame.side_sign(route.exit.side)

    def angle_to_edge(xy):
        heading = driver._climb_heading(np.asarray(xy), route)
        forward = np.array([math.cos(heading), math.sin(heading)])
        return math.degrees(math.atan2(float(forward @ (far * frame.left)),
                                       float(forward @ (route.climb_sign * frame.tangent))))

    middle = (terrain.toe_distance_m + route.exit.hinge_distance_m) / 2
    on_line = route.climb_hinge_m - route.climb_sign * (route.exit.hinge_distance_m - middle) / math.tan(
        math.radians(route.climb_angle_deg))
    assert angle_to_edge(frame.point(on_line, far * middle)) == pytest.approx(route.climb_angle_deg)
    # Slipped along the wall, past the line: steeper, toward the planned exit, within the correction.
    steeper = angle_to_edge(frame.point(on_line + route.climb_sign * 1.0, far * middle))
    assert route.climb_angle_deg < steeper <= route.climb_angle_deg + planner.config.climb_correction_deg
    assert angle_to_edge(frame.point(on_line + route.climb_sign * 6.0, far * middle)) == pytest.approx(
        route.climb_angle_deg + planner.config.climb_correction_deg)


def test_no_route_where_the_start_and_the_goal_share_a_side():
    terrain = _terrain("wide_search")
    driver = draw_expert_style(0).driver
    planner = WindowRoutePlanner(terrain, [0.0, -11.0], driver)
    assert planner.plan([5.0, -11.0], 20.0, 35.0, 2.5) is None


def _commands(system, poses):
    """The command `system` (a driver, or the expert's diagram) outputs after one control update
    at each of `poses`."""
    commands = []
    for x, y, yaw in poses:
        context = system.CreateDefaultContext()
        X_WB = RigidTransform(RollPitchYaw(0.0, 0.0, yaw), [x, y, 0.0])
        system.GetInputPort("body_poses").FixValue(context, [X_WB])
        simulator = Simulator(system, context)
        simulator.AdvanceTo(CONTROLLER_OFFSET_S + 1e-6)
        port = system.GetOutputPort("raw_command" if isinstance(system, ExpertDriver) else "command")
        commands.append(port.Eval(simulator.get_context()).copy())
    return np.array(commands)


def test_the_expert_keeps_the_plain_driver_where_no_wall_is_too_steep():
    poses = [(0.0, -11.0, math.pi / 2), (2.0, -8.0, 2.0), (-1.0, -5.0, 1.2), (3.0, 0.5, 0.4), (0.0, 7.0, 1.0)]
    style = draw_expert_style(3)
    style.steering_noise_radps = 0.0
    style.reaction_delay_steps = 0
    for name in ("wide", "sine"):
        terrain = _terrain(name)
        goal = get_environment(name).tasks[0].goal
        expert = ExpertDriver(terrain, goal, 0, style)
        assert type(expert.GetSubsystemByName("edge_angle_driver")) is EdgeAngleDriver
        plain = EdgeAngleDriver(terrain, goal, 0, style.driver, offset_s=CONTROLLER_OFFSET_S)
        np.testing.assert_array_equal(_commands(expert, poses), _commands(plain, poses))
    search = ExpertDriver(_terrain("wide_search"), [0.0, 11.0], 0, style)
    assert type(search.GetSubsystemByName("edge_angle_driver")) is WindowRouteDriver


def test_the_expert_descends_and_climbs_through_the_windows():
    diagram, scene = MakeRolloutDiagram(RolloutConfig(SceneConfig(environment="wide_search", task=0),
                                                      ExpertConfig(style_seed=0)))
    chassis = scene.plant.GetBodyByName("chassis", scene.husky)
    frame = course_frame(scene.terrain)
    steep = []  # (tilt deg, along m, side) of every pose tilted more than 30 deg

    def watch(context):
        X_WB = scene.plant.EvalBodyPoseInWorld(scene.plant.GetMyContextFromRoot(context), chassis)
        tilt = math.degrees(math.acos(min(1.0, X_WB.rotation().matrix()[2, 2])))
        if tilt > 30.0:
            along, offset = frame.along_and_offset(X_WB.translation()[:2])
            steep.append((tilt, float(along), "left" if offset > 0 else "right"))

    outcome = RunEpisode(Simulator(diagram), diagram, scene, 0, watch=watch, watch_period_s=0.25)
    assert outcome.status == "reached_goal"
    assert outcome.peak_tilt_deg >= 15.0
    windows = windows_by_side(scene.terrain)
    assert {side for _, _, side in steep} == {"right", "left"}  # down one wall, up the other
    for tilt, along, side in steep:
        assert tilt < smallest_tip_angle_deg()
        assert any(window.holds(along) for window in windows[side])
    peak = max(steep)
    assert any(window.holds(peak[1]) for window in windows[peak[2]])
