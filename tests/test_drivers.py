"""Scripted drivers in the simulator: the rollover phenomenon with seeds (short, fast versions).

The 10-trial calibration is `ditch-drake calibrate` / `pytest -m slow`.
"""

import pytest

from ditch_drake.systems.edge_angle_driver import EdgeAngleDriverConfig
from ditch_drake.validation.calibration import driven_trials

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

    from ditch_drake.systems.edge_angle_driver import EdgeAngleDriver
    from ditch_drake.world.environments import get_environment
    from ditch_drake.world.terrain import DitchTerrain

    environment = get_environment("narrow")  # Course along x at y = 0; goal (5, 9) across.
    terrain = DitchTerrain(environment.terrain)
    return EdgeAngleDriver(terrain, np.array([5.0, 9.0]), 0, EdgeAngleDriverConfig(replan_each_step=replan)), terrain


def test_a_replanning_labeller_answers_from_the_current_pose_not_the_latched_plan():
    import math

    import numpy as np

    from ditch_drake.spec.planar import wrap_to_pi
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


def test_a_driver_keeping_the_facing_side_takes_over_a_robot_on_its_own_side_of_square():
    import math

    import numpy as np

    from ditch_drake.systems.edge_angle_driver import DESCEND, EdgeAngleDriver
    from ditch_drake.world.environments import get_environment
    from ditch_drake.world.terrain import DitchTerrain

    terrain = DitchTerrain(get_environment("narrow").terrain)  # Course along x at y = 0; goal (5, 9) across.
    def driver(keep):
        return EdgeAngleDriver(terrain, np.array([5.0, 9.0]), 0, EdgeAngleDriverConfig(keep_facing_side=keep))

    in_approach_zone = np.array([0.0, -(terrain.hinge_distance_m + 1.0)])
    facing_north_west = math.radians(120)  # Toward the ditch, 30 deg off square to the west (-x).
    heading, sign, _ = driver(False).desired_heading(in_approach_zone, 1.0, DESCEND, heading=facing_north_west)
    assert sign == 1.0 and math.cos(heading) > 0  # The latched east side: a turn through head-on.
    heading, sign, phase = driver(True).desired_heading(in_approach_zone, 1.0, DESCEND, heading=facing_north_west)
    assert (sign, phase) == (-1.0, DESCEND)
    assert math.cos(heading) < 0 and math.sin(heading) > 0  # West and toward the ditch.
    assert abs(heading - facing_north_west) < math.radians(45)
    # Within 15 deg of square on it faces neither side: the side chosen so far, else the convention (east).
    nearly_square = math.radians(100)
    assert driver(True).desired_heading(in_approach_zone, -1.0, DESCEND, heading=nearly_square)[1] == -1.0
    assert driver(True).desired_heading(in_approach_zone, 0.0, DESCEND, heading=nearly_square)[1] == 1.0
    # On the wall the side stays latched, as without the option.
    on_near_wall = np.array([0.0, -0.5 * (terrain.toe_distance_m + terrain.hinge_distance_m)])
    assert driver(True).desired_heading(on_near_wall, 1.0, DESCEND, heading=facing_north_west)[1] == 1.0
    # Before the approach zone it heads for the goal and chooses nothing.
    on_the_flat = np.array([0.0, -(terrain.hinge_distance_m + 4.0)])
    assert driver(True).desired_heading(on_the_flat, 0.0, DESCEND, heading=facing_north_west)[1] == 0.0
    # The expert's drawn style carries the option into a built driver's context (`set_style`).
    from ditch_drake.systems.expert import ExpertVariation, draw_expert_style

    style = draw_expert_style(3, ExpertVariation(keep_facing_side=True)).driver
    built = driver(False)
    context = built.CreateDefaultContext()
    built.set_style(context, style)
    assert style.keep_facing_side and context.get_numeric_parameter(0).get_value()[5] == 1.0


def test_the_replanning_driver_itself_gets_through():
    (record,) = driven_trials("narrow", 1, EdgeAngleDriverConfig(replan_each_step=True), seeds=[5], time_step_s=0.02)
    assert record["status"] == "reached_goal"


def test_lead_in_heads_away_along_the_rim_only_when_the_ditch_is_too_short_ahead():
    import math

    import numpy as np

    from ditch_drake.systems.edge_angle_driver import DESCEND, EdgeAngleDriver
    from ditch_drake.world.environments import get_environment
    from ditch_drake.world.terrain import DitchTerrain

    terrain = DitchTerrain(get_environment("narrow").terrain)  # Course from x = -15 to 15 at y = 0.
    def heading(goal, lead_in, start=(0.0, -9.0)):
        driver = EdgeAngleDriver(terrain, np.array(goal), 0, EdgeAngleDriverConfig(lead_in=lead_in))
        return driver.desired_heading(np.array(start), 0.0, DESCEND, heading=math.pi / 2)[0], driver

    # Straight across from the middle: the convention goes east (+x), where 15 m of ditch is left.
    plain, driver = heading((0.0, 9.0), False)
    assert abs(plain - math.pi / 2) < 1e-9  # Straight at the goal.
    needed = driver.crossing_length_m(20.0, 35.0, 2.5)
    assert needed > terrain.course_left_ahead([0.0, -9.0], [1.0, 0.0]) == 15.0
    led, _ = heading((0.0, 9.0), True)
    assert math.cos(led) < -0.5  # West along the rim first, to make room.
    # From x = -5, 20 m are left: room enough, no lead-in.
    assert abs(heading((5.0, 9.0), True, start=(-5.0, -9.0))[0] - heading((5.0, 9.0), False, start=(-5.0, -9.0))[0]) < 1e-9
    # Shallower angles travel farther along the ditch.
    assert driver.crossing_length_m(17.0, 32.0, 2.5) > needed > driver.crossing_length_m(23.0, 38.0, 2.5)
    # The expert's drawn style carries the choice into a built driver's context (`set_style`).
    from ditch_drake.systems.expert import ExpertVariation, draw_expert_style

    style = draw_expert_style(3, ExpertVariation(lead_in=True)).driver
    context = driver.CreateDefaultContext()
    driver.set_style(context, style)
    assert style.lead_in and context.get_numeric_parameter(0).get_value()[4] == 1.0


def test_course_left_ahead_counts_to_the_end_it_points_at():
    import math

    from ditch_drake.world.environments import get_environment
    from ditch_drake.world.terrain import DitchTerrain

    line = DitchTerrain(get_environment("narrow").terrain)
    assert line.course_left_ahead([-5.0, -9.0], [1.0, 0.0]) == 20.0
    assert line.course_left_ahead([-5.0, -9.0], [-1.0, 0.2]) == 10.0
    assert line.course_left_ahead([40.0, 3.0], [1.0, 0.0]) == 0.0
    sine = DitchTerrain(get_environment("sine").terrain)
    ahead, behind = sine.course_left_ahead([0.0, -9.0], [1.0, 0.0]), sine.course_left_ahead([0.0, -9.0], [-1.0, 0.0])
    assert ahead + behind > 30.0  # The sine is longer than its 30 m span.
    assert DitchTerrain(get_environment("crater").terrain).course_left_ahead([0.0, -12.0], [1.0, 0.0]) == math.inf


def test_with_lead_in_the_straight_across_crossing_stays_out_of_the_ditch_end():
    """Without it the narrow crossing from the middle runs into the ditch's rounded end
    (x = 15 m) before it turns up; with it the expert starts farther west and stays clear."""
    from pydrake.common import RandomGenerator
    from pydrake.systems.analysis import Simulator

    from ditch_drake.diagrams.ditch_scene import SceneConfig
    from ditch_drake.diagrams.rollout import MakeRolloutDiagram, RolloutConfig

    farthest_east = {}
    for lead_in in (False, True):
        scene_config = SceneConfig(environment="narrow", task=0)
        scene_config.plant.time_step = 0.02
        diagram, scene = MakeRolloutDiagram(RolloutConfig(
            scene=scene_config, controller=EdgeAngleDriverConfig(lead_in=lead_in)))
        simulator = Simulator(diagram)
        context = simulator.get_mutable_context()
        diagram.SetRandomContext(context, RandomGenerator(5))
        simulator.Initialize()
        chassis = scene.plant.GetBodyByName("chassis", scene.husky)
        plant_context = scene.plant.GetMyContextFromRoot(context)
        monitor_context = scene.monitor.GetMyContextFromRoot(context)
        xs = []
        while scene.monitor.outcome(monitor_context).status == "running":
            simulator.AdvanceTo(context.get_time() + 0.5)
            xs.append(scene.plant.EvalBodyPoseInWorld(plant_context, chassis).translation()[0])
        assert scene.monitor.outcome(monitor_context).status == "reached_goal"
        farthest_east[lead_in] = max(xs)
    assert farthest_east[False] > 14.0
    assert farthest_east[True] < 12.0


def test_oracle_crossing_side_follows_the_goal_until_the_approach_zone_and_holds_its_side_there():
    import numpy as np
    from pydrake.math import RigidTransform
    from pydrake.systems.analysis import Simulator

    from ditch_drake.systems.oracle_crossing_side import OracleCrossingSide
    from ditch_drake.world.crossing import crossing_sides
    from ditch_drake.world.environments import get_environment
    from ditch_drake.world.terrain import DitchTerrain

    terrain = DitchTerrain(get_environment("wide").terrain)
    goal = np.array([-8.0, 11.0])
    side = OracleCrossingSide(terrain, goal, chassis_body_index=0)
    simulator = Simulator(side)
    context = simulator.get_mutable_context()
    path = [[0.0, -11.0], [0.0, -8.0], [-12.0, -8.0]]  # As in tests/test_terrain.py.
    outputs = []
    for xy in path:
        side.GetInputPort("body_poses").FixValue(context, [RigidTransform([*xy, 0.0])])
        outputs.append(side.GetOutputPort("crossing_side").Eval(context)[0])
        simulator.AdvanceTo(context.get_time() + 0.1)
    assert outputs == crossing_sides(terrain, np.array(path), goal, 2.5, 15.0).tolist() == [-1.0, -1.0, -1.0]
    # Away from the ditch again, it keeps the side it committed to.
    side.GetInputPort("body_poses").FixValue(context, [RigidTransform([-12.0, -20.0, 0.0])])
    assert side.GetOutputPort("crossing_side").Eval(context)[0] == -1.0
    fresh = side.CreateDefaultContext()
    side.GetInputPort("body_poses").FixValue(fresh, [RigidTransform([-12.0, -20.0, 0.0])])
    assert side.GetOutputPort("crossing_side").Eval(fresh)[0] == 1.0


@pytest.mark.parametrize("source, side_at_start", [("perceived", 0.0), ("oracle", 1.0)])
def test_a_canonical_side_clone_is_told_the_side_in_its_rollout_diagram(tmp_path, source, side_at_start):
    import torch
    from pydrake.systems.analysis import Simulator

    from ditch_drake.diagrams.ditch_scene import SceneConfig
    from ditch_drake.diagrams.rollout import LearnedPolicyConfig, MakeRolloutDiagram, RolloutConfig
    from ditch_drake.learning.checkpoint import make_checkpoint, save_checkpoint
    from ditch_drake.learning.config import ModelConfig
    from ditch_drake.learning.model import FourInputClassifier

    torch.manual_seed(0)
    path = save_checkpoint(make_checkpoint(FourInputClassifier(ModelConfig(canonical_side=True))), tmp_path / "c.pt")
    diagram, _ = MakeRolloutDiagram(RolloutConfig(
        scene=SceneConfig(environment="wide", task=0),
        controller=LearnedPolicyConfig(checkpoint=str(path), crossing_side=source)))
    side = diagram.GetSubsystemByName(f"{source}_crossing_side")
    simulator = Simulator(diagram)
    simulator.AdvanceTo(0.25)
    # Task 0 runs square across: right, by the expert's convention, for the oracle; the edge is
    # beyond the lidar's range at the start, so the perceived side is none yet.
    assert side.GetOutputPort("crossing_side").Eval(
        side.GetMyContextFromRoot(simulator.get_context()))[0] == side_at_start
    assert diagram.GetSubsystemByName("learned_policy").HasInputPort("crossing_side")
    # Only the perceived side is measured against the oracle's.
    assert diagram.HasSubsystemNamed("crossing_side_agreement") == (source == "perceived")
