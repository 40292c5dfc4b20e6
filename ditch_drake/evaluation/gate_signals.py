"""The learned policy's uncertainty on its own rollouts: every signal its checkpoint has, at
every control step, with each episode's outcome (`ditch-drake gate-signals`).

The policy drives, ungated (the `learned` controller), and `SignalWatch`, a `RunEpisode` watch
called once per control step, reads its block's inputs and decision: it runs the block's own
`decide` on the stacks the block read (they do not change between its tick and the next
stacker tick), so it gets every member's probabilities, checks that the label is the one the
block chose, and evaluates every signal of `ditch_drake.learning.uncertainty` the checkpoint
has (all three for an ensemble, "mean_softmax_entropy" for a single clone) on them. The extra
forward pass per step is the price of not changing the policy block's ports.
"""

import math
from dataclasses import dataclass, field, replace

from ditch_drake.diagrams.ditch_scene import SceneConfig
from ditch_drake.diagrams.rollout import LearnedPolicyConfig, MakeRolloutDiagram, RolloutConfig, RunEpisode
from ditch_drake.learning.uncertainty import DISAGREEMENT_SIGNALS, UNCERTAINTY_SIGNALS
from ditch_drake.spec.schedule import ScheduleConfig
from ditch_drake.systems.episode_monitor import EpisodeConfig
from ditch_drake.systems.policy import LearnedPolicy

# The policy block's observation inputs, in `LearnedPolicy.decide`'s order.
STACK_PORTS = ("image_stack", "imu_stack", "distance_stack", "bearing_stack")


def supported_signals(members: int) -> list[str]:
    """The signals a policy of `members` clones has: the disagreement ones need two or more."""
    return [name for name in UNCERTAINTY_SIGNALS if members >= 2 or name not in DISAGREEMENT_SIGNALS]


class SignalWatch:
    """Records every signal at each of the policy's decisions; a `RunEpisode` watch.

    Called with the root Context at the end of each control period (`watch_period_s` = the
    control period), when the policy's latest tick is `offset_s` into the period just ended.
    A tick already recorded (an episode that ended mid-period) is not recorded twice; before
    the policy's first tick nothing is.
    """

    def __init__(self, policy: LearnedPolicy, schedule: ScheduleConfig):
        self._policy = policy
        self._period_s = schedule.control_period_s
        self._offset_s = schedule.controller_offset_s
        self.signals = supported_signals(policy.members)
        self._rates = policy.action_commands[:, 1]
        self.time_s: list[float] = []
        self.values: dict[str, list[float]] = {name: [] for name in self.signals}

    def __call__(self, root_context) -> bool:
        context = self._policy.GetMyContextFromRoot(root_context)
        label = int(self._policy.GetOutputPort("label").Eval(context)[0])
        tick_s = self._offset_s + math.floor((root_context.get_time() - self._offset_s) / self._period_s + 1e-9) * (
            self._period_s)
        if label < 0 or tick_s < 0 or (self.time_s and tick_s <= self.time_s[-1] + 1e-9):
            return False
        stacks = [self._policy.GetInputPort(name).Eval(context) for name in STACK_PORTS]
        side = (float(self._policy.GetInputPort("crossing_side").Eval(context)[0])
                if self._policy.HasInputPort("crossing_side") else 1.0)
        decision = self._policy.decide(*stacks, crossing_side=side)
        if decision.label != label:
            raise RuntimeError(f"the policy chose label {label} at {tick_s:.3f} s but its inputs now give "
                               f"{decision.label}: the watch does not see what the policy saw")
        self.time_s.append(tick_s)
        for name in self.signals:
            self.values[name].append(float(UNCERTAINTY_SIGNALS[name](decision.member_probabilities, self._rates)))
        return False


@dataclass
class GateSignals:
    """What `record_gate_signals` recorded: the arrays of a signals file
    (`ditch_drake.learning.gate_calibration.save_signals`)."""

    signals: dict[str, list[float]] = field(default_factory=dict)
    steps: dict[str, list] = field(default_factory=lambda: {"time_s": [], "episode": []})
    episodes: dict[str, list] = field(default_factory=lambda: {
        "episode_environment": [], "episode_task": [], "episode_seed": [], "episode_status": [],
        "episode_end_time_s": []})


def record_gate_signals(checkpoint: str, runs: list[tuple[str, int]], rollouts: int = 10, seed: int = 0,
                        time_limit_s: float = EpisodeConfig.time_limit_s, environments_file: str = "",
                        progress: bool = True) -> GateSignals:
    """Runs `rollouts` episodes (seeds seed ..) of the learned policy of `checkpoint` on each
    (environment, task) of `runs`, ungated, and records every signal it has at every control step.

    Raises:
        ConfigError: a bad environment, task or time limit.
        CheckpointError: the checkpoint does not load.
    """
    from pydrake.systems.analysis import Simulator

    recorded = GateSignals()
    for environment, task in runs:
        scene = SceneConfig(environment=environment, task=task, environments_file=environments_file,
                            episode=replace(EpisodeConfig(), time_limit_s=time_limit_s))
        diagram, built = MakeRolloutDiagram(RolloutConfig(scene=scene, controller=LearnedPolicyConfig(checkpoint)))
        policy = diagram.GetSubsystemByName("learned_policy")
        simulator = Simulator(diagram)
        for episode_seed in range(seed, seed + rollouts):
            watch = SignalWatch(policy, built.schedule)
            description = f"{environment} task {task} seed {episode_seed}" if progress else None
            outcome = RunEpisode(simulator, diagram, built, episode_seed, progress=description, watch=watch,
                                 watch_period_s=built.schedule.control_period_s)
            index = len(recorded.episodes["episode_seed"])
            for name in watch.signals:
                recorded.signals.setdefault(name, []).extend(watch.values[name])
            recorded.steps["time_s"].extend(watch.time_s)
            recorded.steps["episode"].extend([index] * len(watch.time_s))
            for key, value in (("episode_environment", environment), ("episode_task", task),
                               ("episode_seed", episode_seed), ("episode_status", outcome.status),
                               ("episode_end_time_s", outcome.time_s)):
                recorded.episodes[key].append(value)
    return recorded

