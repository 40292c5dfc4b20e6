"""Which side along the edge to cross on, read from the analytic ditch: the oracle a side-conditioned
clone can be told instead of `PerceivedCrossingSide` (privileged: no sensor gives it)."""

import numpy as np
from pydrake.common.value import Value
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector, LeafSystem

from ditch_drake.spec import robot
from ditch_drake.systems.edge_angle_driver import EdgeAngleDriverConfig
from ditch_drake.world.crossing import crossing_side_step
from ditch_drake.world.terrain import DitchTerrain

# Where the expert commits to a side, and its convention near square on, by default.
_EXPERT = EdgeAngleDriverConfig()


class OracleCrossingSide(LeafSystem):
    """The side along the edge the expert's rule would cross on, from the ditch's analytic course.

    Until the robot first enters the approach zone (within `approach_margin_m` of the hinge
    line) the output is the expert's rule at the current pose; from then on, the side it had
    there, as the expert commits to its side (`ditch_drake.world.crossing.crossing_side_step`). A clone trained
    with every crossing reflected to one side (`ModelConfig.canonical_side`) is told this
    side, as a route planner tells a driving policy which way to turn at a junction. It reads
    the ditch's course and the true pose, which no sensor gives: an oracle, for the ablation
    against `PerceivedCrossingSide`, which finds the edge in the lidar's rays. Offline,
    `ditch_drake.world.crossing.crossing_sides` gives the same sides along a recorded path.

    .. pydrake_system::

        name: OracleCrossingSide
        input_ports:
        - body_poses
        output_ports:
        - crossing_side

    Ports:
        body_poses: the plant's body poses X_WB (vector of RigidTransform).
        crossing_side: [+1] to cross turned right along the edge (facing the ditch), [-1] left.
    """

    def __init__(self, terrain: DitchTerrain, goal_xy, chassis_body_index,
                 approach_margin_m: float = _EXPERT.approach_margin_m,
                 straight_across_deg: float = _EXPERT.straight_across_deg,
                 period_s: float = robot.CONTROL_PERIOD_S, offset_s: float = 0.0):
        super().__init__()
        self._terrain = terrain
        self._goal_xy = np.asarray(goal_xy, dtype=float)
        self._chassis_index = int(chassis_body_index)
        self._approach_margin_m = float(approach_margin_m)
        self._straight_across_deg = float(straight_across_deg)
        self._poses_port = self.DeclareAbstractInputPort("body_poses", Value([RigidTransform()]))
        # [side held (0 until the robot enters the approach zone)].
        self._held_index = self.DeclareDiscreteState(1)
        self.DeclareVectorOutputPort("crossing_side", BasicVector(1), self._calc_side,
                                     {self.xd_ticket(), self._poses_port.ticket()})
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, offset_s, self._hold)

    def _step(self, context) -> tuple[float, float]:
        return crossing_side_step(
            self._terrain, self._poses_port.Eval(context)[self._chassis_index].translation()[:2], self._goal_xy,
            context.get_discrete_state(self._held_index).GetAtIndex(0), self._approach_margin_m,
            self._straight_across_deg)

    def _calc_side(self, context, output) -> None:
        output.SetAtIndex(0, self._step(context)[0])

    def _hold(self, context, discrete_state) -> None:
        discrete_state.set_value(self._held_index, [self._step(context)[1]])
