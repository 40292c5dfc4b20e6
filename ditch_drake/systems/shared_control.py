"""The uncertainty gate: the policy drives where it is sure, a fallback where it is not."""

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from pydrake.systems.framework import DiscreteValues, LeafSystem

from ditch_drake.common.errors import ConfigError
from ditch_drake.learning.uncertainty import UNCERTAINTY_SIGNALS, check_budget, threshold_for_budget
from ditch_drake.spec import robot
from ditch_drake.spec.schedule import CONTROLLER_OFFSET_S, RECORDER_OFFSET_S

# Who drives, as the `who_drives` output says it.
POLICY, FALLBACK = 0, 1
# What can take over: the scripted expert (standing in for a person), the MPPI planner (no
# privileged input anywhere), or a person at the teleop input.
FALLBACKS = ("expert", "mppi", "teleop")
# After the controllers have computed this control step's commands, before the recorder reads it.
GATE_OFFSET_S = (CONTROLLER_OFFSET_S + RECORDER_OFFSET_S) / 2


@dataclass
class SharedControlConfig:
    """When the gate hands control to the fallback and back.

    Attributes:
        signal: the uncertainty signal the policy reports (`ditch_drake.learning.uncertainty`).
        upper_threshold: hand over when the signal is above this (the signal's unit: rad/s for
            "angular_rate_spread", nats for the entropies). Set from `budget` when that is given.
        lower_threshold: hand back only after the signal has stayed below this ...
        calm_steps: ... for this many consecutive control steps (hysteresis: fewer switches).
        budget: the share of control steps the fallback may drive, in [0, 1]; given, the upper
            threshold is the quantile of the signal over the policy's own validation rollouts that
            hands over that share (`with_budget`); None keeps the fixed thresholds.
        fallback: who takes over, one of `FALLBACKS`.
    """

    signal: str = "angular_rate_spread"
    upper_threshold: float = 0.2
    lower_threshold: float = 0.1
    calm_steps: int = 5
    budget: float | None = None
    fallback: str = "expert"

    def validate(self) -> None:
        """Raises ConfigError naming the first bad value.

        With a budget, the thresholds' order is checked once the budget has set the upper one
        (`with_budget`), since until then it is not known.
        """
        if self.signal not in UNCERTAINTY_SIGNALS:
            raise ConfigError(f"shared control signal {self.signal!r}: expected one of {list(UNCERTAINTY_SIGNALS)}")
        if self.fallback not in FALLBACKS:
            raise ConfigError(f"shared control fallback {self.fallback!r}: expected one of {list(FALLBACKS)}")
        if isinstance(self.calm_steps, bool) or not isinstance(self.calm_steps, int) or self.calm_steps < 1:
            raise ConfigError(f"shared control calm_steps {self.calm_steps!r}: expected an integer >= 1 control steps")
        for key in ("upper_threshold", "lower_threshold"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value):
                raise ConfigError(f"shared control {key} {value!r}: expected a number")
        if self.budget is not None:
            check_budget(self.budget, "shared control budget")
        elif self.lower_threshold > self.upper_threshold:
            raise ConfigError(f"shared control lower_threshold {self.lower_threshold} > upper_threshold "
                              f"{self.upper_threshold}: expected lower <= upper (hand back below, over above)")

    def with_budget(self, signal_values) -> "SharedControlConfig":
        """This config with the upper threshold its budget sets on `signal_values` (the signal over
        the policy's own validation rollouts, `threshold_for_budget`) and no budget left to apply;
        the lower threshold is kept, or lowered to the upper one where it was above it. Without a
        budget, itself.

        Raises:
            ConfigError: as `validate`, or from `threshold_for_budget`.
        """
        self.validate()
        if self.budget is None:
            return self
        upper = threshold_for_budget(signal_values, self.budget)
        return dataclasses.replace(self, upper_threshold=upper, lower_threshold=min(self.lower_threshold, upper),
                                   budget=None)


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
    the calm count. The update stores who drives, the calm count, the number of switches (either
    way) and the command of whoever drives after it, which the outputs read, so the command
    changes only at the gate's ticks. The same update is declared as a forced discrete update,
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
        output_ports:
        - command
        - who_drives
        - switches

    Ports:
        policy_command: [v m/s, w rad/s] the policy commands.
        uncertainty: [the policy's uncertainty], in the unit of the configured signal.
        fallback_command: [v m/s, w rad/s] the fallback commands.
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
            config: the thresholds and hysteresis, with no budget left to apply (a budget's
                threshold is set from the policy's validation rollouts by
                `SharedControlConfig.with_budget`, which gives such a config).
            period_s: update period (s), the control rate.
            offset_s: time of the first update (s).

        Raises:
            ConfigError: a bad config, or one with a budget (its threshold not set yet).
            ValueError: a non-positive period or a negative offset.
        """
        super().__init__()
        config.validate()
        if config.budget is not None:
            raise ConfigError(f"shared control budget {config.budget}: its upper threshold comes from the signal over "
                              "the policy's validation rollouts; expected a config with it set "
                              "(SharedControlConfig.with_budget)")
        if not (period_s > 0 and offset_s >= 0):
            raise ValueError(f"period_s={period_s} must be positive and offset_s={offset_s} non-negative")
        self._config = config
        self._policy_port = self.DeclareVectorInputPort("policy_command", 2)
        self._uncertainty_port = self.DeclareVectorInputPort("uncertainty", 1)
        self._fallback_port = self.DeclareVectorInputPort("fallback_command", 2)
        self._command_index = self.DeclareDiscreteState(2)
        self._driver_index = self.DeclareDiscreteState(np.array([float(POLICY)]))
        self._calm_index = self.DeclareDiscreteState(1)
        self._switches_index = self.DeclareDiscreteState(1)
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
        uncertainty = float(self._uncertainty_port.Eval(context)[0])
        driver = int(context.get_discrete_state(self._driver_index).get_value()[0])
        calm = int(context.get_discrete_state(self._calm_index).get_value()[0])
        switches = context.get_discrete_state(self._switches_index).get_value()[0]
        if driver == POLICY:
            if uncertainty > self._config.upper_threshold:
                driver, calm, switches = FALLBACK, 0, switches + 1
        else:
            calm = calm + 1 if uncertainty < self._config.lower_threshold else 0
            if calm >= self._config.calm_steps:
                driver, calm, switches = POLICY, 0, switches + 1
        source = self._policy_port if driver == POLICY else self._fallback_port
        discrete_state.set_value(self._command_index, source.Eval(context))
        discrete_state.set_value(self._driver_index, [float(driver)])
        discrete_state.set_value(self._calm_index, [float(calm)])
        discrete_state.set_value(self._switches_index, [switches])
