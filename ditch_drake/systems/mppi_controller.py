"""The rollover-aware MPPI baseline as a Drake block: elevation map, attitude prediction, MPPI."""

import enum

import numpy as np
from pydrake.common.value import Value
from pydrake.math import RigidTransform
from pydrake.perception import PointCloud
from pydrake.systems.framework import BasicVector, LeafSystem

from ditch_drake.common.errors import ConfigError
from ditch_drake.perception.lidar_points import returns_in_world, within_chassis_in_plan
from ditch_drake.planning.elevation_map import ElevationGrid, ElevationMapConfig
from ditch_drake.planning.mppi import MppiPlanner, MppiPlannerConfig
from ditch_drake.spec import robot
from ditch_drake.spec.planar import planar_yaw
from ditch_drake.systems.elevation_mapper import SELF_MARGIN_M, fuse_scan


class MppiMode(enum.IntEnum):
    """What the last update did (the `status` output's first value)."""

    DRIVING = 0  # An admissible command sequence was chosen.
    GOAL_REACHED = 1  # Within the goal tolerance: stopped for good.
    HALTED = 2  # No sampled sequence kept the tip margins: stopped.
    NO_DATA = 3  # No return in the cloud yet, or none at all this step: stopped.
    FALLBACK = 4  # No sample kept the tip margins: the least-bad one is driven (stopping on a wall fails too).


# Layout of the bookkeeping state.
_MODE, _UPDATES, _HALTS, _NO_DATA, _GOAL_REACHED, _WX, _WY, _WINDOW_VALID, _LAST_W, _FALLBACKS = range(10)
_STATUS_SIZE = 10
_STATUS_OUTPUT = (_MODE, _UPDATES, _HALTS, _NO_DATA)


class MppiController(LeafSystem):
    """MPPI on an elevation map fused from the lidar: drives to a goal keeping a margin to tipping.

    Every control period one periodic discrete update rolls the elevation map's window to the
    robot, fuses the cloud into it (`ditch_drake.planning.elevation_map`), fills the still
    unknown cells under the robot with the plane of its wheels, and runs one MPPI update
    (`ditch_drake.planning.mppi`) warm-started from the stored nominal sequence, with a random
    generator seeded by (planner seed, update count), so a run repeats exactly. Its command is the
    first step quantized to the action labels. While no sample is admissible it drives the least
    bad one (the planner's `fallback`; with it off, it stops). It commands [0, 0] within the goal
    tolerance (for good), and while the cloud holds no return (empty, all NaN):
    the map then keeps what it had. The map, its window, the nominal sequence, the command and
    the counters live in the discrete state; the outputs read it. Points within the chassis
    box in plan (the robot itself) are dropped.

    .. pydrake_system::

        name: MppiController
        input_ports:
        - point_cloud
        - body_poses
        - target_xy (optional)
        output_ports:
        - command
        - elevation_map
        - status

    Ports:
        point_cloud: a `pydrake.perception.PointCloud` in the lidar frame L (no return: non-finite).
        body_poses: the plant's body poses X_WB (vector of RigidTransform).
        target_xy: (only with `target_input`) the planar point (m, W) to drive toward instead of
            the goal: a route-level target such as `WindowSearch`'s.
        command: [v (m/s), w (rad/s)], zero until the first update.
        elevation_map: [origin_x (m), origin_y (m), h_0, ..., h_{n-1}]: heights (m, NaN unknown) of
            `map_shape` row-major; see `unpack_map`.
        status: [mode (`MppiMode`), updates, halts, no_data].
    """

    def __init__(self, goal_xy, chassis_body_index, X_BL: RigidTransform, planner: MppiPlannerConfig | None = None,
                 elevation_map: ElevationMapConfig | None = None, goal_tolerance_m: float = 1.0,
                 period_s: float = robot.CONTROL_PERIOD_S, offset_s: float = 0.0, target_input: bool = False):
        """Declares the ports, the state and the periodic update; with `target_input`, a `target_xy`
        input that the planner drives toward in place of the goal (the goal still ends the run).

        Raises:
            ConfigError: a planner, map or goal tolerance value out of range (naming the key).
        """
        super().__init__()
        if not goal_tolerance_m >= 0.0:
            raise ConfigError(f"mppi goal_tolerance_m={goal_tolerance_m!r}: expected >= 0")
        self._planner = MppiPlanner(planner)
        self._grid = ElevationGrid(elevation_map)
        self._goal_xy = np.asarray(goal_xy, dtype=float)[:2]
        self._goal_tolerance_m = float(goal_tolerance_m)
        self._chassis_index = int(chassis_body_index)
        self._X_BL = X_BL
        self._on_robot_B = within_chassis_in_plan(SELF_MARGIN_M)
        self._cloud_port = self.DeclareAbstractInputPort("point_cloud", Value(PointCloud()))
        self._poses_port = self.DeclareAbstractInputPort("body_poses", Value([RigidTransform()]))
        self._target_port = self.DeclareVectorInputPort("target_xy", 2) if target_input else None
        self._command_index = self.DeclareDiscreteState(2)
        self._map_index = self.DeclareDiscreteState(self._grid.empty().reshape(-1))
        self._nominal_index = self.DeclareDiscreteState(self._planner.initial_nominal())
        status = np.zeros(_STATUS_SIZE)
        status[_MODE] = MppiMode.NO_DATA
        self._status_index = self.DeclareDiscreteState(status)
        self.DeclareStateOutputPort("command", self._command_index)
        self.DeclareVectorOutputPort(
            "elevation_map", BasicVector(2 + self._grid.size), self._calc_map,
            prerequisites_of_calc={self.discrete_state_ticket(self._map_index),
                                   self.discrete_state_ticket(self._status_index)})
        self.DeclareVectorOutputPort("status", BasicVector(len(_STATUS_OUTPUT)), self._calc_status,
                                     prerequisites_of_calc={self.discrete_state_ticket(self._status_index)})
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, offset_s, self._update)

    @property
    def grid(self) -> ElevationGrid:
        """The map's geometry (cell side, shape)."""
        return self._grid

    @property
    def planner(self) -> MppiPlanner:
        return self._planner

    def unpack_map(self, value: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(origin xy (m), heights (ny, nx)) from an `elevation_map` output value."""
        return self._grid.unpack(value)

    def cloud_in_world(self, cloud: PointCloud, X_WB: RigidTransform) -> np.ndarray:
        """The cloud's returns (N, 3) in W as this block fuses them: less those within the chassis
        box in plan (the robot itself)."""
        return returns_in_world(cloud, self._X_BL, X_WB, self._on_robot_B)[0]

    def planner_status(self, context) -> dict[str, int]:
        """Counters of this system's `context`: mode, updates, halts, no_data, goal_reached, fallbacks."""
        status = context.get_discrete_state(self._status_index).get_value()
        return {"mode": int(status[_MODE]), "updates": int(status[_UPDATES]), "halts": int(status[_HALTS]),
                "no_data": int(status[_NO_DATA]), "goal_reached": int(status[_GOAL_REACHED]),
                "fallbacks": int(status[_FALLBACKS])}

    def _calc_map(self, context, output) -> None:
        status = context.get_discrete_state(self._status_index).get_value()
        origin_m = self._grid.origin_m(status[_WX:_WY + 1]) if status[_WINDOW_VALID] else np.zeros(2)
        output.SetFromVector(self._grid.pack(origin_m, context.get_discrete_state(self._map_index).get_value()))

    def _calc_status(self, context, output) -> None:
        output.SetFromVector(context.get_discrete_state(self._status_index).get_value()[list(_STATUS_OUTPUT)])

    def _update(self, context, discrete_state) -> None:
        grid = self._grid
        X_WB = self._poses_port.Eval(context)[self._chassis_index]
        pose = np.array([*X_WB.translation()[:2], planar_yaw(X_WB)])
        status = context.get_discrete_state(self._status_index).get_value().copy()
        heights = context.get_discrete_state(self._map_index).get_value().reshape(grid.shape)
        nominal = context.get_discrete_state(self._nominal_index).get_value().copy()
        points_W = self.cloud_in_world(self._cloud_port.Eval(context), X_WB)
        window = status[_WX:_WY + 1].astype(int) if status[_WINDOW_VALID] else None
        heights, origin = fuse_scan(grid, heights, window, X_WB, points_W)
        status[_WX:_WINDOW_VALID + 1] = [*origin, 1.0]
        command = np.zeros(2)
        update = int(status[_UPDATES])
        status[_UPDATES] += 1
        if status[_GOAL_REACHED] or np.linalg.norm(self._goal_xy - pose[:2]) <= self._goal_tolerance_m:
            status[_GOAL_REACHED], status[_MODE] = 1.0, MppiMode.GOAL_REACHED
        elif len(points_W) == 0:
            status[_NO_DATA] += 1
            status[_MODE] = MppiMode.NO_DATA
        else:
            rng = np.random.default_rng([self._planner.config.seed, update])
            target_xy = self._goal_xy if self._target_port is None else self._target_port.Eval(context)
            result = self._planner.plan(grid, heights, origin, pose, target_xy, nominal, status[_LAST_W], rng)
            nominal = result.next_nominal
            if result.admissible:
                command = result.command
                status[_MODE] = MppiMode.DRIVING
            elif result.fallback:
                command = result.command
                status[_FALLBACKS] += 1
                status[_MODE] = MppiMode.FALLBACK
            else:
                status[_HALTS] += 1
                status[_MODE] = MppiMode.HALTED
        status[_LAST_W] = command[1]
        discrete_state.set_value(self._command_index, command)
        discrete_state.set_value(self._map_index, heights.reshape(-1))
        discrete_state.set_value(self._nominal_index, nominal)
        discrete_state.set_value(self._status_index, status)
