"""The Gymnasium environment's speed against the closed loop it wraps: `gym_env_steps_per_s`.

    python -m ditch_drake.perf.bench_gym [episodes]

The closed loop is the bench's (`MakeClosedLoopDiagram`, as `measure_closed_loops` times it):
the scene with every perception block at 10 Hz and a fixed straight command, advanced by one
`AdvanceTo` per episode. The
environment runs the same blocks and steps them one control period per `step(8)` (label 8:
straight ahead), reading the observation dictionary and the reward at every step. Both
drive from the same seeded starts of the same task until the robot rolls over on the
first wall, about 60 control steps, taking turns episode by episode so that a slow spell of
the shared host touches both; the figures are medians over the episodes.
"""

import json
import sys
import time

import numpy as np

from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.diagrams.rollout import ConstantCommandConfig
from ditch_drake.diagrams.scenario import Scenario
from ditch_drake.gym.env import DitchDrakeEnv
from ditch_drake.perf.closed_loop import (
    TRAVERSAL_S,
    WARMUP_S,
    MakeClosedLoopDiagram,
    timed_run,
)
from ditch_drake.spec import actions, robot

STRAIGHT_COMMAND = actions.COMMANDS[actions.STRAIGHT_LABEL]
# Episodes of each kind; one is about 55 steps, a fifth of a second of wall time.
GYM_EPISODES = 15


def _timed_env_episode(env: DitchDrakeEnv, seed: int, max_steps: int) -> tuple[float, int]:
    """Wall seconds and steps of one episode of straight-ahead steps (the reset untimed)."""
    env.reset(seed=seed)
    steps = 0
    start = time.perf_counter()
    while steps < max_steps:
        steps += 1
        _, _, terminated, truncated, _ = env.step(actions.STRAIGHT_LABEL)
        if terminated or truncated:
            break
    return time.perf_counter() - start, steps


def measure_gym_env(environment: str = "wide", task: int = 0, seed: int = 0,
                    episodes: int = GYM_EPISODES) -> dict:
    """Median environment steps per second, the closed loop's control steps per second, and
    their ratio of time per step (environment over closed loop; the issue's target: at most 1.10).

    Returns:
        `gym_env_steps_per_s`, `gym_closed_loop_steps_per_s`, `gym_env_step_time_ratio`.
    """
    if episodes < 1:
        raise ValueError(f"episodes={episodes!r} must be >= 1")
    env = DitchDrakeEnv(scenario=Scenario(environment=environment, task=task))
    loop = MakeClosedLoopDiagram(SceneConfig(environment=environment, task=task),
                                 ConstantCommandConfig(list(STRAIGHT_COMMAND)))
    env_rates, loop_rates = [], []
    for episode_seed in range(seed, seed + episodes):
        wall_s, steps = _timed_env_episode(env, episode_seed, round(TRAVERSAL_S / robot.CONTROL_PERIOD_S))
        env_rates.append(steps / wall_s)
        loop_wall_s, loop_sim_s, _ = timed_run(loop, episode_seed, TRAVERSAL_S, WARMUP_S)
        loop_rates.append(loop_sim_s / robot.CONTROL_PERIOD_S / loop_wall_s)
    env.close()
    env_rate, loop_rate = float(np.median(env_rates)), float(np.median(loop_rates))
    return {"gym_env_steps_per_s": env_rate, "gym_closed_loop_steps_per_s": loop_rate,
            "gym_env_step_time_ratio": loop_rate / env_rate}


if __name__ == "__main__":
    print(json.dumps(measure_gym_env(episodes=int(sys.argv[1]) if len(sys.argv) > 1 else GYM_EPISODES)))
