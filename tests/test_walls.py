"""Walled environments: fences that make every route cross the ditch, the bypass check that
proves it at load, and the walls in the plant (the robot hits them, the lidar sees them)."""

import copy
import dataclasses

import numpy as np
import pytest
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from ditch_drake.cli import main
from ditch_drake.common.errors import ConfigError, TerrainError
from ditch_drake.diagrams.ditch_scene import AddDitchScene, SceneConfig
from ditch_drake.diagrams.lidar_rig import AddLidar
from ditch_drake.diagrams.rollout import ConstantCommandConfig, MakeRolloutDiagram, RolloutConfig, RunEpisode
from ditch_drake.learning.checkpoint import environment_model
from ditch_drake.world.bypass import check_no_bypass, rasterize_field
from ditch_drake.world.environments import environment_names, get_environment, validate_environment
from ditch_drake.world.terrain import DitchTerrain, TerrainParams, Wall

WALLED = ["crater_walled", "wide_walled", "narrow_walled", "sine_walled"]


def test_every_environment_has_a_walled_variant_with_the_same_ditch_and_tasks():
    assert environment_names() == ["crater", "wide", "narrow", "sine"]
    assert environment_names(variants=True) == [*environment_names(), *WALLED, "wide_search", "wide_search_offset"]
    for name in environment_names():
        open_field, walled = get_environment(name), get_environment(f"{name}_walled")
        assert walled.based_on == name
        assert walled.terrain.walls and not open_field.terrain.walls
        assert dataclasses.replace(walled.terrain, walls=[]) == open_field.terrain
        assert walled.tasks == open_field.tasks


@pytest.mark.parametrize("name", WALLED)
def test_no_route_avoids_the_ditch_in_a_walled_environment(name):
    environment = get_environment(name)
    terrain = DitchTerrain(environment.terrain)
    grid = rasterize_field(terrain)
    for task in environment.tasks:
        check_no_bypass(terrain, task.start[:2], task.goal, grid)  # Raises on a bypass.
        start, goal = grid.cell(task.start[:2]), grid.cell(task.goal)
        # Through the ditch there is a way; round it there is none.
        assert grid.walls_only[start] == grid.walls_only[goal]
        assert grid.walls_and_slopes[start] != grid.walls_and_slopes[goal]


def _wide_walled():
    return copy.deepcopy(get_environment("wide_walled"))


def test_a_short_wall_leaves_a_bypass_and_is_refused():
    environment = _wide_walled()
    # The wall from the ditch's east end to the field's side stops 1.2 m short of the ditch.
    environment.terrain.walls[1].points[0] = [22.5, 0.0]
    with pytest.raises(ConfigError, match=r"task 'straight_across': the walls leave a bypass") as error:
        validate_environment(environment)
    x, y = (float(v) for v in str(error.value).split("passes (")[1].split(")")[0].split(", "))
    assert x > 21.3 and abs(y) < 2.0  # Round the ditch's east end (which reaches x = 21.3 m).


def test_a_gap_on_one_side_lets_the_robot_out_and_is_refused():
    environment = _wide_walled()
    # The field's south side open from x = -5 to 5 m: the start's half opens onto the field beyond.
    environment.terrain.walls[0].points = [[-5.0, -14.0], [-27.0, -14.0], [-27.0, 14.0], [27.0, 14.0],
                                           [27.0, -14.0], [5.0, -14.0]]
    with pytest.raises(ConfigError, match=r"task 'straight_across': start \[0.0, -11.0\] is outside the walls"):
        validate_environment(environment)


def test_a_wall_across_the_ditch_is_refused():
    params = dataclasses.replace(get_environment("wide").terrain,
                                 walls=[Wall(points=[[14.0, -14.0], [14.0, 14.0]])])
    with pytest.raises(TerrainError, match=r"walls\[0\] crosses the ditch: its point \(14.00, -3"):
        DitchTerrain(params)


def test_a_wall_through_a_task_is_refused():
    environment = _wide_walled()
    environment.terrain.walls[0].points = [[-27.0, -11.3], [27.0, -11.3], [27.0, 14.0], [-27.0, 14.0], [-27.0, -11.3]]
    with pytest.raises(ConfigError, match=r"task 'straight_across': start \[0.0, -11.0\] is 0.20 m from a wall"):
        validate_environment(environment)


@pytest.mark.parametrize("field, value, expected", [
    ("points", [[0.0, -14.0]], "at least two finite"),
    ("points", [[0.0, -14.0], [0.0, -14.0]], "repeats a point"),
    ("height_m", 0.0, "0 < height_m <= 10"),
    ("thickness_m", -1.0, "0 < thickness_m <= 2"),
])
def test_bad_wall_parameters_are_named(field, value, expected):
    wall = dataclasses.replace(Wall(points=[[-14.0, -14.0], [14.0, -14.0]]), **{field: value})
    with pytest.raises(TerrainError, match=rf"walls\[0\]\.{field}=.*{expected}"):
        TerrainParams(walls=[wall]).validate()


def test_a_bad_walled_environments_file_exits_2_naming_environment_and_task(tmp_path, capsys):
    path = tmp_path / "leaky.yaml"
    path.write_text(
        "environments:\n  leaky:\n    terrain:\n      course: line\n      bottom_width_m: 6.0\n"
        "      walls:\n        - points: [[10.0, -8.5], [10.0, -14.0], [-14.0, -14.0], [-14.0, -5.3]]\n"
        "        - points: [[10.0, 8.5], [10.0, 14.0], [-14.0, 14.0], [-14.0, 5.3]]\n"
        "    tasks: [{name: across, start: [0.0, -11.0, 90.0], goal: [0.0, 11.0]}]\n")
    code = main(["evaluate", "--controller", "dwa", "--environments", str(path), "--env", "leaky",
                 "--rollouts", "1", "--out", str(tmp_path / "r.jsonl")])
    assert code == 2
    error = capsys.readouterr().err
    assert "'leaky'" in error and "task 'across'" in error and "bypass" in error
    assert not (tmp_path / "r.jsonl").exists()


def test_a_walled_variant_drives_the_model_of_its_base():
    assert environment_model("wide_walled") == "wide"
    with pytest.raises(ConfigError, match="has no shipped model"):
        environment_model("no_such_place")


def test_the_lidar_sees_a_wall_and_not_in_the_open_field():
    """The robot 2 m from the south wall of wide_walled, facing it: the cloud holds points on
    the wall's face, up to its top; in the open field the same pose sees only level ground."""
    X_WB = RigidTransform(RotationMatrix.MakeZRotation(-np.pi / 2), [3.0, -11.8, 0.135])
    for name, expect_wall in (("wide_walled", True), ("wide", False)):
        builder = DiagramBuilder()
        scene = AddDitchScene(builder, SceneConfig(environment=name))
        lidar = AddLidar(builder, scene)
        diagram = builder.Build()
        context = diagram.CreateDefaultContext()
        plant = scene.plant
        plant_context = plant.GetMyMutableContextFromRoot(context)
        plant.SetFreeBodyPose(plant_context, plant.GetBodyByName("chassis", scene.husky), X_WB)
        converter_context = lidar.converter.GetMyMutableContextFromRoot(context)
        lidar.converter.ExecuteForcedEvents(converter_context)
        p_L = lidar.converter.GetOutputPort("point_cloud").Eval(converter_context).xyzs().astype(float)
        p_W = (X_WB @ lidar.X_BL).multiply(p_L)
        on_wall = (np.abs(p_W[1] + 13.9) < 0.05) & (p_W[2] > 0.3)
        if expect_wall:
            assert on_wall.sum() > 100
            assert p_W[2, on_wall].max() == pytest.approx(1.0, abs=0.1)
        else:
            assert on_wall.sum() == 0
            assert np.abs(p_W[2]).max() < 0.05


def test_the_robot_stops_at_a_wall():
    """Driven straight at the south wall from 3 m, the chassis never passes it."""
    environment = get_environment("wide_walled")
    field = copy.deepcopy(environment)
    field.tasks[0].start = [3.0, -11.0, -90.0]
    scene = SceneConfig(environment="fenced", environments={"fenced": field})
    scene.episode.time_limit_s = 8.0
    diagram, built = MakeRolloutDiagram(RolloutConfig(scene=scene, controller=ConstantCommandConfig([1.0, 0.0])))
    outcome = RunEpisode(Simulator(diagram), diagram, built, seed=0)
    wall_face_y = -14.0 + 0.1
    assert outcome.final_xy[1] > wall_face_y + 0.3  # The chassis' front half (0.5 m) stays outside the wall.
    assert outcome.final_xy[1] < -12.5  # It did drive there.
