"""The Gymnasium environment: Gymnasium's checker, equivalence with `ditch-drake evaluate`, vector envs, bad input."""

import functools
import subprocess
import sys

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import ditch_drake.gym  # noqa: F401  (registers DitchDrake-v0)
from ditch_drake.common.errors import ConfigError
from ditch_drake.diagrams.scenario import Scenario
from ditch_drake.evaluation.batch import make_specs
from ditch_drake.evaluation.rollout_worker import run_rollout
from ditch_drake.gym.env import DitchDrakeEnv, RewardConfig
from ditch_drake.learning.checkpoint import load_checkpoint, resolve_checkpoint_path
from ditch_drake.spec import actions
from ditch_drake.spec.observation_layout import IMAGE_STACK_SIZE
from ditch_drake.systems.action_label_input import NO_ACTION, ActionLabelInput
from ditch_drake.systems.observation_dict import ObservationDict
from ditch_drake.systems.policy import LearnedPolicy


@pytest.fixture(scope="module")
def wide_env():
    env = gymnasium.make("DitchDrake-v0", env="wide", task=1)
    yield env
    env.close()


def test_gymnasium_checker_passes(wide_env):
    check_env(wide_env.unwrapped, skip_render_check=True)


def test_reset_with_a_seed_repeats_the_observation_and_seeds_differ(wide_env):
    first, info = wide_env.reset(seed=7)
    again, _ = wide_env.reset(seed=7)
    other, _ = wide_env.reset(seed=8)
    assert info["seed"] == 7
    for key in first:
        np.testing.assert_array_equal(first[key], again[key])
    assert not np.array_equal(first["distance"], other["distance"])  # The start pose is jittered by the seed.
    assert wide_env.observation_space.contains(first)


def test_the_shipped_policy_stepping_the_environment_drives_the_evaluated_rollout(wide_env):
    """Same task and seed as `ditch-drake evaluate --controller learned --checkpoint wide --env wide --task 1
    --seed 1 --rollouts 1`: same outcome, time and path length to the last digit."""
    [spec] = make_specs("learned", "wide", "wide", tasks=[1], rollouts=1, seed=1)
    record = run_rollout(spec)
    policy = LearnedPolicy(load_checkpoint(resolve_checkpoint_path("wide")))
    observation, _ = wide_env.reset(seed=1)
    start_distance = float(observation["distance"][0])
    total, steps = 0.0, 0
    while True:
        label, _ = policy.infer(observation["image"], observation["imu"], observation["distance"],
                                observation["bearing"])
        observation, reward, terminated, truncated, info = wide_env.step(label)
        total, steps = total + reward, steps + 1
        if terminated or truncated:
            break
    assert record.status == "reached_goal"
    assert terminated and not truncated
    for field in ("status", "success", "time_s", "path_length_m", "peak_tilt_deg", "min_stability_margin_deg",
                  "final_x_m", "final_y_m", "failure_region", "halts_by_region"):
        assert info[field] == getattr(record, field), field
    # The progress rewards add up to the distance covered toward the goal, plus the bonus.
    final_distance = np.hypot(*(np.array([info["final_x_m"], info["final_y_m"]]) - wide_env.unwrapped.scene.task.goal))
    assert total == pytest.approx(RewardConfig().goal_bonus + start_distance - final_distance, abs=0.05)
    assert steps == pytest.approx(record.time_s / 0.1, abs=1)


def test_the_side_told_generalist_stepping_the_environment_drives_the_evaluated_rollout():
    """`narrow`'s task 2 crosses turned left: the shipped generalist, told `info["crossing_side"]`
    (perceived from the lidar, as in a rollout), drives the rollout of `ditch-drake evaluate
    --controller learned --checkpoint generalist --env narrow --task 2 --seed 0 --rollouts 1`."""
    [spec] = make_specs("learned", "generalist", "narrow", tasks=[2], rollouts=1, seed=0)
    record = run_rollout(spec)
    policy = LearnedPolicy(load_checkpoint(resolve_checkpoint_path("generalist")))
    assert policy.HasInputPort("crossing_side")
    env = DitchDrakeEnv(env="narrow", task=2)
    observation, info = env.reset(seed=0)
    sides = []
    while True:
        sides.append(info["crossing_side"])
        label, _ = policy.infer(observation["image"], observation["imu"], observation["distance"],
                                observation["bearing"], crossing_side=info["crossing_side"])
        observation, _, terminated, truncated, info = env.step(label)
        if terminated or truncated:
            break
    env.close()
    assert record.status == "reached_goal"
    # The perceived side: none (0) until the edge comes into the lidar's view, then left for good.
    seen = sides.index(-1.0)
    assert set(sides[:seen]) == {0.0} and set(sides[seen:]) == {-1.0}
    for field in ("status", "time_s", "path_length_m", "peak_tilt_deg", "final_x_m", "final_y_m"):
        assert info[field] == getattr(record, field), field


def test_a_rollover_terminates_with_the_penalty_and_the_outcome_in_info(wide_env):
    wide_env.reset(seed=1)
    while True:  # Straight ahead: into the ditch head-on (task 1 faces it).
        _, reward, terminated, truncated, info = wide_env.step(8)
        if terminated or truncated:
            break
    assert terminated and not truncated
    assert info["status"] == "rolled_over" and info["failure_region"] == "down_wall"
    assert reward < -RewardConfig().rollover_penalty + 1.0
    with pytest.raises(gymnasium.error.ResetNeeded, match="ended"):
        wide_env.step(8)


def test_the_time_limit_truncates():
    env = DitchDrakeEnv(env="wide", task=1, override="{episode: {time_limit_s: 0.5}}")
    env.reset(seed=0)
    results = [env.step(8) for _ in range(5)]
    *_, (_, _, terminated, truncated, info) = results
    assert (terminated, truncated, info["status"]) == (False, True, "timeout")
    assert [r[3] for r in results] == [False] * 4 + [True]


def test_a_scenario_file_and_reward_settings(tmp_path):
    path = tmp_path / "mine.yaml"
    path.write_text("environment: crater\ntask: 2\nseed: 4\nepisode: {time_limit_s: 1.0}\n")
    env = gymnasium.make("DitchDrake-v0", scenario=str(path), reward={"progress_per_m": 2.0})
    unwrapped = env.unwrapped
    assert (unwrapped.scenario.environment, unwrapped.scenario.task) == ("crater", 2)
    assert unwrapped.reward_config == RewardConfig(progress_per_m=2.0)
    env.close()


@pytest.mark.parametrize("action", [17, -1, 2.0, "8", True, np.array([3])])
def test_bad_actions_are_named(wide_env, action):
    wide_env.reset(seed=0)
    with pytest.raises(gymnasium.error.InvalidAction, match="expected an integer label in 0..16"):
        wide_env.step(action)


def test_numpy_integer_actions_are_taken(wide_env):
    wide_env.reset(seed=0)
    assert wide_env.step(np.int64(8))[4]["time_s"] == pytest.approx(0.103)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"env": "moat"}, "moat"),
    ({"env": "wide", "task": 7}, "7"),
    ({"env": "wide", "reward": {"bonus": 1}}, "bonus"),
    ({"env": "wide", "reward": {"goal_bonus": float("nan")}}, "goal_bonus"),
    ({"env": "wide", "render_mode": "rgb_array"}, "rgb_array"),
])
def test_bad_environment_arguments_are_named(kwargs, message):
    with pytest.raises(gymnasium.error.Error, match=message) as raised:
        gymnasium.make("DitchDrake-v0", **kwargs)
    assert isinstance(raised.value, ConfigError)


def test_stepping_before_reset_is_refused():
    env = DitchDrakeEnv(scenario=Scenario(environment="wide", task=0))
    with pytest.raises(gymnasium.error.ResetNeeded, match="no episode"):
        env.step(8)


def test_a_vector_env_of_two_spawned_workers_batches_the_observations():
    make = functools.partial(gymnasium.make, "ditch_drake:DitchDrake-v0", env="wide", task=0)
    envs = gymnasium.vector.AsyncVectorEnv([make, make], context="spawn")
    try:
        observations, infos = envs.reset(seed=[3, 4])
        assert observations["image"].shape == (2, 4, 128, 128)
        assert observations["imu"].shape == (2, 8)
        assert list(infos["seed"]) == [3, 4]
        observations, rewards, terminated, truncated, _ = envs.step(np.array([8, 12]))
        assert observations["image"].dtype == np.float32 and rewards.shape == terminated.shape == truncated.shape == (2,)
        assert observations["distance"].shape == (2, 4) and observations["bearing"].shape == (2, 4)
    finally:
        envs.close()


def test_the_issue_bar_in_a_fresh_process():
    code = ("import gymnasium, ditch_drake; from gymnasium.utils.env_checker import check_env; "
            "check_env(gymnasium.make('DitchDrake-v0', env='wide').unwrapped)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=False)
    assert result.returncode == 0, result.stderr


def test_the_action_block_commands_the_labels_row_and_stands_still_without_one():
    block = ActionLabelInput()
    context = block.CreateDefaultContext()
    block.GetInputPort("action").FixValue(context, NO_ACTION)  # None, where Drake takes it: test_versions.py
    assert list(block.GetOutputPort("command").Eval(context)) == [0.0, 0.0]
    assert list(block.GetOutputPort("label").Eval(context)) == [-1.0]
    block.GetInputPort("action").FixValue(context, np.int64(12))
    np.testing.assert_array_equal(block.GetOutputPort("command").Eval(context), actions.COMMANDS[12])
    assert list(block.GetOutputPort("label").Eval(context)) == [12.0]
    block.GetInputPort("action").FixValue(context, 17)
    with pytest.raises(ValueError, match="17"):
        block.GetOutputPort("command").Eval(context)


def test_the_observation_dictionary_shapes_the_stacks_as_float32():
    block = ObservationDict()
    context = block.CreateDefaultContext()
    image = np.linspace(0.0, 1.0, IMAGE_STACK_SIZE)
    block.GetInputPort("image_stack").FixValue(context, image)
    for name, value in (("imu_stack", np.arange(8.0)), ("distance_stack", [4.0, 3, 2, 1]),
                        ("bearing_stack", [0.1, 0.2, 0.3, 0.4])):
        block.GetInputPort(name).FixValue(context, value)
    observation = block.GetOutputPort("observation").Eval(context)
    assert {key: (value.shape, value.dtype) for key, value in observation.items()} == {
        "image": ((4, 128, 128), np.float32), "imu": ((8,), np.float32), "distance": ((4,), np.float32),
        "bearing": ((4,), np.float32)}
    np.testing.assert_array_equal(observation["image"].reshape(-1), image.astype(np.float32))
    assert observation["distance"][0] == 4.0 and observation["imu"][7] == 7.0


def test_human_rendering_draws_in_meshcat():
    from pydrake.geometry import Meshcat

    meshcat = Meshcat()
    env = gymnasium.make("DitchDrake-v0", env="wide", task=0, render_mode="human", meshcat=meshcat)
    env.reset(seed=0)
    env.step(8)
    env.render()
    assert meshcat.HasPath("/drake/illustration")
    env.close()
