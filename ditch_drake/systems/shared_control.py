"""The uncertainty gate: the policy drives where it is sure, a fallback where it is not."""

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
from pydrake.systems.framework import DiscreteValues, LeafSystem

from ditch_drake.common.config_yaml import WRITTEN_WHEN_SET
from ditch_drake.common.errors import ConfigError
from ditch_drake.learning.gate_calibration import FALLBACK, POLICY, budget_thresholds, calibration_values, gate_step
from ditch_drake.learning.uncertainty import (
    GATE_SIGNALS,
    PROGRESS_SIGNAL,
    RANDOM_SIGNAL,
    REGRESS_SIGNAL,
    REVERSAL_SIGNAL,
    UNCERTAINTY_SIGNALS,
)
from ditch_drake.spec import robot
from ditch_drake.spec.observation_layout import STACK_DEPTH
from ditch_drake.spec.schedule import CONTROLLER_OFFSET_S, RECORDER_OFFSET_S

# What can take over: the scripted expert (standing in for a person), the MPPI planner (no
# privileged input anywhere), or a person at the teleop input.
FALLBACKS = ("expert", "mppi", "teleop")
# After the controllers have computed this control step's commands, before the recorder reads it.
GATE_OFFSET_S = (CONTROLLER_OFFSET_S + RECORDER_OFFSET_S) / 2
# The watchdogs a gate may keep beside its signal: the signal each reads (`GoalProgress`'s
# outputs) and the config field of its limit, in the signal's unit.
WATCHDOGS = {PROGRESS_SIGNAL: "progress_limit_s", REGRESS_SIGNAL: "regress_limit_m"}


@dataclass
class SharedControlConfig:
    """When the gate hands control to the fallback and back.

    Attributes:
        signal: the uncertainty signal the policy reports (`ditch_drake.learning.uncertainty`),
            a risk signal ("tip_risk_now", "tip_risk_ahead": minus the tip margin now or along
            the policy's commanded arc, `ditch_drake.systems.tip_risk`), "command_reversals" (how
            often the policy's turn reversed over the last second,
            `ditch_drake.systems.command_reversals`), "seconds_without_progress" (how long
            the robot has come no nearer its goal, `ditch_drake.systems.goal_progress`),
            "metres_regressed" (the most it has fallen back from the goal since), or "random"
            (`RANDOM_SIGNAL`): a uniform draw in [0, 1) each control step, seeded by the
            episode's seed and keyed by its environment and task, in its place (the chance
            handover a gate is compared with).
        upper_threshold: hand over when the signal is above this (the signal's unit: rad/s for
            "angular_rate_spread", nats for the entropies, deg for the risk signals, in [0, 1]
            for "random", a count for "command_reversals", s for "seconds_without_progress", m for
            "metres_regressed").
            With a budget, set from it.
        lower_threshold: hand back only after the signal has stayed below this ...
        calm_steps: ... for this many consecutive control steps (hysteresis: fewer switches).
        warmup_steps: control steps at each episode's start whose signal the gate ignores (the
            policy drives them): the policy's stacks of the last `STACK_DEPTH` observations fill
            over the first `STACK_DEPTH` - 1 steps, and on the partly empty stacks the members
            of the paper clones' ensembles disagree at the start of every narrow and nearly
            every wide validation episode, far above their later disagreement.
        budget: the share of control steps the fallback may drive, in (0, 1); given, both
            thresholds come from the signal's values in `calibration` (`resolved`): the
            (1 - s) and (1 - 2 s) quantiles at the largest share s for which this gate,
            `calm_steps` included, replayed over the recorded episodes hands the fallback at
            most `budget` of their steps (`ditch_drake.learning.gate_calibration.budget_thresholds`).
            With signal "random" only the upper one, and no file: the lower one and
            `calm_steps` stay as set, and the upper one is the one at which the fallback's
            expected share of the steps, hysteresis included (`random_fallback_share`), is the
            budget (`random_upper_threshold`). None: the fixed thresholds above.
        calibration: with a budget, the signals file of the gated policy's own validation
            rollouts (`ditch-drake gate-signals`) whose values of `signal` set the thresholds
            (none with signal "random").
        fallback: who takes over, one of `FALLBACKS`.
        progress_limit_s: a watchdog beside the signal: where set, the gate also hands over
            once the robot has come no nearer its goal for more than this many seconds
            ("seconds_without_progress", `ditch_drake.systems.goal_progress`), whatever the
            signal says, and a step counts calm only where that is back within the limit, so
            the fallback keeps control until the robot is nearer the goal than it had been. It
            reads the pose and the goal only. A budget's thresholds are set for the signal as
            without it: the watchdog's handovers come on top. None: no watchdog.
        regress_limit_m: a second watchdog, the same way: where set, the gate also hands over
            once the robot has fallen back more than this many metres from the goal since it
            last came nearer ("metres_regressed"), and keeps the fallback driving until it is
            nearer the goal than it had been. None: no such watchdog.
    """

    signal: str = "angular_rate_spread"
    upper_threshold: float = 0.2
    lower_threshold: float = 0.1
    calm_steps: int = 5
    warmup_steps: int = STACK_DEPTH - 1
    budget: float | None = None
    fallback: str = "expert"
    calibration: str = field(default="", metadata=WRITTEN_WHEN_SET)
    progress_limit_s: float | None = field(default=None, metadata=WRITTEN_WHEN_SET)
    regress_limit_m: float | None = field(default=None, metadata=WRITTEN_WHEN_SET)

    def validate(self) -> None:
        """Raises ConfigError naming the first bad value.

        With a budget, the thresholds' order is not checked: the budget sets both (`resolved`),
        and the file it reads is read only then. With signal "random" it is (the budget sets
        the upper one alone, with no file), and both must lie in [0, 1].
        """
        if self.signal not in GATE_SIGNALS:
            raise ConfigError(f"shared control signal {self.signal!r}: expected one of {list(GATE_SIGNALS)}")
        if self.fallback not in FALLBACKS:
            raise ConfigError(f"shared control fallback {self.fallback!r}: expected one of {list(FALLBACKS)}")
        if isinstance(self.calm_steps, bool) or not isinstance(self.calm_steps, int) or self.calm_steps < 1:
            raise ConfigError(f"shared control calm_steps {self.calm_steps!r}: expected an integer >= 1 control steps")
        if isinstance(self.warmup_steps, bool) or not isinstance(self.warmup_steps, int) or self.warmup_steps < 0:
            raise ConfigError(f"shared control warmup_steps {self.warmup_steps!r}: expected an integer >= 0 control "
                              "steps")
        for key in ("upper_threshold", "lower_threshold"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value):
                raise ConfigError(f"shared control {key} {value!r}: expected a number")
        if self.budget is not None:
            budget = self.budget
            if isinstance(budget, bool) or not isinstance(budget, (int, float)) or not 0.0 < budget < 1.0:
                raise ConfigError(f"shared control budget {budget!r}: expected a share of control steps in (0, 1)")
        self._validate_watchdogs()
        if (self.signal in UNCERTAINTY_SIGNALS or self.signal in (REVERSAL_SIGNAL, *WATCHDOGS)) and (
                self.budget is None):
            for key in ("upper_threshold", "lower_threshold"):
                if getattr(self, key) < 0.0:
                    raise ConfigError(f"shared control {key} {getattr(self, key)!r} with signal {self.signal!r}, "
                                      "which is never negative (a risk signal's threshold in deg?); expected a "
                                      "threshold >= 0 in the signal's unit, or a budget with a calibration file")
        if self.signal == RANDOM_SIGNAL:
            self._validate_random()
        elif self.budget is not None:
            if not self.calibration:
                raise ConfigError(f"shared control budget {budget} without a calibration: its thresholds are "
                                  f"quantiles of the {self.signal} signal over the policy's validation rollouts; "
                                  "expected calibration: a signals file of ditch-drake gate-signals")
        elif self.calibration:
            raise ConfigError(f"shared control calibration {self.calibration!r} without a budget: expected a budget "
                              "in (0, 1) to set the thresholds from it, or no calibration")
        elif self.lower_threshold > self.upper_threshold:
            raise ConfigError(f"shared control lower_threshold {self.lower_threshold} > upper_threshold "
                              f"{self.upper_threshold}: expected lower <= upper (hand back below, over above)")

    def resolved(self) -> "SharedControlConfig":
        """This config with the thresholds its budget sets on its calibration file
        (`ditch_drake.learning.gate_calibration.budget_thresholds`), the budget and the file
        kept so that it says where they came from; with signal "random", the upper threshold
        `random_upper_threshold` and the lower one as set; without a budget, itself. Resolving a resolved
        config gives the same thresholds (the file read again).

        Raises:
            ConfigError: as `validate`; a calibration file that does not read, or has no values
                of the signal (a single clone's has none of the disagreement signals), naming
                `gate.calibration`.
        """
        self.validate()
        if self.budget is None:
            return self
        if self.signal == RANDOM_SIGNAL:
            return dataclasses.replace(
                self, upper_threshold=random_upper_threshold(self.budget, self.lower_threshold, self.calm_steps))
        upper, lower = budget_thresholds(calibration_values(self.calibration, self.signal), self.budget,
                                         self.calm_steps, self.warmup_steps)
        return dataclasses.replace(self, upper_threshold=upper, lower_threshold=lower)

    def watchdog_limits(self) -> dict[str, float]:
        """The limit of each watchdog set, by the signal it reads (`WATCHDOGS`)."""
        return {signal: getattr(self, key) for signal, key in WATCHDOGS.items() if getattr(self, key) is not None}

    def _validate_watchdogs(self) -> None:
        """Each watchdog limit, where set: a finite number > 0 in its signal's unit, beside a
        signal other than the one it reads (a gate on that has its thresholds for it)."""
        expected = {PROGRESS_SIGNAL: "a number of seconds > 0 without progress toward the goal",
                    REGRESS_SIGNAL: "a number of metres > 0 fallen back from the goal"}
        for signal, key in WATCHDOGS.items():
            limit = getattr(self, key)
            if limit is None:
                continue
            if isinstance(limit, bool) or not isinstance(limit, (int, float)) or not 0.0 < limit < math.inf:
                raise ConfigError(f"shared control {key} {limit!r}: expected {expected[signal]}, or none")
            if self.signal == signal:
                raise ConfigError(f"shared control {key} {limit!r} with signal {signal!r}: the gate already reads "
                                  f"it, with its thresholds; expected another signal, or no {key}")

    def _validate_random(self) -> None:
        """The thresholds of the random draw: in [0, 1], where a draw in [0, 1) can cross them
        (a leftover of another signal's, such as the default gate's 2.3 nats, is refused rather
        than read as "always calm"), lower <= upper, no calibration file, and a budget that the
        hysteresis can meet (`random_upper_threshold`)."""
        if self.calibration:
            raise ConfigError(f"shared control calibration {self.calibration!r} with signal 'random': its upper "
                              "threshold comes from the budget and the hysteresis, from no file; expected no "
                              "calibration")
        keys = ("lower_threshold",) if self.budget is not None else ("upper_threshold", "lower_threshold")
        for key in keys:
            value = getattr(self, key)
            if not 0.0 <= value <= 1.0:
                raise ConfigError(f"shared control {key} {value!r} with signal 'random': expected a number in "
                                  "[0, 1], the range of the uniform draw it is compared with")
        if self.budget is not None:
            upper, source = random_upper_threshold(self.budget, self.lower_threshold, self.calm_steps), (
                f"the budget {self.budget}'s upper threshold")
        else:
            upper, source = self.upper_threshold, "upper_threshold"
        if self.lower_threshold > upper:
            raise ConfigError(f"shared control lower_threshold {self.lower_threshold} > {source} {upper:g} with "
                              "signal 'random': expected lower <= upper (hand back below, over above)")


def random_fallback_share(upper_threshold: float, lower_threshold: float, calm_steps: int) -> float:
    """The long-run share of control steps the fallback drives when the gate reads a uniform draw
    in [0, 1) each step (signal "random"), hysteresis included.

    While the policy drives, each step hands over with chance p = 1 - upper, so a spell of the
    policy lasts 1 / p steps on average (the handback step included). The fallback's spell lasts
    until `calm_steps` draws in a row fall below the lower threshold (chance q each): on average
    N = (1 - q^c) / ((1 - q) q^c) steps (the handover step included, the handback step not;
    N = c where q = 1). The share is N / (1 / p + N) = p N / (1 + p N): p itself where c = 1 and
    q = 1 - p (each step's driver then its own draw's), more with any hysteresis. An episode
    starts with the policy driving, so a short one's share is a little less.

    Raises:
        ConfigError: thresholds outside [0, 1] or lower above upper, or calm_steps < 1.
    """
    SharedControlConfig(signal=RANDOM_SIGNAL, upper_threshold=upper_threshold, lower_threshold=lower_threshold,
                        calm_steps=calm_steps).validate()
    handover = 1.0 - upper_threshold
    if handover == 0.0:
        return 0.0
    if lower_threshold == 0.0:
        return 1.0
    spell = _mean_fallback_spell(lower_threshold, calm_steps)
    return handover * spell / (1.0 + handover * spell)


def _mean_fallback_spell(lower_threshold: float, calm_steps: int) -> float:
    """Control steps a random handover lasts on average, the handover step included: until
    `calm_steps` draws in a row fall below `lower_threshold` (in (0, 1])."""
    calm = lower_threshold
    return float(calm_steps) if calm == 1.0 else (1.0 - calm**calm_steps) / ((1.0 - calm) * calm**calm_steps)


def random_upper_threshold(budget: float, lower_threshold: float, calm_steps: int) -> float:
    """The upper threshold of the random draw at which the fallback's expected share of the steps
    (`random_fallback_share`) is `budget`, for the hysteresis set.

    With the fallback's spells N steps long on average, the share p N / (1 + p N) is the budget
    where the chance of a handover is p = budget / ((1 - budget) N); the threshold is 1 - p.
    Without hysteresis (`calm_steps` 1, lower = upper) that is 1 - budget.

    Raises:
        ConfigError: a lower threshold outside [0, 1], calm_steps < 1, or a budget that spells
            of N steps cannot stay within (p above 1: the budget above N / (1 + N)).
    """
    if not 0.0 <= lower_threshold <= 1.0:
        raise ConfigError(f"shared control lower_threshold {lower_threshold!r} with signal 'random': expected a "
                          "number in [0, 1], the range of the uniform draw it is compared with")
    if isinstance(calm_steps, bool) or not isinstance(calm_steps, int) or calm_steps < 1:
        raise ConfigError(f"shared control calm_steps {calm_steps!r}: expected an integer >= 1 control steps")
    if lower_threshold == 0.0:
        raise ConfigError(f"shared control lower_threshold 0 with signal 'random' and budget {budget}: the draw is "
                          "never below it, so the fallback never hands back; expected a lower threshold in (0, 1]")
    spell = _mean_fallback_spell(lower_threshold, calm_steps)
    handover = budget / ((1.0 - budget) * spell)
    if handover > 1.0:
        raise ConfigError(f"shared control budget {budget} with signal 'random', lower_threshold {lower_threshold} "
                          f"and calm_steps {calm_steps}: the fallback's spells ({spell:.3g} steps on average) hold "
                          f"it more than that even with a handover at every policy step; expected a budget of at "
                          f"most {spell / (1.0 + spell):.3g}, or a lower threshold nearer 1, or fewer calm steps")
    return 1.0 - handover


class SharedControl(LeafSystem):
    """Executes the policy's command while its uncertainty is low, the fallback's while it is high.

    A periodic discrete update every `period_s` (at t_k = offset_s + k * period_s) reads the
    inputs and decides who drives, with hysteresis:

    - while the policy drives, an uncertainty above `upper_threshold` hands over to the fallback
      at this step;
    - while the fallback drives, each step with the uncertainty below `lower_threshold` counts
      one calm step and any other step resets the count; the step on which the count reaches
      `calm_steps` hands back to the policy.

    A NaN uncertainty is neither above nor below a threshold: it hands nothing over and resets
    the calm count; the first `warmup_steps` updates read the uncertainty as NaN (the policy
    drives while its observation stacks fill). With a watchdog (`config.progress_limit_s`,
    `config.regress_limit_m`), a step whose watched input is above its limit hands over too,
    and is not calm (`gate_step`'s `forced`; none in the warm-up). The update stores who drives,
    the calm count, the number of switches (either way) and the command of whoever drives after
    it, which the outputs read, so the command changes only at the gate's ticks. The same update is declared as a forced discrete update,
    so `CalcForcedDiscreteVariableUpdate` runs one step too. Until the first update the policy
    drives and the command is [0, 0] (stand still).

    In a scene it ticks after the controllers and before the recorder (`GATE_OFFSET_S`), so the
    commands it chooses between are this control step's and the recorder sees its choice.

    .. pydrake_system::

        name: SharedControl
        input_ports:
        - policy_command
        - uncertainty
        - fallback_command
        - seconds_without_progress (optional)
        - metres_regressed (optional)
        output_ports:
        - command
        - who_drives
        - switches

    Ports:
        policy_command: [v m/s, w rad/s] the policy commands.
        uncertainty: [the policy's uncertainty], in the unit of the configured signal; with
            signal "random", the draw in [0, 1) that `AddSharedControl` connects instead, and
            with a risk signal the `TipRisk` block's output of that name.
        fallback_command: [v m/s, w rad/s] the fallback commands.
        seconds_without_progress: (only with `config.progress_limit_s`) [s] since the robot
            last came nearer its goal (`GoalProgress`).
        metres_regressed: (only with `config.regress_limit_m`) [m] the most it has fallen back
            from the goal since (`GoalProgress`).
        command: [v m/s, w rad/s] the executed command.
        who_drives: [0] the policy, [1] the fallback (a float).
        switches: [handovers plus handbacks so far] (a float).
    """

    def __init__(
        self,
        config: SharedControlConfig,
        period_s: float = robot.CONTROL_PERIOD_S,
        offset_s: float = GATE_OFFSET_S,
    ):
        """Declares the ports, the state and the periodic update.

        Args:
            config: the thresholds and hysteresis; a budget's are set from its calibration
                file here (`SharedControlConfig.resolved`).
            period_s: update period (s), the control rate.
            offset_s: time of the first update (s).

        Raises:
            ConfigError: a bad config, or a budget's calibration file that does not give the
                signal's values.
            ValueError: a non-positive period or a negative offset.
        """
        super().__init__()
        config = config.resolved()
        if not (period_s > 0 and offset_s >= 0):
            raise ValueError(f"period_s={period_s} must be positive and offset_s={offset_s} non-negative")
        self._config = config
        self._policy_port = self.DeclareVectorInputPort("policy_command", 2)
        self._uncertainty_port = self.DeclareVectorInputPort("uncertainty", 1)
        self._fallback_port = self.DeclareVectorInputPort("fallback_command", 2)
        self._watchdogs = [(self.DeclareVectorInputPort(signal, 1), limit)
                           for signal, limit in config.watchdog_limits().items()]
        self._command_index = self.DeclareDiscreteState(2)
        self._driver_index = self.DeclareDiscreteState(np.array([float(POLICY)]))
        self._calm_index = self.DeclareDiscreteState(1)
        self._switches_index = self.DeclareDiscreteState(1)
        self._step_index = self.DeclareDiscreteState(1)
        self.DeclareStateOutputPort("command", self._command_index)
        self.DeclareStateOutputPort("who_drives", self._driver_index)
        self.DeclareStateOutputPort("switches", self._switches_index)
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, offset_s, self._update)
        self.DeclareForcedDiscreteUpdateEvent(self._update)

    @property
    def config(self) -> SharedControlConfig:
        """The thresholds and hysteresis it gates with."""
        return self._config

    def _update(self, context, discrete_state: DiscreteValues) -> None:
        step = int(context.get_discrete_state(self._step_index).get_value()[0])
        warm = step >= self._config.warmup_steps
        uncertainty = float(self._uncertainty_port.Eval(context)[0]) if warm else math.nan
        forced = warm and any(float(port.Eval(context)[0]) > limit for port, limit in self._watchdogs)
        driver = int(context.get_discrete_state(self._driver_index).get_value()[0])
        calm = int(context.get_discrete_state(self._calm_index).get_value()[0])
        switches = context.get_discrete_state(self._switches_index).get_value()[0]
        driver, calm, switched = gate_step(driver, calm, uncertainty, self._config.upper_threshold,
                                           self._config.lower_threshold, self._config.calm_steps, forced)
        switches += switched
        source = self._fallback_port if driver == FALLBACK else self._policy_port
        discrete_state.set_value(self._command_index, source.Eval(context))
        discrete_state.set_value(self._driver_index, [float(driver)])
        discrete_state.set_value(self._calm_index, [float(calm)])
        discrete_state.set_value(self._switches_index, [switches])
        discrete_state.set_value(self._step_index, [float(step + 1)])
