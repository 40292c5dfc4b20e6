"""A person's steering through meshcat: keyboard arrows or a gamepad stick."""

import numpy as np
from pydrake.geometry import Meshcat
from pydrake.systems.framework import LeafSystem

from ditch_drake.spec import actions, robot, schedule

TURN_LEFT = "Turn left (ArrowLeft)"
TURN_RIGHT = "Turn right (ArrowRight)"
STRAIGHT = "Straight (ArrowUp)"
# One key press changes the yaw rate by one action label's step.
RATE_STEP_RADPS = 0.1


def steer(previous_w: float, left_presses: int, right_presses: int, straight_presses: int,
          stick_x: float | None) -> float:
    """The yaw rate (rad/s) after the presses since the last step, or from the gamepad stick.

    A gamepad stick, when present, sets the rate directly (full right = -0.85 rad/s);
    otherwise each arrow press turns one step further and the up arrow straightens.
    """
    limit = robot.MAX_ANGULAR_RATE_RADPS
    if stick_x is not None:
        return float(np.clip(-stick_x * limit, -limit, limit))
    w = 0.0 if straight_presses > 0 else previous_w
    w += RATE_STEP_RADPS * (left_presses - right_presses)
    return float(np.clip(w, -limit, limit))


class MeshcatTeleop(LeafSystem):
    """Reads a person's steering from the meshcat page at the control rate.

    Adds three buttons to the meshcat controls, bound to the arrow keys (press with
    the meshcat tab focused), and reads a gamepad's left stick when the browser
    reports one (press a gamepad button in the meshcat tab to opt in). Speed is
    always `actions.SPEED_MPS`, as in the paper's demonstrations. Connect
    `raw_command` to an `ActionQuantizer`, which snaps it to a label, like the
    scripted expert.

    .. pydrake_system::

        name: MeshcatTeleop
        output_ports:
        - raw_command

    Ports:
        raw_command: [v (m/s), w (rad/s)], updated at the control rate.
    """

    def __init__(self, meshcat: Meshcat, period_s: float = robot.CONTROL_PERIOD_S,
                 offset_s: float = schedule.CONTROLLER_OFFSET_S):
        super().__init__()
        self._meshcat = meshcat
        for name, key in ((TURN_LEFT, "ArrowLeft"), (TURN_RIGHT, "ArrowRight"), (STRAIGHT, "ArrowUp")):
            meshcat.AddButton(name, key)
        self._command_index = self.DeclareDiscreteState(np.array([actions.SPEED_MPS, 0.0]))
        # Button clicks seen so far: [left, right, straight].
        self._clicks_index = self.DeclareDiscreteState(3)
        self.DeclareStateOutputPort("raw_command", self._command_index)
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, offset_s, self._update)

    def _update(self, context, discrete_state) -> None:
        seen = context.get_discrete_state(self._clicks_index).get_value()
        clicks = np.array([self._meshcat.GetButtonClicks(name) for name in (TURN_LEFT, TURN_RIGHT, STRAIGHT)],
                          dtype=float)
        presses = np.maximum(clicks - seen, 0).astype(int)
        gamepad = self._meshcat.GetGamepad()
        stick_x = float(gamepad.axes[0]) if gamepad.index is not None and len(gamepad.axes) > 0 else None
        previous_w = context.get_discrete_state(self._command_index).get_value()[1]
        w = steer(previous_w, *presses, stick_x)
        discrete_state.set_value(self._command_index, [actions.SPEED_MPS, w])
        discrete_state.set_value(self._clicks_index, clicks)
