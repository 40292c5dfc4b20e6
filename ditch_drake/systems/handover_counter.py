"""Handover counter: how much of a rollout the shared controller's fallback drove, and where it took over."""

import math

import numpy as np
from pydrake.common.value import Value
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem

from ditch_drake.spec import robot
from ditch_drake.world.regions import REGIONS, ditch_region
from ditch_drake.world.terrain import DitchTerrain

# Layout of the counts: control steps seen, steps the fallback drove, the driver of the last
# step seen (0 policy, 1 fallback, as `SharedControl.who_drives`), handovers named so far.
_STEPS, _FALLBACK_STEPS, _LAST_DRIVER, _HANDOVERS = range(4)
_FALLBACK = 1.0


def handover_capacity(time_limit_s: float, period_s: float = robot.CONTROL_PERIOD_S) -> int:
    """The most handovers an episode of `time_limit_s` can hold: each one after the first needs a
    step of the fallback's and a step of the policy's before it (+ 1 for the monitor's backstop)."""
    return math.ceil(time_limit_s / period_s / 2) + 2


class HandoverCounter(LeafSystem):
    """Counts the control steps the shared controller's fallback drove and names the region of the
    ditch (`ditch_drake.world.regions`) where each handover to it began.

    At each tick from the second on (t_k = k * period_s, k >= 1) it samples `who_drives`: the
    gate's decision of the control step before, which held from that step's gate tick until this
    one's. So each of the gate's decisions is counted once, at the monitor's tick (offset 0), an
    event time the simulator already stops at, which leaves every other system's results
    unchanged. A step whose driver is the fallback after one whose driver was the policy (or
    the first step) began a handover: its region is that of the chassis at this tick, one
    control period after the gate's decision.

    It reads the analytic ditch, as the episode monitor and the halt counter do: it measures
    and drives nothing.

    .. pydrake_system::

        name: HandoverCounter
        input_ports:
        - who_drives
        - body_poses

    Ports:
        who_drives: [0] the policy drove, [1] the fallback (`SharedControl`'s output).
        body_poses: the plant's body poses X_WB (vector of RigidTransform).
    """

    def __init__(self, terrain: DitchTerrain, start_xy, chassis_body_index, max_handovers: int,
                 period_s: float = robot.CONTROL_PERIOD_S):
        """
        Args:
            terrain: the ditch the regions are measured against.
            start_xy: the task's start (m): its side of the course is the approach side.
            chassis_body_index: the chassis body's index in the plant's body poses.
            max_handovers: how many handovers' regions it keeps (`handover_capacity` of the
                episode: all of them); later ones are counted in the steps, not named.
            period_s: the sampling period (s): the control period.
        """
        super().__init__()
        self._terrain = terrain
        self._start_xy = (float(start_xy[0]), float(start_xy[1]))
        self._chassis_index = int(chassis_body_index)
        self._period_s = float(period_s)
        self._driver_port = self.DeclareVectorInputPort("who_drives", 1)
        self._poses_port = self.DeclareAbstractInputPort("body_poses", Value([RigidTransform()]))
        self._counts_index = self.DeclareDiscreteState(np.array([0.0, 0.0, 0.0, 0.0]))
        self._regions_index = self.DeclareDiscreteState(np.full(int(max_handovers), -1.0))
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, 0.0, self._count)

    def _count(self, context, discrete_state) -> None:
        # The tick at t = 0 comes before the gate's first decision.
        if context.get_time() < 0.5 * self._period_s:
            return
        counts = context.get_discrete_state(self._counts_index).get_value().tolist()
        driver = float(self._driver_port.Eval(context)[0])
        if driver == _FALLBACK:
            counts[_FALLBACK_STEPS] += 1
            if counts[_LAST_DRIVER] != _FALLBACK:
                regions = context.get_discrete_state(self._regions_index).get_value()
                handover = int(counts[_HANDOVERS])
                if handover < regions.size:
                    p_WB = self._poses_port.Eval(context)[self._chassis_index].translation()
                    regions = regions.copy()
                    regions[handover] = REGIONS.index(ditch_region(self._terrain, self._start_xy, p_WB[:2]))
                    discrete_state.set_value(self._regions_index, regions)
                    counts[_HANDOVERS] += 1
        counts[_STEPS] += 1
        counts[_LAST_DRIVER] = driver
        discrete_state.set_value(self._counts_index, counts)

    def summary(self, context) -> dict:
        """This system's counts in `context`, as `RolloutRecord`'s fields: `handover_fraction`
        (the share of the counted control steps the fallback drove; 0 before any) and
        `handover_regions` (the region where each handover began, in order)."""
        counts = context.get_discrete_state(self._counts_index).get_value()
        regions = context.get_discrete_state(self._regions_index).get_value()
        steps = counts[_STEPS]
        return {"handover_fraction": float(counts[_FALLBACK_STEPS] / steps) if steps else 0.0,
                "handover_regions": [REGIONS[int(index)] for index in regions[:int(counts[_HANDOVERS])]]}
