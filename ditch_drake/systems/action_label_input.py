"""An action label from outside the diagram (a Gymnasium agent), executed from the action table."""

import numpy as np
from pydrake.common.value import Value
from pydrake.systems.framework import BasicVector, LeafSystem

from ditch_drake.spec import actions

# The `action` port's value for no action: stand still, label -1. (None also means none where
# pydrake's Value[object] holds None: 1.51's pybind11 bindings do, 1.58's nanobind ones refuse it.)
NO_ACTION = -1


class ActionLabelInput(LeafSystem):
    """Commands the [v, w] of the action label on its input: the learned policy's action path
    with the network outside the diagram.

    The command is the label's row of the action table (`ditch_drake.spec.actions.COMMANDS`,
    the table every shipped checkpoint carries), as the `LearnedPolicy` block commands its
    chosen label's. The block keeps no state and declares no event: an agent sets `action`
    between two `AdvanceTo` calls, at the control ticks where the policy block would update
    (`ditch_drake.gym`), and Drake's cache recomputes the outputs only when the input
    changes, not at every physics step that pulls `command`. With no action on `action`
    (`NO_ACTION`, -1; or None where Drake takes it), the command is [0, 0] (stand still) and
    the label -1, as the policy's before its first update.

    .. pydrake_system::

        name: ActionLabelInput
        input_ports:
        - action
        output_ports:
        - command
        - label

    Ports:
        action: an integer label in 0..16 (any Python or numpy integer), or `NO_ACTION`; abstract-valued.
        command: [v m/s, w rad/s] of the label.
        label: [the label] as a float, -1 for no action.
    """

    def __init__(self):
        super().__init__()
        self._action_port = self.DeclareAbstractInputPort("action", Value[object](NO_ACTION))
        prerequisites = {self._action_port.ticket()}
        self.DeclareVectorOutputPort("command", 2, self._calc_command, prerequisites_of_calc=prerequisites)
        self.DeclareVectorOutputPort("label", 1, self._calc_label, prerequisites_of_calc=prerequisites)

    def _label(self, context) -> int | None:
        label = self._action_port.Eval(context) if self._action_port.HasValue(context) else None
        no_action = label is None or (isinstance(label, (int, np.integer)) and label == NO_ACTION)
        return None if no_action else label

    def _calc_command(self, context, output: BasicVector) -> None:
        label = self._label(context)
        # `label_to_command` refuses anything but an integer in 0..16, naming it.
        output.SetFromVector(np.zeros(2) if label is None else actions.label_to_command(label))

    def _calc_label(self, context, output: BasicVector) -> None:
        label = self._label(context)
        output.SetFromVector([-1.0 if label is None else float(label)])
