"""Diagram-level tests of the scene: it builds, drives, rests on the terrain, and ends episodes."""

import math

import numpy as np
import pytest
from pydrake.common import RandomGenerator
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.analysis import Simulator

from ditch_drake.diagrams.ditch_scene import MakeDitchDiagram, SceneConfig, chassis_pose
from ditch_drake.diagrams.rollout import ConstantCommandConfig, MakeRolloutDiagram, RolloutConfig, RunEpisode
from ditch_drake.spec import robot
from ditch_drake.systems.episode_monitor import EpisodeConfig, stability_margins_rad
from ditch_drake.world.environments import ConfigError

ENVIRONMENTS = ["crater", "wide", "narrow", "sine"]


@pytest.mark.parametrize("name", ENVIRONMENTS)
def test_diagram_builds_with_named_ports(name):
    diagram, _ = MakeDitchDiagram(SceneConfig(environment=name))
    assert diagram.HasInputPort("command")
    for port in ("husky_state", "body_poses", "episode_state", "query_object"):
        assert diagram.HasOutputPort(port)
    assert diagram.GetInputPort("command").size() == 2


def test_flat_ground_drive_moves_forward(wide_diagram):
    diagram, scene = wide_diagram
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    diagram.GetInputPort("command").FixValue(context, [1.0, 0.0])
    start = chassis_pose(diagram, scene, context)
    simulator.AdvanceTo(2.0)
    end = chassis_pose(diagram, scene, context)
    forward = start.rotation().matrix()[:, 0]
    travelled = (end.translation() - start.translation()) @ forward
    assert 1.5 < travelled < 2.1
    assert abs(end.translation()[2] - start.translation()[2]) < 0.02


def test_positive_angular_rate_turns_left(wide_diagram):
    diagram, scene = wide_diagram
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    diagram.GetInputPort("command").FixValue(context, [1.0, 0.45])
    simulator.AdvanceTo(2.0)
    chassis = scene.plant.GetBodyByName("chassis", scene.husky)
    V = scene.plant.EvalBodySpatialVelocityInWorld(scene.plant.GetMyContextFromRoot(context), chassis)
    assert V.rotational()[2] == pytest.approx(0.45, rel=0.1)


@pytest.mark.parametrize("name", ["crater", "sine"])
def test_dropped_robot_rests_on_the_ditch_bottom(name):
    """The terrain is not a convex hull: a robot dropped over the ditch lands at the bottom."""
    diagram, scene = MakeDitchDiagram(SceneConfig(environment=name, episode=EpisodeConfig(stuck_window_s=100)))
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    diagram.GetInputPort("command").FixValue(context, [0.0, 0.0])
    bottom = scene.terrain.course_xy[len(scene.terrain.course_xy) // 2]
    plant_context = scene.plant.GetMyContextFromRoot(context)
    scene.plant.SetFreeBodyPose(plant_context, scene.plant.GetBodyByName("chassis", scene.husky),
                                RigidTransform(RotationMatrix.MakeZRotation(0.3), [*bottom, -scene.terrain.params.depth_m + 0.5]))
    simulator.AdvanceTo(3.0)
    z = chassis_pose(diagram, scene, context).translation()[2]
    expected = -scene.terrain.params.depth_m + robot.WHEEL_RADIUS_M
    assert z == pytest.approx(expected, abs=0.03)


def test_forced_rollover_is_detected(wide_diagram):
    diagram, scene = wide_diagram
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    diagram.GetInputPort("command").FixValue(context, [0.0, 0.0])
    plant_context = scene.plant.GetMyContextFromRoot(context)
    upside_down = RigidTransform(RotationMatrix.MakeXRotation(math.pi), [0.0, -11.0, 0.6])
    scene.plant.SetFreeBodyPose(plant_context, scene.plant.GetBodyByName("chassis", scene.husky), upside_down)
    status = simulator.AdvanceTo(5.0)
    outcome = scene.monitor.outcome(scene.monitor.GetMyContextFromRoot(context))
    assert outcome.status == "rolled_over"
    assert outcome.peak_tilt_deg > 170
    assert outcome.min_stability_margin_deg < 0
    assert context.get_time() < 1.0  # The monitor stopped the simulator.
    assert "rolled_over" in status.FormatMessage()


def test_goal_timeout_and_stuck_outcomes():
    config = RolloutConfig(scene=SceneConfig(environment="wide", episode=EpisodeConfig(time_limit_s=2.0)),
                           controller=ConstantCommandConfig([1.0, 0.0]))
    diagram, scene = MakeRolloutDiagram(config)
    assert RunEpisode(Simulator(diagram), diagram, scene, seed=0).status == "timeout"
    config.scene.episode = EpisodeConfig(stuck_window_s=1.0)
    config.controller = ConstantCommandConfig([0.0, 0.0])
    diagram, scene = MakeRolloutDiagram(config)
    outcome = RunEpisode(Simulator(diagram), diagram, scene, seed=0)
    assert outcome.status == "stuck" and outcome.time_s == pytest.approx(1.0, abs=0.11)
    config.scene.episode = EpisodeConfig(goal_radius_m=30.0)
    diagram, scene = MakeRolloutDiagram(config)
    assert RunEpisode(Simulator(diagram), diagram, scene, seed=0).status == "reached_goal"


def test_seeded_start_jitter_is_reproducible(wide_diagram):
    diagram, scene = wide_diagram
    poses = []
    for seed in (3, 3, 4):
        context = diagram.CreateDefaultContext()
        diagram.SetRandomContext(context, RandomGenerator(seed))
        poses.append(chassis_pose(diagram, scene, context))
    assert np.allclose(poses[0].GetAsMatrix4(), poses[1].GetAsMatrix4())
    assert not np.allclose(poses[0].GetAsMatrix4(), poses[2].GetAsMatrix4())
    offset = poses[2].translation()[:2] - np.array(scene.task.start[:2])
    assert np.all(np.abs(offset) <= 0.25)


def test_stability_margins_upright_and_tipped():
    upright = stability_margins_rad(np.eye(3))
    assert math.degrees(min(upright)) == pytest.approx(math.degrees(math.atan2(0.256, 0.15)), abs=0.1)
    rolled = stability_margins_rad(RotationMatrix.MakeXRotation(math.radians(70)).matrix())
    assert min(rolled) < 0


def test_bad_scene_config_errors():
    with pytest.raises(ConfigError, match="unknown environment 'moat'"):
        MakeDitchDiagram(SceneConfig(environment="moat"))
    with pytest.raises(ConfigError, match="task index 5"):
        MakeDitchDiagram(SceneConfig(task=5))
    bad = SceneConfig()
    bad.plant.time_step = 0.0
    with pytest.raises(ConfigError, match="time_step=0.0 must be > 0"):
        MakeDitchDiagram(bad)


def test_bad_sdf_is_reported_with_file_and_line(tmp_path):
    from pydrake.multibody.plant import MultibodyPlant

    from ditch_drake.diagrams.ditch_scene import load_model_file

    broken = tmp_path / "broken.sdf"
    broken.write_text("<sdf version='1.9'><model name='x'><link name='a'></model></sdf>\n")
    with pytest.raises(ConfigError, match=r"broken.sdf"):
        load_model_file(MultibodyPlant(0.01), broken)


def test_same_seed_same_rollout():
    config = RolloutConfig(scene=SceneConfig(environment="narrow", episode=EpisodeConfig(time_limit_s=6.0)))
    outcomes = []
    for _ in range(2):
        diagram, scene = MakeRolloutDiagram(config)
        outcomes.append(RunEpisode(Simulator(diagram), diagram, scene, seed=11))
    assert outcomes[0] == outcomes[1]
