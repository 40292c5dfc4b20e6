"""How near the robot is to tipping, now and along the arc it is commanded: a risk signal for a gate.

The members' disagreement says how unsure a clone is of a view; it does not say whether being
wrong there matters. The tip margin does: `tip_risk_now` is the margin of the chassis as it
stands, and `tip_risk_ahead` the least margin that the `mppi` baseline's attitude model
(`ditch_drake.planning.attitude`) predicts on the perceived elevation map along the arc the
robot is commanded, held for `horizon_s`. Both are minus the margin in degrees, so that, as for
the uncertainty signals, higher is worse: -60 on flat ground, 0 at the tipping point.
"""

import math
from dataclasses import dataclass

import numpy as np
from pydrake.common.value import Value
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector, LeafSystem

from ditch_drake.common.errors import ConfigError
from ditch_drake.planning.attitude import predict_attitude
from ditch_drake.planning.elevation_map import ElevationGrid
from ditch_drake.planning.mppi import MppiPlanner, rollout
from ditch_drake.spec import robot
from ditch_drake.spec.planar import planar_yaw
from ditch_drake.systems.episode_monitor import stability_margins_rad


@dataclass
class TipRiskConfig:
    """The arc along which `TipRisk` predicts the margin.

    Attributes:
        horizon_s: how long the commanded (v, w) is held (s); the arc is cut in control periods.
        presume_drops: judge the arc on the map the `mppi` baseline plans on: unknown cells next
            to known ones presumed to fall away as a ditch wall would (its planner's defaults,
            `MppiPlannerConfig.presumed_drop_*`); False: unknown cells are left out.
    """

    horizon_s: float = 2.0
    presume_drops: bool = True

    def validate(self) -> None:
        if not (math.isfinite(self.horizon_s) and self.horizon_s >= robot.CONTROL_PERIOD_S):
            raise ConfigError(f"tip_risk horizon_s={self.horizon_s!r}: expected at least one control period "
                              f"({robot.CONTROL_PERIOD_S} s)")


def arc_margins_rad(grid: ElevationGrid, heights: np.ndarray, origin_m: np.ndarray, pose: np.ndarray,
                    v: float, w: float, horizon_s: float, planner: MppiPlanner | None = None) -> np.ndarray:
    """Predicted stability margins (rad) at the poses of (v, w) held from `pose` (x, y, yaw) for
    `horizon_s`, the pose itself first; NaN where the map does not know enough wheels. With
    `planner`, on the map it plans on (`MppiPlanner.planning_heights`: presumed drops)."""
    origin = np.round(np.asarray(origin_m) / grid.resolution).astype(int)
    if planner is not None:
        heights = planner.planning_heights(grid, heights, origin, pose)
    steps = max(1, round(horizon_s / robot.CONTROL_PERIOD_S))
    poses = rollout(np.asarray(pose, dtype=float), np.full((1, steps), float(w)), float(v), robot.CONTROL_PERIOD_S)[0]
    return predict_attitude(grid, heights, origin, poses).margin


class TipRisk(LeafSystem):
    """Minus the tip margin, now and along the commanded arc (module doc), each computed when read.

    .. pydrake_system::

        name: TipRisk
        input_ports:
        - elevation_map
        - body_poses
        - command
        output_ports:
        - tip_risk_now
        - tip_risk_ahead

    Ports:
        elevation_map: [origin_x (m), origin_y (m), heights (m, NaN unknown) row-major] of `grid`,
            as `ElevationMapper` gives it.
        body_poses: the plant's body poses X_WB (vector of RigidTransform).
        command: [v m/s, w rad/s], the command the arc holds.
        tip_risk_now: [deg] minus the static stability margin of the chassis's attitude.
        tip_risk_ahead: [deg] minus the least margin predicted along the arc (the current pose's
            margin where the map knows no pose of it).
    """

    def __init__(self, chassis_body_index, grid: ElevationGrid, config: TipRiskConfig | None = None):
        """Raises:
            ConfigError: a horizon shorter than a control period.
        """
        super().__init__()
        self._config = config or TipRiskConfig()
        self._config.validate()
        self._planner = MppiPlanner() if self._config.presume_drops else None
        self._grid = grid
        self._chassis_index = int(chassis_body_index)
        self._map_port = self.DeclareVectorInputPort("elevation_map", 2 + grid.size)
        self._poses_port = self.DeclareAbstractInputPort("body_poses", Value([RigidTransform()]))
        self._command_port = self.DeclareVectorInputPort("command", 2)
        self.DeclareVectorOutputPort("tip_risk_now", BasicVector(1), self._calc_now,
                                     prerequisites_of_calc={self._poses_port.ticket()})
        self.DeclareVectorOutputPort("tip_risk_ahead", BasicVector(1), self._calc_ahead)

    def _margin_now_rad(self, context) -> float:
        return min(stability_margins_rad(self._poses_port.Eval(context)[self._chassis_index].rotation().matrix()))

    def _calc_now(self, context, output) -> None:
        output.SetAtIndex(0, -math.degrees(self._margin_now_rad(context)))

    def _calc_ahead(self, context, output) -> None:
        X_WB = self._poses_port.Eval(context)[self._chassis_index]
        origin_m, heights = self._grid.unpack(self._map_port.Eval(context))
        v, w = self._command_port.Eval(context)
        pose = np.array([*X_WB.translation()[:2], planar_yaw(X_WB)])
        margins = arc_margins_rad(self._grid, heights, origin_m, pose, v, w, self._config.horizon_s, self._planner)
        ahead_rad = float(np.nanmin(margins)) if np.isfinite(margins).any() else self._margin_now_rad(context)
        output.SetAtIndex(0, -math.degrees(ahead_rad))
