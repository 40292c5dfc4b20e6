"""Halt counter: how often the controller stopped, and where relative to the ditch."""

import numpy as np
from pydrake.common.value import Value
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem

from ditch_drake.spec import robot
from ditch_drake.world.regions import REGIONS, ditch_region
from ditch_drake.world.terrain import DitchTerrain

# Layout of the run state: the current run's time below the speed (s), and 1 once it is counted.
_RUN_S, _COUNTED = range(2)
# Sums of control periods compare with the minimum up to rounding.
_TIME_TOLERANCE_S = 1e-9


class HaltCounter(LeafSystem):
    """Counts the controller's halts per region of the ditch (`ditch_drake.world.regions`).

    A halt is a maximal run of control ticks whose commanded speed |v| is below
    `halt_speed_mps`, lasting `min_halt_s` or more: the paper's move_base stopping to
    replan. It is counted once, in the region where the chassis is at the tick the run
    reaches `min_halt_s`, so a stop that turns into a slide down the backslope counts
    where the robot stopped, not where it ended up.

    The command is sampled at each tick and held for a period: the controllers update
    at the control rate, so a stop of n periods is n samples and lasts n periods.
    Sampling at a tick where other systems update too (the episode monitor's, offset 0)
    leaves every other system's results unchanged: the simulator already stops there.

    .. pydrake_system::

        name: HaltCounter
        input_ports:
        - command
        - body_poses
        output_ports:
        - halts_by_region

    Ports:
        command: [v m/s, w rad/s], the command that drives the robot.
        body_poses: the plant's body poses X_WB (vector of RigidTransform).
        halts_by_region: halts counted so far per region, in `REGIONS` order.
    """

    def __init__(self, terrain: DitchTerrain, start_xy, chassis_body_index,
                 period_s: float = robot.CONTROL_PERIOD_S, offset_s: float = 0.0,
                 halt_speed_mps: float = 0.05, min_halt_s: float = 0.5):
        """
        Args:
            terrain: the ditch the regions are measured against.
            start_xy: the task's start (m): its side of the course is the approach side.
            chassis_body_index: the chassis body's index in the plant's body poses.
            period_s: the sampling period (s): the control period.
            offset_s: the sampling offset within the period (s).
            halt_speed_mps: a command with |v| below this (m/s) is a stop.
            min_halt_s: a stop lasting this long (s) or more is a halt.
        """
        super().__init__()
        self._terrain = terrain
        self._start_xy = (float(start_xy[0]), float(start_xy[1]))
        self._chassis_index = int(chassis_body_index)
        self._period_s = float(period_s)
        self._halt_speed_mps = float(halt_speed_mps)
        self._min_halt_s = float(min_halt_s)
        self._command_port = self.DeclareVectorInputPort("command", 2)
        self._poses_port = self.DeclareAbstractInputPort("body_poses", Value([RigidTransform()]))
        self._run_index = self.DeclareDiscreteState(2)
        self._counts_index = self.DeclareDiscreteState(len(REGIONS))
        self._counts_port = self.DeclareStateOutputPort("halts_by_region", self._counts_index)
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, offset_s, self._update)

    def _update(self, context, discrete_state):
        # Plain floats: this runs every control step of every rollout.
        run = context.get_discrete_state(self._run_index).get_value().tolist()
        speed = abs(float(self._command_port.Eval(context)[0]))
        if speed < self._halt_speed_mps:
            run[_RUN_S] += self._period_s
        else:
            run[_RUN_S], run[_COUNTED] = 0.0, 0.0
        if not run[_COUNTED] and run[_RUN_S] >= self._min_halt_s - _TIME_TOLERANCE_S:
            # The pose is read only here, once per halt, not at every tick.
            p_WB = self._poses_port.Eval(context)[self._chassis_index].translation()
            region = ditch_region(self._terrain, self._start_xy, p_WB[:2])
            counts = context.get_discrete_state(self._counts_index).get_value().copy()
            counts[REGIONS.index(region)] += 1.0
            discrete_state.set_value(self._counts_index, counts)
            run[_COUNTED] = 1.0
        discrete_state.set_value(self._run_index, run)

    def halts_by_region(self, context) -> dict[str, int]:
        """The halts counted so far, by region name (all of `REGIONS`), from this system's context."""
        counts = self._counts_port.Eval(context)
        return {region: round(float(count)) for region, count in zip(REGIONS, np.asarray(counts), strict=True)}
