"""`DitchDrakeEnv`: a Scenario as a Gymnasium environment, on Drake's own `pydrake.gym.DrakeGymEnv`.

The agent takes the learned policy's place: every step it reads the frame stacker's four
stacks and picks one of the 17 action labels (docs/design.md, "The action table"), which the diagram executes for one
control period (`MakeExternalAgentDiagram`). Steps begin and end at the policy block's
ticks (`ScheduleConfig.controller_offset_s` + k * period), after the stacker's, so the agent
sees exactly what the `LearnedPolicy` block would see at its update and its label takes
effect exactly when the block's would. The shipped policy stepping this environment drives
the same rollout as `ditch-drake evaluate`, to the last digit (`tests/test_gym.py`), for every
plant step that does not fall on a policy tick itself: the default 20 ms does not. (There,
the block's update and the plant's step would be simultaneous, the plant reading the old
command, while the environment's label is set before the plant's step.)
"""

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from pydrake.geometry import Meshcat
from pydrake.gym import DrakeGymEnv
from pydrake.systems.analysis import ApplySimulatorConfig, Simulator

from ditch_drake.common.errors import ConfigError
from ditch_drake.common.seeds import SEED_LIMIT, check_seed
from ditch_drake.diagrams.external_agent import MakeExternalAgentDiagram, observation_config
from ditch_drake.diagrams.rollout import StartEpisode
from ditch_drake.diagrams.scenario import Scenario, check_scenario, load_scenario
from ditch_drake.evaluation.rollout_worker import outcome_fields
from ditch_drake.spec import actions
from ditch_drake.spec.observation_layout import (
    BEARING_STACK_SIZE,
    DISTANCE_STACK_SIZE,
    IMAGE_STACK_SHAPE,
    STACK_DEPTH,
)
from ditch_drake.systems.action_label_input import NO_ACTION

# The monitor's outcomes that end the task itself (terminated) and the one that only cuts it short (truncated).
TERMINAL_STATUSES = ("reached_goal", "rolled_over", "stuck")
TIME_LIMIT_STATUS = "timeout"

# The diagrams of closed environments, by the Scenario (its repr) they were built from, each
# taken by the next environment of that Scenario. Drake 1.51 never frees a diagram that holds
# a Python LeafSystem (a reference cycle through C++ that the garbage collector cannot see;
# drake#22515), about 30 MB each, so an environment that built its own at every `make` grew the
# process by that much per make/close. Nothing is evicted: an evicted diagram would not be freed either.
# Drake 1.58 frees a one-system diagram of a Python LeafSystem, but this environment's diagram
# still grew the process by 32 MB per make/close there: the pool stays on every version.
_IDLE_DIAGRAMS: dict[str, list[tuple]] = {}



class DitchDrakeEnvError(gym.error.Error, ConfigError):
    """A bad argument to `DitchDrakeEnv`: a Gymnasium error and the project's `ConfigError` (a
    `ValueError`), so either kind of handler catches it."""


@dataclass
class RewardConfig:
    """The reward of one step: `progress_per_m` times the metres the robot came closer to the
    goal in the plane (negative when it went away), plus `goal_bonus` on the step that
    reaches the goal, minus `rollover_penalty` on the step that rolls over and
    `stuck_penalty` on the step the monitor calls it stuck. A timeout adds nothing (it
    truncates the episode)."""

    progress_per_m: float = 1.0
    goal_bonus: float = 10.0
    rollover_penalty: float = 10.0
    stuck_penalty: float = 0.0

    def __post_init__(self):
        for name, value in dataclasses.asdict(self).items():
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ConfigError(f"reward {name}={value!r}: expected a finite number")


def reward_config(reward: RewardConfig | dict | None) -> RewardConfig:
    """`reward` as a RewardConfig (a dict of its fields, or None for the defaults).

    Raises:
        ConfigError: a key RewardConfig does not have, or a value that is not a finite number.
    """
    if isinstance(reward, dict):
        known = {field.name for field in dataclasses.fields(RewardConfig)}
        if set(reward) - known:
            raise ConfigError(f"reward keys {sorted(set(reward) - known)}: expected among {sorted(known)}")
        return RewardConfig(**reward)
    return reward or RewardConfig()


def observation_space(imu_noise_std_rad: float = 0.0) -> spaces.Dict:
    """The observation's spaces, with the bounds the values really have (`ObservationDict`'s layout).

    image: normals' z components in [0, 1]; imu: Drake's roll in [-pi, pi] and pitch in
    [-pi/2, pi/2] (unbounded once Gaussian noise is added); distance: [0, inf) m; bearing:
    [-pi, pi] rad (the stacks start as zeros, which every bound admits).
    """
    roll_pitch_high = np.tile([np.pi, np.pi / 2], STACK_DEPTH).astype(np.float32)  # [roll, pitch] per step
    if imu_noise_std_rad > 0:
        roll_pitch_high = np.full_like(roll_pitch_high, np.inf)
    return spaces.Dict({
        "image": spaces.Box(0.0, 1.0, IMAGE_STACK_SHAPE, np.float32),
        "imu": spaces.Box(-roll_pitch_high, roll_pitch_high, dtype=np.float32),
        "distance": spaces.Box(0.0, np.inf, (DISTANCE_STACK_SIZE,), np.float32),
        "bearing": spaces.Box(-np.pi, np.pi, (BEARING_STACK_SIZE,), np.float32),
    })


def make_scenario(env: str | None = None, task: int | None = None, scenario: str | Path | Scenario | None = None,
                  scenario_name: str | None = None, override: str | None = None) -> Scenario:
    """The Scenario an environment wraps: `scenario` (a Scenario, a Scenario YAML file or None
    for the default one, with `scenario_name` and `override` as for `load_scenario`), then `env`
    and `task` where given. (Its seed is not the episodes': `reset(seed=...)` gives those.)

    Raises:
        ConfigError: an unknown environment or task, or a bad scenario file, naming the value.
    """
    base = scenario if isinstance(scenario, Scenario) else load_scenario(scenario, scenario_name, override)
    changes = {name: value for name, value in (("environment", env), ("task", task)) if value is not None}
    result = dataclasses.replace(base, **changes)
    check_scenario(result)
    return result


class DitchDrakeEnv(DrakeGymEnv):
    """A ditch crossing as a Gymnasium environment (`gymnasium.make("DitchDrake-v0", env="wide", task=0)`).

    Spaces:
        action: `Discrete(17)`, the action table's labels (`ditch_drake.spec.actions`): v = 1 m/s,
            w from -0.85 to 0.85 rad/s, 8 straight; executed for one control period.
        observation: `Dict` of "image" (4, 128, 128) float32, "imu" (8,), "distance" (4,)
            and "bearing" (4,), newest first (`observation_space`).

    Episodes: `reset(seed=s)` starts the scenario's task from the start pose jittered by
    seed s, with sensor noise drawn from s (the seed `ditch-drake evaluate --seed s` gives
    its first rollout); `reset()` without a seed draws the next episode's seed from the
    environment's `np_random`. The episode monitor ends an episode: `terminated` on reaching
    the goal, rolling over or being stuck, `truncated` at the scenario's time limit (and when
    the simulator fails). The last step's `info` holds the outcome record's fields
    (`RolloutRecord`'s status .. halts_by_region) with the seed; every `info` has "seed",
    "time_s" and "crossing_side": +1 or -1, the side along the edge to cross on that a clone
    trained in one side's frame is told (`LearnedPolicy.infer`'s `crossing_side`), or 0 before
    the edge is seen: `PerceivedCrossingSide`, from the lidar's rays and the pose, unless the
    scenario's learned controller asks for the oracle (`crossing_side: oracle`, from the
    ditch's analytic course: privileged). Reward: `RewardConfig`.

    The diagram is built once (the packaged sine takes seconds) and every reset reuses it.
    """

    metadata = {"render_modes": ["human"], "render_fps": 10}

    def __init__(self, env: str | None = None, task: int | None = None,
                 scenario: str | Path | Scenario | None = None, scenario_name: str | None = None,
                 override: str | None = None, reward: RewardConfig | dict | None = None,
                 render_mode: str | None = None, meshcat: Meshcat | None = None):
        """Args:
            env: an environment's name (None: the scenario's, by default "wide").
            task: the environment's task index (None: the scenario's, by default 1).
            scenario: a Scenario, or a Scenario YAML file, or None for the default Scenario.
            scenario_name, override: as for `ditch_drake.diagrams.scenario.load_scenario`.
            reward: a `RewardConfig` or a dict of its fields (None: the defaults).
            render_mode: None, or "human": the scene in Meshcat (`meshcat`, else a new one),
                drawn on `render()`.

        Raises:
            DitchDrakeEnvError: an unknown environment or task, a bad scenario, reward or render
                mode, naming the value.
        """
        try:
            if render_mode not in (None, "human"):
                raise ConfigError(f"render_mode={render_mode!r}: expected None or 'human'")
            self.reward_config = reward_config(reward)
            self.scenario = make_scenario(env, task, scenario, scenario_name, override)
        except ConfigError as error:
            raise DitchDrakeEnvError(str(error)) from error
        self.metadata = dict(type(self).metadata)
        if render_mode == "human" and meshcat is None:
            meshcat = Meshcat()
        self.meshcat = meshcat
        # A diagram drawing in a Meshcat is that Meshcat's: only those without one are shared.
        self._diagram_key = repr(self.scenario) if meshcat is None else None
        idle = _IDLE_DIAGRAMS.get(self._diagram_key, [])
        self.diagram, self.scene = idle.pop() if idle else MakeExternalAgentDiagram(self.scenario, meshcat)
        simulator = Simulator(self.diagram)
        ApplySimulatorConfig(self.scenario.simulator, simulator)
        schedule = self.scene.schedule
        super().__init__(
            simulator, time_step=schedule.control_period_s, action_space=spaces.Discrete(actions.NUM_LABELS),
            observation_space=observation_space(observation_config(self.scenario).imu.noise_std_rad),
            reward=self._step_reward, action_port_id="action", observation_port_id="observation",
            render_mode=render_mode)
        # DrakeGymEnv writes the render modes it offers into `metadata` (the class's dict, were it
        # not for the instance's copy above): this environment offers only "human".
        self.metadata = dict(type(self).metadata)
        self._first_boundary_s = schedule.controller_offset_s  # See the module docstring.
        # The Simulator keeps one Context for the environment's life; these are parts of it.
        goal = self.diagram.GetSubsystemByName("goal_sensor")
        self._distance_port, self._goal_context = goal.GetOutputPort("distance"), goal.GetMyContextFromRoot(
            self.simulator.get_context())
        self._side_port = self.diagram.GetOutputPort("crossing_side")
        self._distance_m = math.nan
        self._episode_seed: int | None = None
        self._ended = True

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        gym.Env.reset(self, seed=seed)
        if options:
            raise ValueError(f"reset options {options!r}: DitchDrakeEnv takes none")
        if seed is None:
            seed = int(self.np_random.integers(SEED_LIMIT))
        check_seed(seed, where="reset seed")
        self.action_port.FixValue(self.simulator.get_mutable_context(), NO_ACTION)  # Stand still until the first step.
        StartEpisode(self.simulator, self.diagram, seed)
        self.simulator.AdvanceTo(self._first_boundary_s)
        context = self.simulator.get_context()
        self._distance_m = self._read_distance()
        self._episode_seed, self._ended = seed, False
        return self.observation_port.Eval(context), self._info(context)

    def step(self, action):
        if self._ended:
            raise gym.error.ResetNeeded("DitchDrakeEnv: call reset() before step(): "
                                        + ("no episode has started" if self._episode_seed is None
                                           else "the episode has ended"))
        if isinstance(action, (bool, np.bool_)) or not self.action_space.contains(action):
            raise gym.error.InvalidAction(f"action {action!r} (type {type(action).__name__}): expected an integer "
                                          f"label in 0..{actions.NUM_LABELS - 1} (Discrete({actions.NUM_LABELS}))")
        # DrakeGymEnv's `terminated` is the simulator's termination: the episode monitor ended the
        # episode (or, with `truncated`, the simulator failed).
        observation, reward, ended, truncated, _ = super().step(int(action))
        context = self.simulator.get_context()
        info = self._info(context)
        terminated = False
        if ended:
            info.update(outcome_fields(self.diagram, self.scene, context))
            terminated = info["status"] in TERMINAL_STATUSES
            truncated = info["status"] == TIME_LIMIT_STATUS
            reward += self._outcome_reward(info["status"])
        self._ended = terminated or truncated
        return observation, float(reward), terminated, truncated, info

    def _read_distance(self) -> float:
        return float(self._distance_port.EvalBasicVector(self._goal_context)[0])

    def _step_reward(self, system, context) -> float:
        """The progress part of the reward (DrakeGymEnv's reward callable); `step` adds the outcome's."""
        distance = self._read_distance()
        reward = self.reward_config.progress_per_m * (self._distance_m - distance)
        self._distance_m = distance
        return reward

    def _outcome_reward(self, status: str) -> float:
        config = self.reward_config
        return {"reached_goal": config.goal_bonus, "rolled_over": -config.rollover_penalty,
                "stuck": -config.stuck_penalty}.get(status, 0.0)

    def close(self):
        """Gives the diagram to the next environment of this Scenario (see `_IDLE_DIAGRAMS`); each
        environment simulates it in its own Context, so a closed one that is still stepped is unharmed."""
        super().close()
        if self._diagram_key is not None:
            _IDLE_DIAGRAMS.setdefault(self._diagram_key, []).append((self.diagram, self.scene))
            self._diagram_key = None  # Given once, however often close() is called.

    def _info(self, context) -> dict:
        return {"seed": self._episode_seed, "time_s": context.get_time(),
                "crossing_side": float(self._side_port.Eval(context)[0])}
