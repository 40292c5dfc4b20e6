"""How long, and how far, the robot has come no nearer its goal: watchdogs for a policy that has
lost its way.

On the paper's ditches the retrained clones' failures that no tip or uncertainty signal
foresees come after the crossing: the robot, past the ditch, drives on past the goal or circles
near it until the time limit, or off the field. Those are failures of progress, not of
attitude, and they read off the pose and the goal alone (no map, nothing privileged): the
seconds since the distance to the goal last fell by `PROGRESS_STEP_M` below where the last
such fall left it. Driving at the policy's speed toward the goal keeps it under a few tenths
of a second; driving along the ditch before the climb lets it grow for a while; past the goal,
or circling, it grows until the robot is nearer the goal than ever before.

The same anchor gives a second count, in metres: the most the distance has risen above the
anchor since it was set. A robot that drives away from its goal at 1 m/s takes 20 s to pass a
20 s limit and is 20 m off by then, at the field's edge on sine; the metres pass a limit of a
few metres in a few seconds. Like the seconds, they fall back to 0 only with progress.
"""

import math
from typing import NamedTuple

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from ditch_drake.spec import robot
from ditch_drake.spec.observation_layout import DISTANCE_STACK_SIZE
from ditch_drake.spec.schedule import CONTROLLER_OFFSET_S, RECORDER_OFFSET_S, gate_signal_offset_s

# A quarter of a metre: at the policy's 1 m/s, progress is seen every third control step, and a
# robot that circles or rocks in place is not taken for one that progresses.
PROGRESS_STEP_M = 0.25


class Progress(NamedTuple):
    """The watchdogs' state after a control step (`progress_step`).

    Attributes:
        anchor_m: the distance to the goal where progress was last seen (inf before the first step).
        stalled_s: the seconds since then.
        regressed_m: the most the distance has risen above the anchor since then (>= 0).
    """

    anchor_m: float = math.inf
    stalled_s: float = 0.0
    regressed_m: float = 0.0


def progress_step(state: Progress, distance_m: float, period_s: float) -> Progress:
    """One control step of the watchdogs, from `state` and this step's distance to the goal.

    A distance `PROGRESS_STEP_M` or more below the anchor is progress: it becomes the anchor
    and both counts restart at 0. Otherwise the seconds grow by `period_s` and the metres are
    the larger of theirs and how far the distance now lies above the anchor. The first step
    only sets the anchor.
    """
    if math.isinf(state.anchor_m) or distance_m <= state.anchor_m - PROGRESS_STEP_M:
        return Progress(distance_m)
    return Progress(state.anchor_m, state.stalled_s + period_s,
                    max(state.regressed_m, distance_m - state.anchor_m))


class GoalProgress(LeafSystem):
    """Counts the seconds since the robot last came `PROGRESS_STEP_M` nearer its goal, and the
    most it has fallen back since then (module doc).

    It reads the distance the policy saw this step (the newest entry of the frame stacker's
    `distance_stack`) at its tick, `offset_s` into each control period: after the stacker's and
    the controllers' ticks, before the shared-control gate reads the counts. The anchor and the
    counts are discrete state, so the outputs hold between ticks and `gate-signals`
    (`SignalWatch`), running `progress_step` over the same distances, records the values the gate
    reads. Before the first tick both counts are 0.

    .. pydrake_system::

        name: GoalProgress
        input_ports:
        - distance_stack
        output_ports:
        - seconds_without_progress
        - metres_regressed

    Ports:
        distance_stack: [distance to the goal (m)] x stack depth, newest first (`FrameStacker`).
        seconds_without_progress: [s] since the distance last fell by `PROGRESS_STEP_M`.
        metres_regressed: [m] the most the distance has risen above where it last fell, since then.
    """

    def __init__(self, period_s: float = robot.CONTROL_PERIOD_S,
                 offset_s: float = gate_signal_offset_s(CONTROLLER_OFFSET_S, RECORDER_OFFSET_S)):
        super().__init__()
        self._period_s = period_s
        self._distance_port = self.DeclareVectorInputPort("distance_stack", DISTANCE_STACK_SIZE)
        state = self.DeclareDiscreteState(np.array(Progress()))
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, offset_s, self._update)
        for name, field in (("seconds_without_progress", "stalled_s"), ("metres_regressed", "regressed_m")):
            self.DeclareVectorOutputPort(name, BasicVector(1), self._state_entry(Progress._fields.index(field)),
                                         prerequisites_of_calc={self.discrete_state_ticket(state)})

    @staticmethod
    def _state_entry(index: int):
        """An output's calc that copies entry `index` of the state (`Progress`'s fields)."""
        def calc(context, output) -> None:
            output.SetAtIndex(0, context.get_discrete_state_vector().value()[index])
        return calc

    def _update(self, context, discrete_state) -> None:
        state = Progress(*context.get_discrete_state_vector().value())
        distance_m = float(self._distance_port.Eval(context)[0])
        discrete_state.set_value(np.array(progress_step(state, distance_m, self._period_s)))
