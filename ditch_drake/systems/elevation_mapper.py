"""The rolling elevation map fused from the lidar, as a block of its own (the `mppi` baseline's map)."""

import numpy as np
from pydrake.common.value import Value
from pydrake.math import RigidTransform
from pydrake.perception import PointCloud
from pydrake.systems.framework import BasicVector, LeafSystem

from ditch_drake.perception.lidar_points import returns_in_world, within_chassis_in_plan
from ditch_drake.planning.elevation_map import ElevationGrid, ElevationMapConfig
from ditch_drake.spec import robot
from ditch_drake.spec.planar import planar_yaw

# Points within this of the chassis box in plan belong to the robot (m).
SELF_MARGIN_M = 0.05


def fuse_scan(grid: ElevationGrid, heights: np.ndarray, window: np.ndarray | None, X_WB: RigidTransform,
              points_W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One control step of the map: `heights` rolled from `window` (the previous step's origin
    cells; None: no window yet) to the robot's at `X_WB`, the returns `points_W` (N, 3) fused in,
    and the still unknown cells under the robot filled with the plane of its wheels (which the
    lidar never sees). Returns (heights, the new window's origin cells)."""
    pose = np.array([*X_WB.translation()[:2], planar_yaw(X_WB)])
    origin = grid.window_origin(pose[:2])
    if window is not None:
        heights = grid.roll(heights, window, origin)
    if len(points_W):
        heights = grid.fuse(heights, origin, points_W)
    z_W = X_WB.rotation().matrix()[:, 2]
    half = [robot.WHEELBASE_M / 2 + robot.WHEEL_RADIUS_M, robot.TRACK_M / 2 + 0.05]
    heights = grid.fill_footprint(heights, origin, pose, half, X_WB.translation() - robot.WHEEL_RADIUS_M * z_W, z_W)
    return heights, origin


# Layout of the window state.
_WX, _WY, _WINDOW_VALID = range(3)


class ElevationMapper(LeafSystem):
    """The `mppi` baseline's rolling elevation map, for a controller that has none of its own.

    Every control period one periodic discrete update rolls the map's window to the robot,
    fuses the lidar's returns (less those within the chassis box in plan: the robot itself)
    into it and fills the unknown cells under the wheels (`fuse_scan`, the step `MppiController`
    takes). The map and its window live in the discrete state; the output reads them.

    .. pydrake_system::

        name: ElevationMapper
        input_ports:
        - point_cloud
        - body_poses
        output_ports:
        - elevation_map

    Ports:
        point_cloud: a `pydrake.perception.PointCloud` in the lidar frame L (no return: non-finite).
        body_poses: the plant's body poses X_WB (vector of RigidTransform).
        elevation_map: [origin_x (m), origin_y (m), h_0, ..., h_{n-1}]: heights (m, NaN unknown) of
            `grid.shape` row-major, as `MppiController`'s output of that name.
    """

    def __init__(self, chassis_body_index, X_BL: RigidTransform, config: ElevationMapConfig | None = None,
                 period_s: float = robot.CONTROL_PERIOD_S, offset_s: float = 0.0):
        """Raises:
            ConfigError: a map value out of range (naming the key).
        """
        super().__init__()
        self._grid = ElevationGrid(config)
        self._chassis_index = int(chassis_body_index)
        self._X_BL = X_BL
        self._on_robot_B = within_chassis_in_plan(SELF_MARGIN_M)
        self._cloud_port = self.DeclareAbstractInputPort("point_cloud", Value(PointCloud()))
        self._poses_port = self.DeclareAbstractInputPort("body_poses", Value([RigidTransform()]))
        self._map_index = self.DeclareDiscreteState(self._grid.empty().reshape(-1))
        self._window_index = self.DeclareDiscreteState(np.zeros(3))
        self.DeclareVectorOutputPort(
            "elevation_map", BasicVector(2 + self._grid.size), self._calc_map,
            prerequisites_of_calc={self.discrete_state_ticket(self._map_index),
                                   self.discrete_state_ticket(self._window_index)})
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, offset_s, self._update)

    @property
    def grid(self) -> ElevationGrid:
        """The map's geometry (cell side, shape)."""
        return self._grid

    def _calc_map(self, context, output) -> None:
        window = context.get_discrete_state(self._window_index).get_value()
        origin_m = self._grid.origin_m(window[_WX:_WY + 1]) if window[_WINDOW_VALID] else np.zeros(2)
        output.SetFromVector(self._grid.pack(origin_m, context.get_discrete_state(self._map_index).get_value()))

    def _update(self, context, discrete_state) -> None:
        X_WB = self._poses_port.Eval(context)[self._chassis_index]
        window = context.get_discrete_state(self._window_index).get_value()
        heights = context.get_discrete_state(self._map_index).get_value().reshape(self._grid.shape)
        points_W = returns_in_world(self._cloud_port.Eval(context), self._X_BL, X_WB, self._on_robot_B)[0]
        heights, origin = fuse_scan(self._grid, heights, window[_WX:_WY + 1].astype(int) if window[_WINDOW_VALID]
                                    else None, X_WB, points_W)
        discrete_state.set_value(self._map_index, heights.reshape(-1))
        discrete_state.set_value(self._window_index, np.array([*origin, 1.0]))
