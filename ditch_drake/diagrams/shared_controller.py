"""The `shared` controller: the learned policy drives where it is sure, a fallback where it is not.

The policy's `LearnedPolicy` block reports its uncertainty (`ditch_drake.learning.uncertainty`)
beside its command; a fallback computes its own command at every control step, driving
nothing; the `SharedControl` gate chooses between the two commands, with hysteresis, and its
`command` drives the robot. `AddController` adds a "handover_counter" beside the gate, so that
the rollout's record says what share of the steps the fallback drove, how often the gate
switched and where the handovers began (`RolloutRecord.handover_fraction`, `switches`,
`handover_regions`).

| fallback | what drives when the policy is unsure | reads beyond the sensors, pose and goal |
| --- | --- | --- |
| expert | the scripted shallow-angle expert (standing in for a person), style drawn from the seed | the analytic terrain (privileged) |
| mppi | the rollover-aware MPPI planner on the policy's lidar | nothing |
| teleop | a person at the Meshcat page (`MeshcatTeleop`) | nothing; needs a Meshcat, which a batch never has |

With `gate.signal` "random" the gate reads a seeded uniform draw each control step (a
"random_handover_draw", seeded by the episode's seed and keyed by its environment and task)
in place of the policy's uncertainty: the chance handover a gate is compared with
(`AddRandomHandoverDraw`). With a risk signal
("tip_risk_now", "tip_risk_ahead") it reads a "tip_risk" block (`TipRisk`) on an
"elevation_mapper" of the policy's lidar and the policy's command: how near the robot is to
tipping, now or along the arc the policy commands, rather than how unsure the policy is. With
"command_reversals" it reads a "command_reversals" block (`CommandReversals`) on the policy's
command: how often its turn reversed over the last second. With "seconds_without_progress"
or "metres_regressed", or with a watchdog beside any signal (`gate.progress_limit_s`,
`gate.regress_limit_m`), a "goal_progress" block (`GoalProgress`) on the distances to the goal
the policy saw: how long the robot has come no nearer its goal, and how far it has fallen back.
"""

import dataclasses
from dataclasses import dataclass, field

from pydrake.common import RandomDistribution
from pydrake.geometry import Meshcat
from pydrake.systems.framework import DiagramBuilder, OutputPort
from pydrake.systems.primitives import RandomSource

from ditch_drake.common.errors import ConfigError
from ditch_drake.diagrams.ditch_scene import DitchScene
from ditch_drake.diagrams.lidar_rig import AddLidar
from ditch_drake.diagrams.observation import AddObservation, Observation
from ditch_drake.diagrams.rollout import (
    AddElevationMapper,
    AddExpert,
    AddLearnedPolicy,
    AddMppiController,
    AddTipRisk,
    ExpertConfig,
    LearnedPolicyConfig,
    MppiBaselineConfig,
)
from ditch_drake.learning.checkpoint import GENERALIST_ENSEMBLE, checkpoint_digest, environment_model
from ditch_drake.learning.gate_calibration import load_signals
from ditch_drake.learning.inference import is_ensemble
from ditch_drake.learning.uncertainty import (
    DISAGREEMENT_SIGNALS,
    REVERSAL_SIGNAL,
    RISK_SIGNALS,
    UNCERTAINTY_SIGNALS,
)
from ditch_drake.spec.schedule import gate_signal_offset_s
from ditch_drake.systems.command_reversals import CommandReversals
from ditch_drake.systems.driver_indicator import DriverIndicator
from ditch_drake.systems.goal_progress import GoalProgress
from ditch_drake.systems.keyed_uniform import KeyedUniform
from ditch_drake.systems.meshcat_teleop import MeshcatTeleop
from ditch_drake.systems.policy import DEFAULT_UNCERTAINTY_SIGNAL
from ditch_drake.systems.shared_control import RANDOM_SIGNAL, WATCHDOGS, SharedControl, SharedControlConfig
from ditch_drake.systems.teleop import ActionQuantizer
from ditch_drake.systems.tip_risk import TipRiskConfig

# Where the scene's Meshcat visualizer draws the chassis: the help marker is its child.
CHASSIS_MESHCAT_PATH = "/drake/illustration/husky/chassis"


def default_policy() -> LearnedPolicyConfig:
    """The shipped generalist ensemble (`GENERALIST_ENSEMBLE`, five clones, their mean driving),
    told its crossing side by the lidar: the policy the default gate was calibrated on."""
    return LearnedPolicyConfig(checkpoint=GENERALIST_ENSEMBLE)


def default_gate() -> SharedControlConfig:
    """The gate of the shipped generalist ensemble: the tip risk along the arc it commands
    (`tip_risk_ahead`, deg: minus the least tip margin the `mppi`'s attitude model predicts
    on the perceived elevation map), with the thresholds a budget of 2 % of the control steps
    sets on its own validation rollouts, the expert taking over.

    The signal that foresaw a rollover best there: `ditch-drake gate-signals --checkpoint
    generalist_k5 --split val --rollouts 1 --seed 0 --risk` (the 50 val ditches x 3 tasks,
    rollout seed 0: 150 episodes, 9 rollovers) gave `tip_risk_ahead` an AUC of 0.94 for "a
    rollover within 2 s", against 0.64 for the members' `angular_rate_spread`.
    `ditch-drake gate-thresholds` on that file at a budget of 0.02 (5 calm steps, 3 warm-up
    steps): -6.826 and -7.666 deg (hand over where the least margin ahead falls below 6.8 deg),
    which replayed there hand over 1.99 % of the steps
    (docs/results/shared_control_generalist.md). Degrees of tip margin mean the same for any
    policy; the share of steps they hand over does not: set a budget with the policy's own
    signals file (`SharedControlConfig.budget`, `calibration`).
    """
    return SharedControlConfig(signal="tip_risk_ahead", upper_threshold=-6.826, lower_threshold=-7.666,
                               calm_steps=5, fallback="expert")


@dataclass
class SharedControlControllerConfig:
    """The learned policy gated by its tip risk or its uncertainty, with a fallback where the gate hands over.

    Attributes:
        policy: the clone (`LearnedPolicyConfig`): its checkpoint (by default the shipped
            generalist ensemble, `default_policy`; "" for the environment's shipped model, as
            for `learned`; an ensemble file runs all its members), its observation, crossing
            side and runtime. Its `uncertainty` output reports `gate.signal` (a risk signal
            comes from a "tip_risk" block on its commanded arc instead).
        gate: when control passes to the fallback and back (`SharedControlConfig`; by default
            the tip risk ahead at 2 % of the steps, `default_gate`), and who
            the fallback is (`gate.fallback`: "expert", "mppi" or "teleop"). With `gate.budget`
            and `gate.calibration` (a signals file of `ditch-drake gate-signals` for this
            policy), the thresholds are the budget's quantiles of the signal over the file's
            steps (`resolved`).
        expert: the scripted expert's config, for `gate.fallback` "expert" (its style drawn
            from the episode's seed unless set).
        mppi: the MPPI planner's config, for `gate.fallback` "mppi" (it reads the policy's
            lidar when their lidar configs are equal, else its own).
    """

    policy: LearnedPolicyConfig = field(default_factory=default_policy)
    gate: SharedControlConfig = field(default_factory=default_gate)
    expert: ExpertConfig = field(default_factory=ExpertConfig)
    mppi: MppiBaselineConfig = field(default_factory=MppiBaselineConfig)

    @property
    def checkpoint(self) -> str:
        """The policy's checkpoint (what records, `--checkpoint` and the batch's digest name)."""
        return self.policy.checkpoint

    def with_checkpoint(self, checkpoint: str) -> "SharedControlControllerConfig":
        """This config with its policy naming `checkpoint` (`LearnedPolicyConfig.with_checkpoint`)."""
        return dataclasses.replace(self, policy=self.policy.with_checkpoint(checkpoint))

    def validate(self, meshcat: Meshcat | None = None) -> None:
        """Raises ConfigError naming the first bad value.

        Args:
            meshcat: the Meshcat a teleop fallback is steered on; None (a batch, every
                registered builder) refuses fallback "teleop".
        """
        self.gate.validate()
        self.policy.validate()
        if self.gate.fallback == "teleop" and meshcat is None:
            raise ConfigError("shared control fallback 'teleop' without a Meshcat: a person steers it on the Meshcat "
                              "page, which batch evaluation and the registered builders have none of; expected "
                              "fallback 'expert' or 'mppi'")
        if self.policy.tip_risk is not None and self.gate.signal not in RISK_SIGNALS:
            raise ConfigError(f"shared control policy.tip_risk with signal {self.gate.signal!r}: the tip-risk block "
                              "only feeds a gate on a risk signal; expected signal one of "
                              f"{list(RISK_SIGNALS)}, or no policy.tip_risk")
        if self.gate.signal in DISAGREEMENT_SIGNALS and not is_ensemble(self.policy.checkpoint):
            name = self.policy.checkpoint or "the environment's shipped model"
            raise ConfigError(f"shared control signal {self.gate.signal!r} with checkpoint {name!r}, a single clone "
                              "(K = 1): the signal is the members' disagreement; expected an ensemble file "
                              "(ditch-drake train --ensemble) or signal 'mean_softmax_entropy'")
        self.gate.resolved()  # A budget's calibration file: there, with the signal, before any rollout.

    def resolved(self) -> "SharedControlControllerConfig":
        """This config with the gate's thresholds set from its budget (`SharedControlConfig.resolved`),
        so that the config a record keeps says which thresholds ran; without a budget, itself.

        Raises:
            ConfigError: as `SharedControlConfig.resolved`, or a calibration file of another
                checkpoint than the policy's or, for a risk signal, of another tip-risk arc
                (`check_calibration`).
        """
        gate = self.gate.resolved()
        if gate is self.gate:
            return self
        if gate.calibration:
            check_calibration(gate.calibration, self.policy.checkpoint, _calibrated_tip_risk(self))
        return dataclasses.replace(self, gate=gate)


def shared_for_seed(config: SharedControlControllerConfig, seed: int) -> SharedControlControllerConfig:
    """The config an episode of `seed` builds: the expert fallback's style drawn from the seed
    (as the `expert` controller's), unless set; other fallbacks are the same for every seed."""
    if config.gate.fallback != "expert" or config.expert.style_seed is not None:
        return config
    return dataclasses.replace(config, expert=dataclasses.replace(config.expert, style_seed=seed))


def shared_privileged(config: SharedControlControllerConfig) -> tuple[str, ...]:
    """What the shared controller reads beyond its sensors, its pose and the goal: its policy's
    (the oracle crossing side) and its fallback's (the expert's analytic terrain)."""
    from ditch_drake.diagrams.controllers import get_controller

    names = set(get_controller("learned").privileged_inputs(config.policy))
    if config.gate.fallback == "expert":
        names.update(get_controller("expert").privileged_inputs(config.expert))
    elif config.gate.fallback == "mppi":
        names.update(get_controller("mppi").privileged_inputs(config.mppi))
    return tuple(sorted(names))


def AddSharedController(builder: DiagramBuilder, scene: DitchScene, config: SharedControlControllerConfig,
                        meshcat: Meshcat | None = None) -> OutputPort:
    """Adds the observation and the policy (its `uncertainty` the gate's signal), the fallback
    (its command connected to the gate only) and the "shared_control" gate; returns the gate's
    `command`.

    The gate ticks after the controllers and before a recorder (between the schedule's
    controller and recorder offsets), so it chooses between this control step's commands.

    Raises:
        ConfigError: a bad config (`SharedControlControllerConfig.validate`), naming the value.
        CheckpointError: the checkpoint does not load.
    """
    config.validate(meshcat)
    observation = AddObservation(builder, scene, config.policy.observation)
    return AddSharedControl(builder, scene, config, observation, meshcat).GetOutputPort("command")


def AddSharedControl(builder: DiagramBuilder, scene: DitchScene, config: SharedControlControllerConfig,
                     observation: Observation, meshcat: Meshcat | None = None) -> SharedControl:
    """`AddSharedController` on an observation the caller made (a demonstration's recorder reads
    the same one): the policy, the fallback and the "shared_control" gate, whose `command` and
    `who_drives` are connected to nothing. With fallback "teleop" a "driver_indicator"
    (`DriverIndicator`) marks the robot and the page while the person is asked to steer.

    Raises:
        ConfigError: a bad config, naming the value.
        CheckpointError: the checkpoint does not load.
    """
    config.validate(meshcat)
    checkpoint = config.policy.checkpoint or environment_model(scene.environment.based_on or scene.environment_name)
    if config.gate.calibration:
        check_calibration(config.gate.calibration, checkpoint, _calibrated_tip_risk(config))
    random_gate = config.gate.signal == RANDOM_SIGNAL
    risk_gate = config.gate.signal in RISK_SIGNALS
    reversal_gate = config.gate.signal == REVERSAL_SIGNAL
    progress_gate = config.gate.signal in WATCHDOGS
    # The other gates read no uncertainty of the policy's; the one every checkpoint has is reported.
    signal = config.gate.signal if config.gate.signal in UNCERTAINTY_SIGNALS else DEFAULT_UNCERTAINTY_SIGNAL
    policy = AddLearnedPolicy(builder, scene, observation, checkpoint, config.policy.crossing_side,
                              config.policy.runtime, uncertainty_signal=signal,
                              precision=config.policy.precision)
    fallback = _add_fallback(builder, scene, config, observation, meshcat)
    schedule = scene.schedule
    gate = builder.AddNamedSystem("shared_control", SharedControl(
        config.gate, period_s=schedule.control_period_s,
        offset_s=(schedule.controller_offset_s + schedule.recorder_offset_s) / 2))
    builder.Connect(policy.GetOutputPort("command"), gate.GetInputPort("policy_command"))
    signal_offset_s = gate_signal_offset_s(schedule.controller_offset_s, schedule.recorder_offset_s)
    watched = list(config.gate.watchdog_limits())
    if progress_gate or watched:
        progress = builder.AddNamedSystem("goal_progress", GoalProgress(schedule.control_period_s, signal_offset_s))
        builder.Connect(observation.stacker.GetOutputPort("distance_stack"), progress.GetInputPort("distance_stack"))
        if progress_gate:
            builder.Connect(progress.GetOutputPort(config.gate.signal), gate.GetInputPort("uncertainty"))
        for name in watched:
            builder.Connect(progress.GetOutputPort(name), gate.GetInputPort(name))
    if random_gate:
        AddRandomHandoverDraw(builder, gate, schedule.control_period_s, random_draw_key(scene))
    elif risk_gate:
        risk = AddTipRisk(builder, scene, AddElevationMapper(builder, scene, observation), policy.GetOutputPort("command"),
                          config.policy.tip_risk or TipRiskConfig())
        builder.Connect(risk.GetOutputPort(config.gate.signal), gate.GetInputPort("uncertainty"))
    elif reversal_gate:
        reversals = builder.AddNamedSystem("command_reversals", CommandReversals(schedule.control_period_s,
                                                                                 signal_offset_s))
        builder.Connect(policy.GetOutputPort("command"), reversals.GetInputPort("command"))
        builder.Connect(reversals.GetOutputPort(REVERSAL_SIGNAL), gate.GetInputPort("uncertainty"))
    elif not progress_gate:
        builder.Connect(policy.GetOutputPort("uncertainty"), gate.GetInputPort("uncertainty"))
    builder.Connect(fallback, gate.GetInputPort("fallback_command"))
    if config.gate.fallback == "teleop":
        indicator = builder.AddNamedSystem("driver_indicator", DriverIndicator(
            meshcat, CHASSIS_MESHCAT_PATH, period_s=schedule.control_period_s, offset_s=schedule.recorder_offset_s))
        builder.Connect(gate.GetOutputPort("who_drives"), indicator.GetInputPort("who_drives"))
    return gate


def AddRandomHandoverDraw(builder: DiagramBuilder, gate: SharedControl, period_s: float, key: str) -> KeyedUniform:
    """Adds the random handover's draws and connects them to `gate`'s `uncertainty`: a
    "random_handover_source" `RandomSource` (one uniform draw in [0, 1) every `period_s`, at
    t_k = k * period_s) through a "random_handover_draw" `KeyedUniform` of `key`; returns the
    latter, whose output the gate reads.

    Sampling at the gate's period, it draws once per gate tick: a gate ticking after t_k (as
    `AddSharedControl`'s, between the controller and recorder offsets) reads the draw of t_k, one
    ticking at t_k that of t_(k-1); either way each draw once. Seeded as the sensor noise is:
    `diagram.SetRandomContext(context, RandomGenerator(seed))` (`StartEpisode`) re-draws it, so
    the same seed hands over at the same steps; the key (the rollout's environment and task)
    gives episodes of one seed in different ditches their own draws. Added after the policy and
    the fallback, it leaves their draws (and the plant's start) as the same seed gives them
    with any other signal.
    """
    source = builder.AddNamedSystem("random_handover_source", RandomSource(RandomDistribution.kUniform, 1, period_s))
    draw = builder.AddNamedSystem("random_handover_draw", KeyedUniform(key))
    builder.Connect(source.get_output_port(), draw.GetInputPort("draw"))
    builder.Connect(draw.GetOutputPort("keyed_draw"), gate.GetInputPort("uncertainty"))
    return draw


def random_draw_key(scene: DitchScene) -> str:
    """The key of a rollout's random handover draws: its environment and task."""
    return f"{scene.environment_name}/task{scene.task_index}"


def check_calibration(calibration: str, checkpoint: str, tip_risk: TipRiskConfig | None = None) -> None:
    """Raises ConfigError unless the signals file `calibration` was recorded with `checkpoint`'s
    file (by digest; "" checks none): another policy's signal says nothing of this one's; and,
    with `tip_risk`, its tip risk on arcs of `tip_risk.horizon_s` (a file that names none was
    recorded at the default): a longer arc predicts a smaller margin, so another arc's quantiles
    would hand over another share of the steps than the budget."""
    signals = load_signals(calibration, "gate.calibration")
    if checkpoint:
        recorded, digest = signals["checkpoint_sha256"], checkpoint_digest(checkpoint)
        if recorded != digest:
            raise ConfigError(f"gate.calibration {calibration}: recorded with checkpoint digest {recorded}, the gated "
                              f"policy {checkpoint!r} has {digest}; expected a signals file of this policy "
                              f"(ditch-drake gate-signals --checkpoint {checkpoint})")
    if tip_risk is None:
        return
    arc_s = float(signals.get("tip_risk_horizon_s", TipRiskConfig.horizon_s))
    if arc_s != tip_risk.horizon_s:
        raise ConfigError(f"gate.calibration {calibration}: its tip risk was recorded on arcs of {arc_s:g} s, the "
                          f"gate's policy.tip_risk.horizon_s is {tip_risk.horizon_s:g}; expected a signals file "
                          f"recorded with ditch-drake gate-signals --risk --risk-horizon {tip_risk.horizon_s:g}")


def _calibrated_tip_risk(config: SharedControlControllerConfig) -> TipRiskConfig | None:
    """The tip risk whose arc a risk gate's calibration file must have been recorded on; None for
    a gate on another signal."""
    return (config.policy.tip_risk or TipRiskConfig()) if config.gate.signal in RISK_SIGNALS else None


def _add_fallback(builder: DiagramBuilder, scene: DitchScene, config: SharedControlControllerConfig,
                  observation: Observation, meshcat: Meshcat | None) -> OutputPort:
    """The fallback's command port (connected to nothing yet)."""
    fallback = config.gate.fallback
    if fallback == "expert":
        return AddExpert(builder, scene, config.expert)
    if fallback == "mppi":
        # One lidar on the robot: the planner reads the policy's where they are the same sensor.
        same = config.mppi.lidar == config.policy.observation.lidar
        lidar = observation.lidar if same else AddLidar(builder, scene, config.mppi.lidar, name="mppi_lidar")
        return AddMppiController(builder, scene, config.mppi, lidar)
    schedule = scene.schedule
    teleop = builder.AddNamedSystem("meshcat_teleop", MeshcatTeleop(
        meshcat, period_s=schedule.control_period_s, offset_s=schedule.controller_offset_s))
    quantizer = builder.AddNamedSystem("teleop_quantizer", ActionQuantizer())
    builder.Connect(teleop.GetOutputPort("raw_command"), quantizer.GetInputPort("raw_command"))
    return quantizer.GetOutputPort("command")
