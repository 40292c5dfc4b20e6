"""Teleop input: any raw (v, w) command, snapped to the 17-label action space."""

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from ditch_drake.spec import actions


class ActionQuantizer(LeafSystem):
    """Snaps a raw command to the nearest action label; the snapped command drives the robot.

    This is the paper's teleop path (3.5): the expert's raw command becomes the
    label with the nearest angular rate, and that label's command is both what the
    robot executes and what a demonstration records. Any source plugs into
    `raw_command`: the scripted expert, a person at a keyboard or gamepad through
    meshcat, or a test's fixed value.

    The outputs depend on `raw_command` alone, so Drake's cache recomputes them only
    when the raw command changes (the sources update at the control rate), not at
    every physics step that pulls `command`.

    .. pydrake_system::

        name: ActionQuantizer
        input_ports:
        - raw_command
        output_ports:
        - command
        - label

    Ports:
        raw_command: [v (m/s), w (rad/s)], any finite values.
        command: the label's [v (m/s), w (rad/s)] (`actions.COMMANDS`).
        label: [label] in 0..16, as a float.
    """

    def __init__(self):
        super().__init__()
        self._raw_port = self.DeclareVectorInputPort("raw_command", 2)
        prerequisites = {self._raw_port.ticket()}
        self.DeclareVectorOutputPort("command", 2, self._calc_command, prerequisites_of_calc=prerequisites)
        self.DeclareVectorOutputPort("label", 1, self._calc_label, prerequisites_of_calc=prerequisites)

    def _label(self, context) -> int:
        return actions.quantize(self._raw_port.Eval(context))

    def _calc_command(self, context, output: BasicVector) -> None:
        output.SetFromVector(actions.COMMANDS[self._label(context)])

    def _calc_label(self, context, output: BasicVector) -> None:
        output.SetFromVector(np.array([float(self._label(context))]))
