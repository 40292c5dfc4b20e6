"""The crossing side toward a moving target: the side a window search's way in and out turns to."""

import math

import numpy as np
from pydrake.common.value import Value
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector, LeafSystem

from ditch_drake.common.errors import ConfigError
from ditch_drake.world.crossing import approach_side


class TargetCrossingSide(LeafSystem):
    """The expert's side rule (`approach_side`) on the edge `PerceivedCrossingSide` found, toward
    a target instead of the goal.

    `PerceivedCrossingSide` holds the side toward the goal from the approach zone on. Where a
    `WindowSearch` leads the robot along the edge to a way in and out, the side to cross on is
    the one toward its target, and it changes where the search turns back; so this block reads
    the perceived edge (the direction across it away from the ditch, as last estimated) and
    applies the rule to the target at every read, holding nothing. Before the edge is seen the
    side is 0, as the perceived block's. The rule's dead zone near square on (+1 by convention
    within `straight_across_deg`) is the expert's.

    .. pydrake_system::

        name: TargetCrossingSide
        input_ports:
        - edge
        - target_xy
        - body_poses
        output_ports:
        - crossing_side

    Ports:
        edge: `PerceivedCrossingSide`'s [seen (0/1), distance (m), away_x, away_y].
        target_xy: the planar point (m, W) the controller drives toward (`WindowSearch`'s).
        body_poses: the plant's body poses X_WB (vector of RigidTransform).
        crossing_side: [+1] to cross turned right along the edge (facing the ditch), [-1] left,
            [0] before the edge is seen.
    """

    def __init__(self, chassis_body_index, straight_across_deg: float):
        """Raises:
            ConfigError: `straight_across_deg` outside [0, 90).
        """
        super().__init__()
        if not 0 <= straight_across_deg < 90:
            raise ConfigError(f"target crossing side straight_across_deg={straight_across_deg!r}: expected [0, 90)")
        self._chassis_index = int(chassis_body_index)
        self._straight_across_deg = float(straight_across_deg)
        self._edge_port = self.DeclareVectorInputPort("edge", 4)
        self._target_port = self.DeclareVectorInputPort("target_xy", 2)
        self._poses_port = self.DeclareAbstractInputPort("body_poses", Value([RigidTransform()]))
        self.DeclareVectorOutputPort("crossing_side", BasicVector(1), self._calc_side,
                                     {self.input_port_ticket(port.get_index())
                                      for port in (self._edge_port, self._target_port, self._poses_port)})

    def _calc_side(self, context, output) -> None:
        seen, _, away_x, away_y = self._edge_port.Eval(context)
        if seen == 0.0 or not (math.isfinite(away_x) and math.isfinite(away_y)):
            output.SetAtIndex(0, 0.0)
            return
        away = np.array([away_x, away_y])
        xy = self._poses_port.Eval(context)[self._chassis_index].translation()[:2]
        to_target = np.asarray(self._target_port.Eval(context), dtype=float) - xy
        output.SetAtIndex(0, approach_side(to_target, -away, np.array([-away[1], away[0]]), self._straight_across_deg))
