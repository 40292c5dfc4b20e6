"""Frame stacker: the last few observations of every input, newest first."""

import functools

from pydrake.systems.framework import BasicVector, DiscreteValues, LeafSystem

from ditch_drake.spec import robot
from ditch_drake.spec.observation_layout import (
    BEARING_SIZE,
    DISTANCE_SIZE,
    IMAGE_PIXELS,
    IMU_SIZE,
    STACK_DEPTH,
)


class FrameStacker(LeafSystem):
    """Stacks the last `depth` control steps of the observation, newest first.

    Each stack is a discrete state vector of `depth` blocks of its input's size,
    block 0 newest; all start as zeros (docs/design.md, "The observation"). A periodic discrete update
    every `period_s` (at times t_k = k * period_s, k = 0, 1, ...) shifts every stack
    one block toward the old end, dropping the oldest, and writes the inputs into
    block 0. The same update is declared as a forced discrete update, so
    `CalcForcedDiscreteVariableUpdate` pushes one step too.

    What a stack holds (Drake's event semantics: all discrete updates at one time
    read the state from before any of them): the update at t_k reads each input as
    it evaluates at t_k before the updates at t_k. For a direct-feedthrough source
    of the body poses (`Imu`, `GoalSensor`) that is the pose at t_k (the discrete
    plant's state at t_k, before its own step); for a source whose output is its
    own state updated at the same ticks it is the value that source computed at
    t_{k-1} (its initial value at t_0). The normal-image converter is a function of
    the lidar's cloud (state), so the image is that of the cloud the lidar holds at
    t_k: in `AddObservation` the lidar ticks earlier in the same control step
    (`ditch_drake.spec.schedule`), so it is this control step's cloud. The outputs
    read the state, so between t_k and t_{k+1} they hold the entries pushed at
    t_k, t_{k-1}, t_{k-2}, t_{k-3}; a controller updating at t_k itself sees the
    stacks as pushed at t_{k-1}. (`Simulator.AdvanceTo(t)` handles an event at
    exactly t only on the next call.)

    Layouts (see `ditch_drake.spec.observation_layout`): `image_stack` is channel-major
    (depth, rows, cols), channel 0 newest, each channel the input image's row-major
    pixels; `imu_stack` is [roll_t, pitch_t, roll_t-1, pitch_t-1, ...];
    `distance_stack` and `bearing_stack` are [value_t, value_t-1, ...].

    .. pydrake_system::

        name: FrameStacker
        input_ports:
        - normal_image
        - roll_pitch
        - distance
        - bearing
        output_ports:
        - image_stack
        - imu_stack
        - distance_stack
        - bearing_stack

    Ports:
        normal_image: the surface-normal image, IMAGE_SIZE * IMAGE_SIZE row-major.
        roll_pitch: [roll (rad), pitch (rad)].
        distance: [distance to the goal (m)].
        bearing: [bearing to the goal (rad)].
        image_stack: depth * IMAGE_SIZE * IMAGE_SIZE, channel 0 newest.
        imu_stack: 2 * depth (rad), newest first.
        distance_stack: depth (m), newest first.
        bearing_stack: depth (rad), newest first.
    """

    def __init__(self, period_s: float = robot.CONTROL_PERIOD_S, depth: int = STACK_DEPTH, offset_s: float = 0.0):
        """Args:
            period_s: the control period (s) at which a step is pushed.
            offset_s: time of the first push (s); see `ditch_drake.spec.schedule`.
            depth: how many steps each stack holds.
        """
        super().__init__()
        if depth < 1:
            raise ValueError(f"depth={depth} must be >= 1")
        self._depth = int(depth)
        # (input port, discrete state index, block size) per stacked input.
        self._channels = []
        for input_name, output_name, size in (
            ("normal_image", "image_stack", IMAGE_PIXELS),
            ("roll_pitch", "imu_stack", IMU_SIZE),
            ("distance", "distance_stack", DISTANCE_SIZE),
            ("bearing", "bearing_stack", BEARING_SIZE),
        ):
            port = self.DeclareVectorInputPort(input_name, size)
            index = self.DeclareDiscreteState(self._depth * size)
            # Not `DeclareStateOutputPort`: its copy of the 65,536-value image stack took
            # 145 us in drake 1.51.1 (a temporary vector on the way), this one 10 us.
            self.DeclareVectorOutputPort(output_name, self._depth * size, functools.partial(self._copy_stack, index),
                                         prerequisites_of_calc={self.discrete_state_ticket(index)})
            self._channels.append((port, index, size))
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, offset_s, self._push)
        self.DeclareForcedDiscreteUpdateEvent(self._push)

    @property
    def depth(self) -> int:
        """How many steps each stack holds."""
        return self._depth

    @staticmethod
    def _copy_stack(index: int, context, output: BasicVector) -> None:
        output.get_mutable_value()[:] = context.get_discrete_state(index).get_value()

    def _push(self, context, discrete_state: DiscreteValues) -> None:
        # `discrete_state` starts as a copy of the current state; shift it in place.
        for port, index, size in self._channels:
            stack = discrete_state.get_mutable_value(index)
            stack[size:] = stack[:-size]  # numpy copies overlapping slices correctly.
            # A read-only view of the input's value: `Eval` would copy it first.
            stack[:size] = port.EvalBasicVector(context).value()
