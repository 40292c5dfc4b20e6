"""Skid-steer drive: a (v, w) body command to wheel speed targets, and a fixed command's source."""

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem, NumericParameterIndex

from ditch_drake.spec import robot

# How many commands' wheel speeds a drive keeps (`SkidSteerDrive._calc_desired_state`).
_KEPT_COMMANDS = 64


def effective_track_m(w_radps: float) -> float:
    """The track (m) that the kinematic map uses for a commanded yaw rate.

    Skid-steering loses yaw rate to lateral wheel scrub, more at low rates, so the
    map widens the track by a factor interpolated in `robot.SKID_STEER_TRACK_FACTORS`
    (measured on flat ground by `ditch-drake calibrate`, docs/concepts/physics.md).
    """
    rates, factors = robot.SKID_STEER_TRACK_FACTORS
    return robot.TRACK_M * float(np.interp(abs(w_radps), rates, factors))


def wheel_speeds_radps(command: np.ndarray, wheel_is_left: np.ndarray) -> np.ndarray:
    """Wheel speeds (rad/s) for command [v m/s, w rad/s]; a left turn slows the left side."""
    v, w = float(command[0]), float(command[1])
    half_track = effective_track_m(w) / 2
    sides = np.where(wheel_is_left, -1.0, 1.0)
    return (v + sides * w * half_track) / robot.WHEEL_RADIUS_M


class SkidSteerDrive(LeafSystem):
    """Turns a body command into desired wheel states for the plant's wheel PD.

    The wheels are velocity-controlled by the plant's own PD actuators (p = 0,
    d = `robot.WHEEL_SPEED_GAIN_NMS`, torque limited to `robot.WHEEL_TORQUE_LIMIT_NM`),
    so this block only maps kinematics. Its output depends on the command alone,
    so Drake's cache recomputes it only when the command changes (at the control
    rate), not at every physics step that pulls it.

    .. pydrake_system::

        name: SkidSteerDrive
        input_ports:
        - command
        output_ports:
        - wheel_desired_state

    Ports:
        command: [v (m/s, forward), w (rad/s, counter-clockwise seen from above)].
        wheel_desired_state: [q_d (rad) x n, v_d (rad/s) x n] for the n wheel
            actuators, in the plant's actuator order; q_d is zero (unused at p = 0).
    """

    def __init__(self, wheel_is_left: list[bool]):
        """Args:
            wheel_is_left: for each wheel actuator, in the plant's actuator order,
                whether it is on the left side.
        """
        super().__init__()
        self._wheel_is_left = np.asarray(wheel_is_left, dtype=bool)
        count = len(self._wheel_is_left)
        self._command_port = self.DeclareVectorInputPort("command", 2)
        self._desired_by_command: dict[bytes, np.ndarray] = {}
        self.DeclareVectorOutputPort(
            "wheel_desired_state", 2 * count, self._calc_desired_state,
            prerequisites_of_calc={self._command_port.ticket()})

    def _calc_desired_state(self, context, output: BasicVector) -> None:
        command = self._command_port.EvalBasicVector(context).value()
        # The commands are few (17 action labels for the learned policy), and the map costs
        # more than a lookup: its results are kept by the command's exact bits.
        key = command.tobytes()
        desired = self._desired_by_command.get(key)
        if desired is None:
            if not np.all(np.isfinite(command)):
                raise ValueError(f"command {command} must be finite [v m/s, w rad/s]")
            speeds = wheel_speeds_radps(command, self._wheel_is_left)
            desired = np.concatenate([np.zeros_like(speeds), speeds])
            if len(self._desired_by_command) >= _KEPT_COMMANDS:  # A continuous controller's commands.
                self._desired_by_command.clear()
            self._desired_by_command[key] = desired
        output.SetFromVector(desired)


class ConstantCommand(LeafSystem):
    """A fixed command, as `ConstantVectorSource` gives it, whose output depends on the command alone.

    `ConstantVectorSource`'s output depends, for Drake's cache, on the time as well, so a
    `SkidSteerDrive` fed by one recomputes its wheel targets at every physics step; fed by this
    source it computes them once, and again only when the command is changed.

    .. pydrake_system::

        name: ConstantCommand
        output_ports:
        - command

    Ports:
        command: [v (m/s), w (rad/s)]: the value of the block's numeric parameter.
    """

    def __init__(self, command):
        """Args:
            command: [v (m/s), w (rad/s)], the parameter's default value.

        Raises:
            ValueError: `command` is not two numbers.
        """
        super().__init__()
        command = np.asarray(command, dtype=float)
        if command.shape != (2,):
            raise ValueError(f"command {command.tolist()} must be [v m/s, w rad/s]")
        self._index = self.DeclareNumericParameter(BasicVector(command))
        self.DeclareVectorOutputPort(
            "command", 2, self._calc_command,
            prerequisites_of_calc={self.numeric_parameter_ticket(NumericParameterIndex(self._index))})

    def get_source_value(self, context) -> BasicVector:
        """The command in `context` (as `ConstantVectorSource.get_source_value`)."""
        return context.get_numeric_parameter(self._index)

    def get_mutable_source_value(self, context) -> BasicVector:
        """The command in `context`, to change it (as `ConstantVectorSource.get_mutable_source_value`)."""
        return context.get_mutable_numeric_parameter(self._index)

    def _calc_command(self, context, output: BasicVector) -> None:
        output.SetFrom(context.get_numeric_parameter(self._index))
