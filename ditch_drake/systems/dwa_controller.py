"""The move_base baseline (paper 4.2): slope costmap, Dijkstra global planner, DWA local planner."""

import enum
import math
from dataclasses import dataclass, field

import numpy as np
from pydrake.common.value import Value
from pydrake.math import RigidTransform
from pydrake.perception import PointCloud
from pydrake.systems.framework import BasicVector, LeafSystem

from ditch_drake.perception.lidar_points import open_rays_B, returns_in_world
from ditch_drake.planning.costmap import CostmapConfig, SlopeCostmap
from ditch_drake.planning.dwa import (
    DwaPlannerConfig,
    find_best_trajectory,
    footprint_outline,
    update_oscillation_flags,
)
from ditch_drake.planning.global_planner import GlobalPlannerConfig, plan
from ditch_drake.spec import robot
from ditch_drake.spec.planar import planar_yaw, wrap_to_pi


@dataclass
class DwaConfig:
    """move_base with a slope costmap, Dijkstra global planner and DWA local planner.

    Attributes:
        planner_frequency: global replanning rate (Hz); 0 plans only when there is no
            plan or the local planner failed (move_base's semantics).
        planner_patience: how long (s) the global planner may keep failing before the
            robot stops and a recovery runs; meanwhile the last plan is followed.
        controller_patience: how long (s) the local planner may keep failing (the robot
            stopped, replanning every step) before a recovery runs. move_base's default
            is 15 s; 5 s lets a recovery happen within the episode's 10 s stuck window.
        recovery_behavior_enabled: run the recovery (move_base's conservative_reset:
            forget the costmap outside a square of side `conservative_reset_dist`).
        conservative_reset_dist: see above (m).
        max_path_points: the plan kept in the Context is subsampled to at most this many points.
        start_clearing_radius: at the first update, the unknown cells within this distance of
            the robot are set FREE: it starts on ground it can stand on, and a 120 deg forward
            lidar never sees beside or behind it (with `local_planner.unknown_is_lethal`, the DWA
            would not move it at all). 0 disables.
        costmap: the slope costmap (costmap_2d's parameters).
        global_planner: Dijkstra's weights (global_planner's parameters).
        local_planner: the DWA (dwa_local_planner's parameters).
    """

    planner_frequency: float = 1.0
    planner_patience: float = 5.0
    controller_patience: float = 5.0
    recovery_behavior_enabled: bool = True
    conservative_reset_dist: float = 3.0
    max_path_points: int = 1000
    start_clearing_radius: float = 1.0
    costmap: CostmapConfig = field(default_factory=CostmapConfig)
    global_planner: GlobalPlannerConfig = field(default_factory=GlobalPlannerConfig)
    local_planner: DwaPlannerConfig = field(default_factory=DwaPlannerConfig)


class DwaMode(enum.IntEnum):
    """What the last update did (the `status` output's first value)."""

    DRIVING = 0  # A trajectory was chosen.
    GOAL_REACHED = 1  # Within xy_goal_tolerance: stopped for good.
    HALTED = 2  # No admissible trajectory: stopped to replan (move_base).
    NO_PLAN = 3  # The global planner found no path and none was kept: stopped.
    NO_DATA = 4  # The cloud held no return at all: stopped, as move_base does when its sensor is not current.


# Layout of the bookkeeping state: window origin (cells), odometry, planner and DWA flags, counters.
(_WX, _WY, _WINDOW_VALID, _ODOM_X, _ODOM_Y, _ODOM_YAW, _ODOM_T, _ODOM_VALID, _LAST_PLAN_T, _REPLAN,
 _PLAN_FAIL_SINCE, _CONTROL_FAIL_SINCE, _OSC0, _OSC1, _OSC2, _OSC3, _STATIONARY_X, _STATIONARY_Y,
 _GOAL_REACHED, _HALTS, _PLANS, _PLAN_FAILURES, _RECOVERIES, _MODE, _NO_DATA) = range(25)
_STATUS_SIZE = 25
_COUNTERS = {"halts": _HALTS, "plans": _PLANS, "plan_failures": _PLAN_FAILURES, "recoveries": _RECOVERIES,
             "goal_reached": _GOAL_REACHED, "no_data": _NO_DATA, "mode": _MODE}
# The `status` output: the mode, then the counters.
_STATUS_OUTPUT = (_MODE, _HALTS, _PLANS, _PLAN_FAILURES, _RECOVERIES, _NO_DATA)


class DwaController(LeafSystem):
    """move_base on the lidar cloud: drives to a goal around steep terrain.

    Every control period one periodic discrete update rolls the costmap window to the
    robot, marks the cloud's slope costs and raytraces it against the level ground under
    the wheels (see `ditch_drake.planning.costmap`), inflates, replans with Dijkstra at
    `planner_frequency` (or at once after the local planner failed; see
    `ditch_drake.planning.global_planner`), and runs the DWA (`ditch_drake.planning.dwa`)
    from the odometry velocity (pose change over the last period). When no trajectory is
    admissible it commands zero and replans at the next step, as move_base stops to
    replan; after `controller_patience` of that it also forgets the costmap beyond
    `conservative_reset_dist` (move_base's first recovery). Within `xy_goal_tolerance` of
    the goal it stops for good. A cloud without a single return (empty or all NaN) stops it
    too, keeping its map, as move_base stops while its sensor is not current; the `status`
    output says which of these it is doing. The observation layer, the costmap, the plan, odometry and
    all flags live in the discrete state; the outputs read it. Points above or below the
    footprint (the robot itself) are dropped.

    .. pydrake_system::

        name: DwaController
        input_ports:
        - point_cloud
        - body_poses
        output_ports:
        - command
        - costmap
        - path_W
        - status

    Ports:
        point_cloud: a `pydrake.perception.PointCloud` in the lidar frame L (points without
            a return non-finite).
        body_poses: the plant's body poses X_WB (vector of RigidTransform).
        command: [v (m/s), w (rad/s)], zero until the first update.
        costmap: [origin_x (m), origin_y (m), cost_0, ..., cost_{n-1}]: the master costmap
            (costmap_2d values, 255 unknown) of `costmap_shape` (ny, nx) row-major, row iy at
            y = origin_y + (iy + 0.5) resolution; see `unpack_costmap`.
        path_W: [count, x_0, y_0, x_1, y_1, ...]: the global plan in W; see `unpack_path`.
        status: [mode (`DwaMode` of the last update), halts, plans, plan_failures, recoveries,
            no_data (updates stopped for a cloud without a single return)].
    """

    def __init__(self, goal_xy, chassis_body_index, X_BL: RigidTransform, config: DwaConfig | None = None,
                 period_s: float = robot.CONTROL_PERIOD_S, offset_s: float = 0.0,
                 ray_directions_L: np.ndarray | None = None):
        """Declares the ports, the state and the periodic update.

        Args:
            goal_xy: the goal (x, y) in W (m).
            chassis_body_index: the BodyIndex of the chassis B in `body_poses`.
            X_BL: the lidar frame L's pose in B.
            config: the planners' parameters; None: `DwaConfig()`.
            period_s: the control period (s); also sizes the DWA's dynamic window.
            offset_s: the first update's time (s); `ditch_drake.spec.schedule.CONTROLLER_OFFSET_S`
                runs it just after the lidar's update in the same control step.
            ray_directions_L: (N, 3) unit directions in L of an organized cloud's rays, when
                `point_cloud` is organized (N points, non-finite where a ray returned nothing
                within range): the rays without a return then also reveal drops (see
                `SlopeCostmap.mark`). NaN rows: rays to ignore (give NaN for the rays outside
                the field of view). Rays that pass through the chassis box are ignored.
                None: the cloud's order carries no meaning.
        """
        super().__init__()
        self._config = config or DwaConfig()
        self._goal_xy = np.asarray(goal_xy, dtype=float)[:2]
        self._chassis_index = int(chassis_body_index)
        self._X_BL = X_BL
        self._period_s = float(period_s)
        self._costmap = SlopeCostmap(self._config.costmap)
        self._outline_B = footprint_outline(self._costmap.footprint, self._costmap.resolution)
        self._rays_B = None if ray_directions_L is None else open_rays_B(np.asarray(ray_directions_L, float), X_BL)
        self._cloud_port = self.DeclareAbstractInputPort("point_cloud", Value(PointCloud()))
        self._poses_port = self.DeclareAbstractInputPort("body_poses", Value([RigidTransform()]))
        self._command_index = self.DeclareDiscreteState(2)
        self._layer_index = self.DeclareDiscreteState(self._costmap.empty_layer().reshape(-1))
        self._costmap_index = self.DeclareDiscreteState(self._costmap.pack(np.zeros(2), self._costmap.empty_layer()))
        self._path_index = self.DeclareDiscreteState(1 + 2 * self._config.max_path_points)
        status = np.zeros(_STATUS_SIZE)
        status[[_LAST_PLAN_T, _PLAN_FAIL_SINCE, _CONTROL_FAIL_SINCE, _STATIONARY_X, _STATIONARY_Y]] = np.nan
        status[_MODE] = DwaMode.NO_DATA  # Nothing seen before the first update.
        self._status_index = self.DeclareDiscreteState(status)
        self.DeclareStateOutputPort("command", self._command_index)
        self.DeclareStateOutputPort("costmap", self._costmap_index)
        self.DeclareStateOutputPort("path_W", self._path_index)
        self.DeclareVectorOutputPort("status", BasicVector(len(_STATUS_OUTPUT)), self._calc_status,
                                     prerequisites_of_calc={self.discrete_state_ticket(self._status_index)})
        self.DeclarePeriodicDiscreteUpdateEvent(self._period_s, offset_s, self._update)

    @property
    def costmap_shape(self) -> tuple[int, int]:
        """(ny, nx) of the costmap; its cell side is `config.costmap.resolution`."""
        return self._costmap.shape

    @property
    def costmap_resolution(self) -> float:
        """The costmap's cell side (m)."""
        return self._costmap.resolution

    @property
    def X_BL(self) -> RigidTransform:
        """The lidar frame L's pose in the chassis frame B."""
        return self._X_BL

    def unpack_costmap(self, value: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(origin xy (m), costs (ny, nx)) from a `costmap` output value."""
        return self._costmap.unpack(value)

    @staticmethod
    def unpack_path(value: np.ndarray) -> np.ndarray:
        """The plan (K, 2) in W from a `path_W` output value."""
        value = np.asarray(value)
        return value[1:1 + 2 * int(value[0])].reshape(-1, 2).copy()

    def planner_status(self, context) -> dict[str, int]:
        """Counters of this system's `context`: halts (steps stopped for lack of an admissible
        trajectory), plans, plan_failures, recoveries, goal_reached (0/1), no_data (steps stopped
        for a cloud without a return) and mode (the last update's `DwaMode`)."""
        status = context.get_discrete_state(self._status_index).get_value()
        return {name: int(status[index]) for name, index in _COUNTERS.items()}

    def _calc_status(self, context, output) -> None:
        output.SetFromVector(context.get_discrete_state(self._status_index).get_value()[list(_STATUS_OUTPUT)])

    def _cloud_in_world(self, cloud: PointCloud,
                        X_WB: RigidTransform) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """The cloud's points (N, 3) in W, less those above or below the footprint; p_WL; the
        directions (M, 3) in W of the rays without a return (none unless `ray_directions_L`);
        and the number of returns (finite points) in the cloud."""
        if self._rays_B is not None and cloud.size() > 0 and cloud.size() != len(self._rays_B):
            raise ValueError(f"point_cloud has {cloud.size()} points; ray_directions_L has {len(self._rays_B)}")
        p_WP, returned = returns_in_world(cloud, self._X_BL, X_WB,
                                          lambda p_BP: self._costmap.inside_footprint(p_BP[:2].T))
        no_return_B = np.zeros((0, 3))
        if self._rays_B is not None and cloud.size() > 0:  # Empty: no data, handled by the caller.
            no_return_B = self._rays_B[~returned & np.isfinite(self._rays_B[:, 0])]
        no_return_W = no_return_B @ X_WB.rotation().matrix().T
        return p_WP, X_WB.multiply(self._X_BL.translation()), no_return_W, int(returned.sum())

    def _update(self, context, discrete_state) -> None:
        config, costmap, t = self._config, self._costmap, context.get_time()
        X_WB = self._poses_port.Eval(context)[self._chassis_index]
        pose = np.array([*X_WB.translation()[:2], planar_yaw(X_WB)])
        status = context.get_discrete_state(self._status_index).get_value().copy()
        # Odometry from the pose change since the last update (the dynamic window's centre).
        velocity = np.zeros(2)
        if status[_ODOM_VALID] and t > status[_ODOM_T]:
            dt = t - status[_ODOM_T]
            velocity[0] = (pose[:2] - status[_ODOM_X:_ODOM_Y + 1]) @ [math.cos(pose[2]), math.sin(pose[2])] / dt
            velocity[1] = wrap_to_pi(pose[2] - status[_ODOM_YAW]) / dt
        status[_ODOM_X:_ODOM_VALID + 1] = [*pose, t, 1.0]
        # The rolling costmap.
        origin = costmap.window_origin(pose[:2])
        layer = context.get_discrete_state(self._layer_index).get_value().reshape(costmap.shape)
        if status[_WINDOW_VALID]:
            layer = costmap.roll(layer, status[_WX:_WY + 1].astype(int), origin)
        else:
            layer = costmap.clear_unknown_around(costmap.empty_layer(), origin, pose[:2], config.start_clearing_radius)
        status[_WX:_WINDOW_VALID + 1] = [*origin, 1.0]
        points_W, p_WL, no_return_W, returns = self._cloud_in_world(self._cloud_port.Eval(context), X_WB)
        # move_base stops the base while its sensor is not current. A cloud without a single return
        # (empty, or no ray came back) is taken as that: the map keeps what it had and the robot
        # stops. On these terrains the 120 deg view always holds some ground within range, except
        # facing straight into a drop from its very edge, where stopping is right too.
        no_data = returns == 0
        if not no_data:
            # For raytracing: the level plane through the ground under the wheels (a tilting
            # chassis would tilt its own plane into the ground far ahead).
            ground_W = (X_WB.translation() - robot.WHEEL_RADIUS_M * X_WB.rotation().matrix()[:, 2],
                        np.array([0, 0, 1.0]))
            layer = costmap.mark(layer, origin, points_W, p_WL, ground_W=ground_W, no_return_W=no_return_W)
        layer = costmap.clear_footprint(layer, origin, pose)
        master = costmap.inflate(layer)
        origin_m = costmap.origin_m(origin)
        path = self.unpack_path(context.get_discrete_state(self._path_index).get_value())
        command = np.zeros(2)
        recover = False
        if status[_GOAL_REACHED] or np.linalg.norm(self._goal_xy - pose[:2]) <= config.local_planner.xy_goal_tolerance:
            status[_GOAL_REACHED], status[_MODE] = 1.0, DwaMode.GOAL_REACHED
        elif no_data:
            status[_NO_DATA] += 1
            status[_MODE] = DwaMode.NO_DATA
        else:
            status[_MODE] = DwaMode.NO_PLAN  # Until the local planner says otherwise.
            # The global planner: at planner_frequency, when there is no plan, or after a failure.
            due = config.planner_frequency > 0 and not t - status[_LAST_PLAN_T] < 1.0 / config.planner_frequency - 1e-9
            if len(path) == 0 or status[_REPLAN] or due:
                status[_PLANS] += 1
                new_plan = plan(master, origin_m, costmap.resolution, pose[:2], self._goal_xy, config.global_planner)
                if new_plan is not None:
                    path = new_plan.path_xy
                    status[[_LAST_PLAN_T, _REPLAN, _PLAN_FAIL_SINCE]] = [t, 0.0, np.nan]
                else:
                    status[_PLAN_FAILURES] += 1
                    status[_REPLAN] = 1.0
                    status[_PLAN_FAIL_SINCE] = np.nan_to_num(status[_PLAN_FAIL_SINCE], nan=t)
                    if t - status[_PLAN_FAIL_SINCE] >= config.planner_patience:
                        path, recover, status[_PLAN_FAIL_SINCE] = np.zeros((0, 2)), True, t
            # The local planner.
            if len(path) > 0:
                result = find_best_trajectory(
                    master, origin_m, costmap.resolution, pose, velocity, path, self._goal_xy, self._outline_B,
                    self._period_s, config.local_planner, status[_OSC0:_OSC3 + 1])
                if result.admissible:
                    command[:] = [result.v, result.w]
                    status[_MODE] = DwaMode.DRIVING
                    status[_CONTROL_FAIL_SINCE] = np.nan
                    status[_OSC0:_OSC3 + 1], status[_STATIONARY_X:_STATIONARY_Y + 1] = update_oscillation_flags(
                        status[_OSC0:_OSC3 + 1], status[_STATIONARY_X:_STATIONARY_Y + 1], pose, result.v, result.w,
                        config.local_planner)
                else:
                    # move_base: publish zero velocity and go back to planning.
                    status[_HALTS] += 1
                    status[_MODE] = DwaMode.HALTED
                    status[_REPLAN] = 1.0
                    status[_CONTROL_FAIL_SINCE] = np.nan_to_num(status[_CONTROL_FAIL_SINCE], nan=t)
                    if t - status[_CONTROL_FAIL_SINCE] >= config.controller_patience:
                        recover, status[_CONTROL_FAIL_SINCE] = True, t
        if recover and config.recovery_behavior_enabled:
            status[_RECOVERIES] += 1
            layer = costmap.reset_outside(layer, origin, pose[:2], config.conservative_reset_dist)
            master = costmap.inflate(layer)
        limits = [config.local_planner.max_vel_x, config.local_planner.max_vel_theta]
        discrete_state.set_value(self._command_index, np.clip(command, np.negative(limits), limits))
        discrete_state.set_value(self._layer_index, layer.reshape(-1))
        discrete_state.set_value(self._costmap_index, costmap.pack(origin_m, master))
        discrete_state.set_value(self._path_index, self._pack_path(path))
        discrete_state.set_value(self._status_index, status)

    def _pack_path(self, path: np.ndarray) -> np.ndarray:
        """[count, x0, y0, ...] padded to the state's size; long plans are subsampled (ends kept)."""
        limit = self._config.max_path_points
        if len(path) > limit:
            path = path[np.round(np.linspace(0, len(path) - 1, limit)).astype(int)]
        value = np.zeros(1 + 2 * limit)
        value[0] = len(path)
        value[1:1 + 2 * len(path)] = path.reshape(-1)
        return value
