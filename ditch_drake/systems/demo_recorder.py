"""Demonstration recorder: the observation and the executed label, every control step."""

from dataclasses import dataclass

import numpy as np
from pydrake.common.value import AbstractValue, Value
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.systems.framework import LeafSystem

from ditch_drake.spec import robot, schedule
from ditch_drake.spec.observation_layout import (
    BEARING_STACK_SIZE,
    DISTANCE_STACK_SIZE,
    IMAGE_PIXELS,
    IMAGE_SHAPE,
    IMAGE_STACK_SIZE,
    IMU_STACK_SIZE,
)


@dataclass(frozen=True)
class RecordedStep:
    """One control step. The image is the stack's newest channel, as uint8 (round(255 v))."""

    time_s: float
    image: np.ndarray  # (128, 128) uint8, read-only
    imu_stack: np.ndarray  # (8,) rad
    distance_stack: np.ndarray  # (4,) m
    bearing_stack: np.ndarray  # (4,) rad
    label: int
    raw_command: np.ndarray  # (2,) [v m/s, w rad/s]
    pose: np.ndarray  # (6,) [x, y, z m, roll, pitch, yaw rad]


class DemoLog:
    """An append-only, immutable sequence of `RecordedStep`s.

    Drake deep-copies abstract state on every unrestricted update; because a log
    never changes once made (appending makes a new log sharing the old steps),
    copying it can return the same object, so recording stays O(1) per step.
    """

    __slots__ = ("_steps",)

    def __init__(self, steps: tuple[RecordedStep, ...] = ()):
        self._steps = steps

    def appended(self, step: RecordedStep) -> "DemoLog":
        return DemoLog(self._steps + (step,))

    @property
    def steps(self) -> tuple[RecordedStep, ...]:
        return self._steps

    def __len__(self) -> int:
        return len(self._steps)

    def __copy__(self) -> "DemoLog":
        return self

    def __deepcopy__(self, memo) -> "DemoLog":
        return self


def _frozen(values, dtype=np.float32) -> np.ndarray:
    array = np.array(values, dtype=dtype)
    array.setflags(write=False)
    return array


class DemoRecorder(LeafSystem):
    """Records (observation, executed label) pairs into its Context at the control rate.

    Runs after the frame stacker and the controller within each control step
    (`schedule.RECORDER_OFFSET_S`), so each step pairs the stacks a policy would
    have seen with the label the robot then executed, plus time, pose and the raw
    command for analysis. Read the result with `log(context)`.

    Only the image stack's newest channel is kept per step: the older channels are
    the previous steps' newest channels (zeros before the first), which
    `ditch_drake.demos.dataset` restacks on loading.

    .. pydrake_system::

        name: DemoRecorder
        input_ports:
        - image_stack
        - imu_stack
        - distance_stack
        - bearing_stack
        - label
        - raw_command
        - body_poses

    Ports:
        image_stack, imu_stack, distance_stack, bearing_stack: the frame stacker's outputs.
        label: the executed action label (1-vector).
        raw_command: the command before quantization, [v m/s, w rad/s].
        body_poses: the plant's body poses X_WB (vector of RigidTransform).
    """

    def __init__(self, chassis_body_index, period_s: float = robot.CONTROL_PERIOD_S,
                 offset_s: float = schedule.RECORDER_OFFSET_S):
        super().__init__()
        self._chassis_index = int(chassis_body_index)
        self._image_port = self.DeclareVectorInputPort("image_stack", IMAGE_STACK_SIZE)
        self._imu_port = self.DeclareVectorInputPort("imu_stack", IMU_STACK_SIZE)
        self._distance_port = self.DeclareVectorInputPort("distance_stack", DISTANCE_STACK_SIZE)
        self._bearing_port = self.DeclareVectorInputPort("bearing_stack", BEARING_STACK_SIZE)
        self._label_port = self.DeclareVectorInputPort("label", 1)
        self._raw_command_port = self.DeclareVectorInputPort("raw_command", 2)
        self._poses_port = self.DeclareAbstractInputPort("body_poses", Value([RigidTransform()]))
        self._log_index = self.DeclareAbstractState(AbstractValue.Make(DemoLog()))
        self.DeclarePeriodicUnrestrictedUpdateEvent(period_s, offset_s, self._record)

    def _record(self, context, state) -> None:
        newest = np.asarray(self._image_port.Eval(context)[:IMAGE_PIXELS]).reshape(IMAGE_SHAPE)
        X_WB = self._poses_port.Eval(context)[self._chassis_index]
        rpy = RollPitchYaw(X_WB.rotation()).vector()
        step = RecordedStep(
            time_s=context.get_time(),
            image=_frozen(np.rint(np.clip(newest, 0.0, 1.0) * 255.0), np.uint8),
            imu_stack=_frozen(self._imu_port.Eval(context)),
            distance_stack=_frozen(self._distance_port.Eval(context)),
            bearing_stack=_frozen(self._bearing_port.Eval(context)),
            label=round(float(self._label_port.Eval(context)[0])),
            raw_command=_frozen(self._raw_command_port.Eval(context)),
            pose=_frozen([*X_WB.translation(), *rpy]),
        )
        log = context.get_abstract_state(self._log_index).get_value()
        state.get_mutable_abstract_state(self._log_index).set_value(log.appended(step))

    def log(self, context) -> DemoLog:
        """The steps recorded so far in this system's `context`."""
        return context.get_abstract_state(self._log_index).get_value()
