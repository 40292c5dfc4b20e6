"""How often a perceived crossing side agrees with the oracle's: an evaluation instrument."""

import math

import numpy as np
from pydrake.common.value import Value
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem

from ditch_drake.spec import robot
from ditch_drake.systems.edge_angle_driver import EdgeAngleDriverConfig
from ditch_drake.world.crossing import crossing_side_step
from ditch_drake.world.terrain import DitchTerrain

_EXPERT = EdgeAngleDriverConfig()

# Layout of the state: the oracle's held side, then the counters and the disagreements' span.
_HELD, _ZONE_STEPS, _AGREEING, _UNSEEN, _NEAREST_M, _FARTHEST_M = range(6)


class CrossingSideAgreement(LeafSystem):
    """Counts the control steps in the approach zone and those where a side told to the
    controller equals `OracleCrossingSide`'s (same rule, same approach margin and convention).

    The approach zone is the oracle's: from the step the chassis first comes within
    `approach_margin_m` of the hinge line on. It reads the analytic ditch, as the episode
    monitor and the halt counter do: it measures and drives nothing, so a controller that
    is told a perceived side stays unprivileged.

    .. pydrake_system::

        name: CrossingSideAgreement
        input_ports:
        - crossing_side
        - body_poses

    Ports:
        crossing_side: the side the controller is told ([+1], [-1], or [0] for none yet).
        body_poses: the plant's body poses X_WB (vector of RigidTransform).
    """

    def __init__(self, terrain: DitchTerrain, goal_xy, chassis_body_index,
                 approach_margin_m: float = _EXPERT.approach_margin_m,
                 straight_across_deg: float = _EXPERT.straight_across_deg,
                 period_s: float = robot.CONTROL_PERIOD_S, offset_s: float = 0.0):
        super().__init__()
        self._terrain = terrain
        self._goal_xy = np.asarray(goal_xy, dtype=float)[:2]
        self._chassis_index = int(chassis_body_index)
        self._approach_margin_m = float(approach_margin_m)
        self._straight_across_deg = float(straight_across_deg)
        self._side_port = self.DeclareVectorInputPort("crossing_side", 1)
        self._poses_port = self.DeclareAbstractInputPort("body_poses", Value([RigidTransform()]))
        self._state_index = self.DeclareDiscreteState(np.array([0.0, 0.0, 0.0, 0.0, math.inf, -math.inf]))
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, offset_s, self._count)

    def summary(self, context) -> dict:
        """This system's counts in `context`, as `RolloutRecord`'s side_* fields:
        `side_zone_steps`, `side_agreeing_steps`, `side_unseen_steps` (zone steps told no side),
        and `side_disagreement_edge_m`, the nearest and farthest distance to the hinge line (m,
        negative inside it) of a disagreeing step ([] if none)."""
        state = context.get_discrete_state(self._state_index).get_value()
        disagreed = state[_ZONE_STEPS] > state[_AGREEING]
        return {"side_zone_steps": int(state[_ZONE_STEPS]), "side_agreeing_steps": int(state[_AGREEING]),
                "side_unseen_steps": int(state[_UNSEEN]),
                "side_disagreement_edge_m": [float(state[_NEAREST_M]), float(state[_FARTHEST_M])] if disagreed else []}

    def _count(self, context, discrete_state) -> None:
        state = context.get_discrete_state(self._state_index).get_value().copy()
        xy = self._poses_port.Eval(context)[self._chassis_index].translation()[:2]
        oracle, state[_HELD] = crossing_side_step(self._terrain, xy, self._goal_xy, state[_HELD],
                                                  self._approach_margin_m, self._straight_across_deg)
        if state[_HELD] != 0.0:
            told = float(self._side_port.Eval(context)[0])
            state[_ZONE_STEPS] += 1
            if told == oracle:
                state[_AGREEING] += 1
            else:
                state[_UNSEEN] += told == 0.0
                edge_m = float(self._terrain.distance_and_away(xy)[0]) - self._terrain.hinge_distance_m
                state[_NEAREST_M] = min(state[_NEAREST_M], edge_m)
                state[_FARTHEST_M] = max(state[_FARTHEST_M], edge_m)
        discrete_state.set_value(self._state_index, state)
