"""`RunEpisode`, the one episode runner: its start hooks, its watch (chunked and per step),
early stops and fixed end times, on a robot standing still on flat ground."""

import numpy as np
import pytest
from pydrake.common import RandomGenerator
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator

from ditch_drake.diagrams.ditch_scene import SceneConfig, chassis_pose
from ditch_drake.diagrams.rollout import ConstantCommandConfig, MakeRolloutDiagram, RolloutConfig, RunEpisode
from ditch_drake.spec import robot
from ditch_drake.systems.episode_monitor import EpisodeConfig


@pytest.fixture(scope="module")
def still():
    """The wide scene with the robot commanded to stand still (the episode would run 3 s)."""
    config = RolloutConfig(scene=SceneConfig(environment="wide", episode=EpisodeConfig(time_limit_s=3.0)),
                           controller=ConstantCommandConfig([0.0, 0.0]))
    return MakeRolloutDiagram(config)


def test_hooks_run_in_order_around_initialize(still):
    diagram, scene = still
    calls = []

    def before_start(root_context):
        # The seeded start is drawn already: the jittered pose of seed 5.
        context = diagram.CreateDefaultContext()
        diagram.SetRandomContext(context, RandomGenerator(5))
        assert np.array_equal(chassis_pose(diagram, scene, root_context).GetAsMatrix4(),
                              chassis_pose(diagram, scene, context).GetAsMatrix4())
        calls.append(("before_start", root_context.get_time()))

    def after_start(root_context):
        calls.append(("after_start", root_context.get_time()))

    def watch(root_context):
        calls.append(("watch", root_context.get_time()))

    RunEpisode(Simulator(diagram), diagram, scene, 5, before_start=before_start, after_start=after_start, watch=watch,
               end_time_s=0.1)
    # Initialize calls the per-step watch once (at t = 0), between the two hooks.
    assert calls[:3] == [("before_start", 0.0), ("watch", 0.0), ("after_start", 0.0)]
    assert all(name == "watch" for name, _ in calls[3:])


def test_before_start_changes_the_start(still):
    """Moved onto the goal before Initialize, the robot ends the episode at once."""
    diagram, scene = still

    def onto_the_goal(root_context):
        plant = scene.plant
        plant.SetFreeBodyPose(plant.GetMyMutableContextFromRoot(root_context), plant.GetBodyByName("chassis"),
                              RigidTransform([*scene.task.goal, robot.WHEEL_RADIUS_M + 0.005]))

    outcome = RunEpisode(Simulator(diagram), diagram, scene, 0, before_start=onto_the_goal)
    assert outcome.status == "reached_goal" and outcome.time_s < 0.2
    assert RunEpisode(Simulator(diagram), diagram, scene, 0).status == "timeout"  # Without it: stands still.


def test_a_periodic_watch_sees_the_end_of_each_chunk(still):
    diagram, scene = still
    times = []
    outcome = RunEpisode(Simulator(diagram), diagram, scene, 0, watch=lambda c: times.append(c.get_time()),
                         watch_period_s=0.3, end_time_s=1.0)
    assert times == pytest.approx([0.3, 0.6, 0.9, 1.0])  # The last chunk is cut at the end time.
    assert outcome.status == "running"


def test_a_periodic_watch_stops_with_the_episode(still):
    diagram, scene = still
    times = []
    outcome = RunEpisode(Simulator(diagram), diagram, scene, 0, watch=lambda c: times.append(c.get_time()),
                         watch_period_s=0.25)
    assert outcome.status == "timeout" and outcome.time_s == pytest.approx(3.0)
    # The monitor's check at 3 s runs at the start of the chunk after it, which it ends at once:
    # the watch sees 3 s twice (the replay's last snapshot is that moment).
    assert times == pytest.approx([0.25 * k for k in range(1, 13)] + [3.0])


def test_a_step_watch_sees_every_step_and_changes_nothing(still):
    diagram, scene = still
    times = []
    watched = RunEpisode(Simulator(diagram), diagram, scene, 2, watch=lambda c: times.append(c.get_time()),
                         end_time_s=1.0)
    plain = RunEpisode(Simulator(diagram), diagram, scene, 2, end_time_s=1.0)
    assert watched == plain
    # Initialize, then every plant step (20 ms) and each control tick between.
    assert times[0] == 0.0 and times[-1] == pytest.approx(1.0)
    assert len(times) >= 1 + round(1.0 / 0.02) and np.all(np.diff(times) > 0)


@pytest.mark.parametrize("period", [None, 0.2])
def test_a_watch_returning_true_ends_the_episode_early(still, period):
    diagram, scene = still
    simulator = Simulator(diagram)
    outcome = RunEpisode(simulator, diagram, scene, 0, watch=lambda c: c.get_time() >= 0.5, watch_period_s=period)
    assert outcome.status == "running"
    assert simulator.get_context().get_time() == pytest.approx(0.6 if period else 0.5, abs=0.021)
    assert simulator.get_monitor() is None  # Cleared afterwards.


def test_end_time_replaces_the_time_limit_backstop(still):
    diagram, scene = still
    simulator = Simulator(diagram)
    assert RunEpisode(simulator, diagram, scene, 0, end_time_s=0.7).status == "running"
    assert simulator.get_context().get_time() == pytest.approx(0.7)
    # One Simulator serves the next episode from a fresh start.
    assert RunEpisode(simulator, diagram, scene, 0).status == "timeout"


def test_a_watch_period_needs_a_watch_and_a_positive_value(still):
    diagram, scene = still
    with pytest.raises(ValueError, match="watch_period_s"):
        RunEpisode(Simulator(diagram), diagram, scene, 0, watch_period_s=0.5)
    with pytest.raises(ValueError, match="watch_period_s"):
        RunEpisode(Simulator(diagram), diagram, scene, 0, watch=lambda c: None, watch_period_s=0.0)
