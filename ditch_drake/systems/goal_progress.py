"""How long the robot has come no nearer its goal: a watchdog for a policy that has lost its way.

On the paper's ditches the retrained clones' failures that no tip or uncertainty signal
foresees come after the crossing: the robot, past the ditch, drives on past the goal or circles
near it until the time limit, or off the field. Those are failures of progress, not of
attitude, and they read off the pose and the goal alone (no map, nothing privileged): the
seconds since the distance to the goal last fell by `PROGRESS_STEP_M` below where the last
such fall left it. Driving at the policy's speed toward the goal keeps it under a few tenths
of a second; driving along the ditch before the climb lets it grow for a while; past the goal,
or circling, it grows until the robot is nearer the goal than ever before.
"""

import math

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from ditch_drake.spec import robot
from ditch_drake.spec.observation_layout import DISTANCE_STACK_SIZE
from ditch_drake.spec.schedule import CONTROLLER_OFFSET_S, RECORDER_OFFSET_S, gate_signal_offset_s

# A quarter of a metre: at the policy's 1 m/s, progress is seen every third control step, and a
# robot that circles or rocks in place is not taken for one that progresses.
PROGRESS_STEP_M = 0.25


def progress_step(anchor_m: float, stalled_s: float, distance_m: float, period_s: float) -> tuple[float, float]:
    """One control step of the watchdog: (the new anchor (m), the seconds without progress).

    The anchor is the distance where progress was last seen (inf before the first step). A
    distance `PROGRESS_STEP_M` or more below it is progress: it becomes the anchor and the
    count restarts at 0; otherwise the count grows by `period_s`. The first step only sets the
    anchor.
    """
    if math.isinf(anchor_m):
        return distance_m, 0.0
    if distance_m <= anchor_m - PROGRESS_STEP_M:
        return distance_m, 0.0
    return anchor_m, stalled_s + period_s


class GoalProgress(LeafSystem):
    """Counts the seconds since the robot last came `PROGRESS_STEP_M` nearer its goal (module doc).

    It reads the distance the policy saw this step (the newest entry of the frame stacker's
    `distance_stack`) at its tick, `offset_s` into each control period: after the stacker's and
    the controllers' ticks, before the shared-control gate reads `seconds_without_progress`. The
    anchor and the count are discrete state, so the output holds between ticks and `gate-signals`
    (`SignalWatch`), running `progress_step` over the same distances, records the values the gate
    reads. Before the first tick the count is 0.

    .. pydrake_system::

        name: GoalProgress
        input_ports:
        - distance_stack
        output_ports:
        - seconds_without_progress

    Ports:
        distance_stack: [distance to the goal (m)] x stack depth, newest first (`FrameStacker`).
        seconds_without_progress: [s] since the distance last fell by `PROGRESS_STEP_M`.
    """

    def __init__(self, period_s: float = robot.CONTROL_PERIOD_S,
                 offset_s: float = gate_signal_offset_s(CONTROLLER_OFFSET_S, RECORDER_OFFSET_S)):
        super().__init__()
        self._period_s = period_s
        self._distance_port = self.DeclareVectorInputPort("distance_stack", DISTANCE_STACK_SIZE)
        state = self.DeclareDiscreteState(np.array([math.inf, 0.0]))  # [anchor m, seconds without progress].
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, offset_s, self._update)
        self.DeclareVectorOutputPort("seconds_without_progress", BasicVector(1), self._calc,
                                     prerequisites_of_calc={self.discrete_state_ticket(state)})

    def _update(self, context, discrete_state) -> None:
        anchor_m, stalled_s = context.get_discrete_state_vector().value()
        distance_m = float(self._distance_port.Eval(context)[0])
        discrete_state.set_value(np.array(progress_step(anchor_m, stalled_s, distance_m, self._period_s)))

    def _calc(self, context, output) -> None:
        output.SetAtIndex(0, context.get_discrete_state_vector().value()[1])
