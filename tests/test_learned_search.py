"""The window search for the learned policy: its config, the blocks it adds (an elevation map fused
from the policy's lidar, the search, the side toward its target) and the goal sensor reading the
search's target."""

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.perception import BaseField, Fields, PointCloud
from pydrake.systems.analysis import Simulator

from ditch_drake.common.config_yaml import config_digest, config_to_yaml
from ditch_drake.common.errors import ConfigError
from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.diagrams.rollout import (
    LearnedPolicyConfig,
    LearnedWindowSearchConfig,
    MakeRolloutDiagram,
    RolloutConfig,
)
from ditch_drake.diagrams.scenario import load_scenario
from ditch_drake.systems.elevation_mapper import ElevationMapper
from ditch_drake.systems.goal import distance_bearing
from ditch_drake.systems.mppi_controller import MppiController
from ditch_drake.systems.target_crossing_side import TargetCrossingSide

# `LearnedPolicyConfig(checkpoint="generalist")`'s digest in the records of its rollouts made
# before the search existed: part of every such record's key.
GENERALIST_DIGEST = "8c196e7faf6ab478"


def test_a_config_without_search_keeps_its_text_and_digest():
    config = LearnedPolicyConfig(checkpoint="generalist")
    assert "search" not in config_to_yaml(config)
    assert config_digest(config) == GENERALIST_DIGEST


def test_a_search_is_written_and_takes_the_learned_defaults():
    scenario = load_scenario(override="{controller: !LearnedPolicyConfig {checkpoint: generalist, search: {}}}")
    assert isinstance(scenario.controller.search, LearnedWindowSearchConfig)
    assert scenario.controller.search.edge_standoff_m == 2.5
    assert "edge_standoff_m: 2.5" in config_to_yaml(scenario.controller)
    assert config_digest(scenario.controller) != GENERALIST_DIGEST
    with pytest.raises(ConfigError, match="crossing_side='oracle' with a search"):
        LearnedPolicyConfig(crossing_side="oracle", search=LearnedWindowSearchConfig()).validate()
    with pytest.raises(ConfigError, match="lookahead_m"):
        LearnedPolicyConfig(search=LearnedWindowSearchConfig(lookahead_m=-1.0)).validate()


def _diagram(search):
    config = RolloutConfig(scene=SceneConfig(environment="wide_search", task=0),
                           controller=LearnedPolicyConfig(checkpoint="generalist", search=search))
    return MakeRolloutDiagram(config)


def test_without_search_the_goal_sensor_reads_the_goal():
    diagram, _ = _diagram(None)
    for name in ("window_search", "elevation_mapper", "target_crossing_side"):
        assert not diagram.HasSubsystemNamed(name)
    assert not diagram.GetSubsystemByName("goal_sensor").HasInputPort("goal_xy")


def test_with_search_the_policy_reads_the_searchs_target():
    diagram, scene = _diagram(LearnedWindowSearchConfig())
    for name in ("window_search", "elevation_mapper", "target_crossing_side", "perceived_crossing_side"):
        assert diagram.HasSubsystemNamed(name)
    context = diagram.CreateDefaultContext()
    search = diagram.GetSubsystemByName("window_search")
    goal = diagram.GetSubsystemByName("goal_sensor")
    # The search's target is its first discrete state; put it somewhere other than the goal.
    target = np.array([-12.0, -7.5])
    search.GetMyMutableContextFromRoot(context).SetDiscreteState(0, target)
    X_WB = scene.plant.EvalBodyPoseInWorld(scene.plant.GetMyContextFromRoot(context),
                                           scene.plant.GetBodyByName("chassis", scene.husky))
    reading = goal.GetOutputPort("distance_bearing").Eval(goal.GetMyContextFromRoot(context))
    np.testing.assert_allclose(reading, distance_bearing(X_WB, target), atol=1e-12)
    assert not np.allclose(reading, distance_bearing(X_WB, scene.task.goal))
    # The side the policy is told comes from the block that reads the target.
    policy_side = diagram.GetSubsystemByName("learned_policy").GetInputPort("crossing_side")
    side = diagram.GetSubsystemByName("target_crossing_side").GetOutputPort("crossing_side")
    assert policy_side.Eval(diagram.GetSubsystemByName("learned_policy").GetMyContextFromRoot(context)) == \
        side.Eval(diagram.GetSubsystemByName("target_crossing_side").GetMyContextFromRoot(context))


@pytest.mark.parametrize("target_x, side", [(5.0, 1.0), (-5.0, -1.0), (0.1, 1.0)])
def test_the_side_is_the_rules_toward_the_target(target_x, side):
    block = TargetCrossingSide(0, straight_across_deg=15.0)
    context = block.CreateDefaultContext()
    # The ditch lies at +y: away from it is -y; facing it, right is +x.
    block.GetInputPort("edge").FixValue(context, [1.0, 2.0, 0.0, -1.0])
    block.GetInputPort("target_xy").FixValue(context, [target_x, 4.0])
    block.GetInputPort("body_poses").FixValue(context, [RigidTransform()])
    assert block.GetOutputPort("crossing_side").Eval(context)[0] == side
    block.GetInputPort("edge").FixValue(context, [0.0, np.nan, np.nan, np.nan])
    assert block.GetOutputPort("crossing_side").Eval(context)[0] == 0.0


def test_the_mapper_fuses_a_cloud_as_the_mppi_does():
    X_BL = RigidTransform(RollPitchYaw(0.0, 0.5, 0.0), [0.3, 0.0, 0.4])
    X_WB = RigidTransform(RollPitchYaw(0.0, 0.0, 0.3), [1.0, -2.0, 0.2])
    rng = np.random.default_rng(0)
    cloud = PointCloud(200, Fields(BaseField.kXYZs))
    cloud.mutable_xyzs()[:] = rng.uniform([0.5, -2.0, -1.0], [4.0, 2.0, 0.5], (200, 3)).T
    maps = []
    for system in (ElevationMapper(0, X_BL), MppiController([10.0, 0.0], 0, X_BL)):
        context = system.CreateDefaultContext()
        system.GetInputPort("point_cloud").FixValue(context, cloud)
        system.GetInputPort("body_poses").FixValue(context, [X_WB])
        simulator = Simulator(system, context)
        simulator.AdvanceTo(0.15)  # Two updates: the second rolls the window.
        maps.append(system.GetOutputPort("elevation_map").Eval(context))
    assert np.isfinite(maps[0]).sum() > 100
    np.testing.assert_array_equal(maps[0], maps[1])


def test_the_benchmark_takes_a_controller_override():
    from ditch_drake.benchmark.run import overridden_controller

    config = overridden_controller("learned", "generalist", "{controller: !LearnedPolicyConfig {search: {}}}")
    assert config.checkpoint == "generalist"
    assert isinstance(config.search, LearnedWindowSearchConfig)
    with pytest.raises(ConfigError):
        overridden_controller("learned", "generalist", "{controller: !LearnedPolicyConfig {search: {bin_m: -1}}}")
