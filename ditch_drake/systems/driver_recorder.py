"""Driver recorder: who drove each control step of a shared rollout, and where the chassis was."""

from dataclasses import dataclass

import numpy as np
from pydrake.common.value import AbstractValue, Value
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem

from ditch_drake.spec import robot, schedule
from ditch_drake.systems.demo_recorder import DemoLog


@dataclass(frozen=True)
class DriverStep:
    """One control step: its time (s), its driver (0 the policy, 1 the fallback, as
    `SharedControl.who_drives`) and the chassis position p_WB (m)."""

    time_s: float
    driver: int
    p_WB: tuple[float, float, float]


class DriverLog(DemoLog):
    """An append-only, immutable sequence of `DriverStep`s, copied by reference as `DemoLog` is."""

    __slots__ = ()

    def appended(self, step: DriverStep) -> "DriverLog":
        return DriverLog(self.steps + (step,))

    def drivers(self) -> np.ndarray:
        """(T,) int8: each step's driver."""
        return np.array([step.driver for step in self.steps], dtype=np.int8)

    def positions(self) -> np.ndarray:
        """(T, 3) float64: each step's chassis position p_WB (m)."""
        return np.array([step.p_WB for step in self.steps], dtype=np.float64).reshape(-1, 3)


class DriverRecorder(LeafSystem):
    """Records, at every control step, who drives and where the chassis is.

    At the demonstration recorder's offset (`schedule.RECORDER_OFFSET_S`, the default) it ticks
    after the shared controller's gate has decided this step's driver, so its step k and
    `DemoRecorder`'s step k are the same control step: a demonstration's `intervention` flag is
    `driver == 1`. At offset 0 (the replay) it ticks at a time the simulator stops at anyway,
    so it changes no other system's results: its entry k (k >= 1) holds the driver of control
    step k - 1 and where the chassis was when that step ended (entry 0: the start, before the
    gate's first decision), so the path from entry k - 1 to entry k was driven by entry k's
    driver. Read the result with `log(context)`.

    .. pydrake_system::

        name: DriverRecorder
        input_ports:
        - who_drives
        - body_poses

    Ports:
        who_drives: [0] the policy drives, [1] the fallback (`SharedControl`'s output).
        body_poses: the plant's body poses X_WB (vector of RigidTransform).
    """

    def __init__(self, chassis_body_index, period_s: float = robot.CONTROL_PERIOD_S,
                 offset_s: float = schedule.RECORDER_OFFSET_S):
        super().__init__()
        self._chassis_index = int(chassis_body_index)
        self._driver_port = self.DeclareVectorInputPort("who_drives", 1)
        self._poses_port = self.DeclareAbstractInputPort("body_poses", Value([RigidTransform()]))
        self._log_index = self.DeclareAbstractState(AbstractValue.Make(DriverLog()))
        self.DeclarePeriodicUnrestrictedUpdateEvent(period_s, offset_s, self._record)

    def _record(self, context, state) -> None:
        p_WB = self._poses_port.Eval(context)[self._chassis_index].translation()
        step = DriverStep(time_s=context.get_time(), driver=round(float(self._driver_port.Eval(context)[0])),
                          p_WB=(float(p_WB[0]), float(p_WB[1]), float(p_WB[2])))
        log = context.get_abstract_state(self._log_index).get_value()
        state.get_mutable_abstract_state(self._log_index).set_value(log.appended(step))

    def log(self, context) -> DriverLog:
        """The steps recorded so far in this system's `context`."""
        return context.get_abstract_state(self._log_index).get_value()
