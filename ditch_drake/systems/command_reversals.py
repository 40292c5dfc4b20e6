"""How often the policy has just reversed its turn: the paper's symptom of an unfamiliar state.

The paper saw its clone "fluctuate between two opposing actions (i.e., predicting a slight left
turn then a slight right turn afterwards, repeatedly) when it encountered unfamiliar states,
often resulting in a rollover". The members' disagreement reads that in one view; this reads it
in time, as the paper saw it: the number of times the sign of the commanded angular rate
reversed over the last `REVERSAL_WINDOW_STEPS` control steps, straight-ahead commands skipped
(left, straight, right is one reversal). It needs no ensemble, so a single clone has it.
"""

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from ditch_drake.spec import robot
from ditch_drake.spec.schedule import CONTROLLER_OFFSET_S, RECORDER_OFFSET_S, gate_signal_offset_s

# One second of control steps: long enough for "repeatedly", short enough that a reversal
# counted is one the robot is still driving through.
REVERSAL_WINDOW_STEPS = round(1.0 / robot.CONTROL_PERIOD_S)


def count_reversals(angular_rates) -> int:
    """How often the sign of `angular_rates` (rad/s, in time order) reverses, zeros skipped."""
    signs = np.sign(np.asarray(angular_rates, dtype=float))
    signs = signs[signs != 0]
    return int(np.count_nonzero(signs[1:] != signs[:-1]))


class CommandReversals(LeafSystem):
    """Counts the reversals of the commanded turn over the last `REVERSAL_WINDOW_STEPS` control
    steps (module doc).

    It keeps the window's angular rates as discrete state, each sampled at its tick (`offset_s`
    into each control period: after the controllers' commands, before the gate reads
    `command_reversals`), and its output is the count over that state. So the gate's tick reads
    the window ending with this step's command, the output holds until the next tick, and a
    step's command is counted once whatever else the simulator stops for. Before the first
    command (a zero command) nothing counts.

    .. pydrake_system::

        name: CommandReversals
        input_ports:
        - command
        output_ports:
        - command_reversals

    Ports:
        command: [v m/s, w rad/s], the policy's command.
        command_reversals: [count] reversals of the sign of w in the window.
    """

    def __init__(self, period_s: float = robot.CONTROL_PERIOD_S,
                 offset_s: float = gate_signal_offset_s(CONTROLLER_OFFSET_S, RECORDER_OFFSET_S)):
        super().__init__()
        self._command_port = self.DeclareVectorInputPort("command", 2)
        window = self.DeclareDiscreteState(REVERSAL_WINDOW_STEPS)  # Oldest first.
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, offset_s, self._shift)
        self.DeclareVectorOutputPort("command_reversals", BasicVector(1), self._calc,
                                     prerequisites_of_calc={self.discrete_state_ticket(window)})

    def _shift(self, context, discrete_state) -> None:
        rates = context.get_discrete_state_vector().value()
        discrete_state.set_value(np.append(rates[1:], self._command_port.Eval(context)[1]))

    def _calc(self, context, output) -> None:
        output.SetAtIndex(0, count_reversals(context.get_discrete_state_vector().value()))
