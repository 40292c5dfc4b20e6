"""Which side along the edge to cross on, from what the lidar saw: the crossing side without a map."""

import math
from dataclasses import dataclass

import numpy as np
from pydrake.common.value import Value
from pydrake.math import RigidTransform
from pydrake.perception import PointCloud
from pydrake.systems.framework import BasicVector, LeafSystem

from ditch_drake.common.errors import ConfigError
from ditch_drake.perception.lidar_points import open_rays_B, within_chassis_in_plan
from ditch_drake.planning.rolling_window import RollingWindow
from ditch_drake.spec import robot
from ditch_drake.systems.edge_angle_driver import EdgeAngleDriverConfig
from ditch_drake.world.crossing import approach_side

_EXPERT = EdgeAngleDriverConfig()

# Layout of the bookkeeping state.
_WX, _WY, _WINDOW_VALID, _HELD, _SIDE, _SEEN, _DISTANCE, _AWAY_X, _AWAY_Y = range(9)
_STATE_SIZE = 9


@dataclass
class PerceivedCrossingSideConfig:
    """How the edge is found in the lidar's rays (m, deg).

    Attributes:
        drop_depth_m: a ray whose return lies this far below the ground plane under the
            wheels, or that returns nothing where that plane lies within the lidar's range,
            has passed over a drop.
        range_fraction: only rays that would meet the plane within this share of the lidar's
            range count, so that a ray grazing its range on open ground is not a drop.
        robot_margin_m: rays meeting the plane within the chassis box grown by this in plan
            are ignored (the robot's own body hides the ground there).
        resolution_m: cell side of the rolling window that accumulates drops in the world.
        window_m: the window's side, centred on the robot.
        min_marks: a cell is a drop once this many rays (over all steps) marked it: a single
            ray that returned nothing on open ground (one did, 2 m short of a crater's edge, and
            set the side there 37 deg off) is not a ditch.
        band_m: drop cells within this of the nearest one are the edge the side is read from.
        min_cells: fewer drop cells than this: the edge is not seen yet.
        approach_margin_m: the side is held from where the nearest drop lies this close to
            the chassis (the expert's approach zone: it commits to its side there).
        straight_across_deg: the expert's convention near square on (`approach_side`).
        hold_tilt_deg: a side seen already is held once the chassis tilts this far (on a
            wall, where the plane under the wheels no longer describes the ground ahead).
    """

    drop_depth_m: float = 0.3
    range_fraction: float = 0.95
    robot_margin_m: float = 0.3
    resolution_m: float = 0.2
    window_m: float = 10.0
    min_marks: int = 2
    band_m: float = 1.0
    min_cells: int = 3
    approach_margin_m: float = _EXPERT.approach_margin_m
    straight_across_deg: float = _EXPERT.straight_across_deg
    hold_tilt_deg: float = 10.0

    def validate(self) -> None:
        """Raises ConfigError naming the first key out of range."""
        positive = ("drop_depth_m", "resolution_m", "window_m", "band_m", "approach_margin_m", "hold_tilt_deg")
        for key in positive:
            value = getattr(self, key)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ConfigError(f"perceived crossing side {key}={value!r}: expected a positive number")
        if not 0 < self.range_fraction <= 1:
            raise ConfigError(f"perceived crossing side range_fraction={self.range_fraction!r}: expected (0, 1]")
        if not self.robot_margin_m >= 0:
            raise ConfigError(f"perceived crossing side robot_margin_m={self.robot_margin_m!r}: expected >= 0")
        if not 0 <= self.straight_across_deg < 90:
            raise ConfigError(f"perceived crossing side straight_across_deg={self.straight_across_deg!r}: "
                              "expected [0, 90)")
        for key in ("min_marks", "min_cells"):
            value = getattr(self, key)
            if not (isinstance(value, int) and value >= 1):
                raise ConfigError(f"perceived crossing side {key}={value!r}: expected an integer >= 1")
        if not self.window_m >= 4 * self.resolution_m:
            raise ConfigError(f"perceived crossing side window_m={self.window_m!r}: expected at least 4 cells")


class PerceivedCrossingSide(LeafSystem):
    """The side along the edge the expert's rule would cross on, from the lidar and odometry.

    The same rule as `OracleCrossingSide` (`ditch_drake.world.crossing.approach_side`: toward
    the goal's side along the edge, or right by convention near square on), held from the
    approach zone on, with the edge found in the lidar's rays instead of read from the ditch's
    course. A ditch's near wall lies in the lidar's shadow: the ground ends and the rays that
    would meet it return nothing within range, or return from far below. Every control step,
    each ray that would meet the plane under the wheels within range but returns nothing or
    returns from more than `drop_depth_m` below it marks the point where it would have met the
    plane: a drop. The marks accumulate in a rolling window fixed in the world (the pose from
    the plant, as the `mppi` baseline's map takes it); a ray that returns from the plane clears
    its cell, and a cell is a drop once `min_marks` rays marked it. The drop cells within `band_m` of the nearest one lie along the edge: their
    principal direction is the edge's, the side of it toward the robot is away from the ditch.
    Until `min_cells` drop cells are seen the output is 0 (a side-conditioned clone is then not
    reflected); from there on, the rule at the current pose; once the nearest drop lies within
    `approach_margin_m` of the chassis (or the chassis tilts past `hold_tilt_deg`), the side
    it had then, for good.

    It updates at the frame stacker's offset, after the lidar's tick and before the
    controller's, so the controller reads the side of the same control step.

    .. pydrake_system::

        name: PerceivedCrossingSide
        input_ports:
        - point_cloud
        - body_poses
        output_ports:
        - crossing_side
        - edge

    Ports:
        point_cloud: the lidar's organized cloud in L (`organized_points`; non-finite: no return).
        body_poses: the plant's body poses X_WB (vector of RigidTransform).
        crossing_side: [+1] to cross turned right along the edge (facing the ditch), [-1]
            left, [0] before the edge is seen.
        edge: [seen (0/1), distance to the nearest drop (m), away_x, away_y]: the unit
            direction across the edge away from the ditch, as last estimated (NaN unseen).
    """

    def __init__(self, goal_xy, chassis_body_index, X_BL: RigidTransform, ray_directions_L: np.ndarray,
                 lidar_range_m: float, config: PerceivedCrossingSideConfig | None = None,
                 period_s: float = robot.CONTROL_PERIOD_S, offset_s: float = 0.0):
        super().__init__()
        self._config = config or PerceivedCrossingSideConfig()
        self._config.validate()
        self._goal_xy = np.asarray(goal_xy, dtype=float)[:2]
        self._chassis_index = int(chassis_body_index)
        self._rays = _PlaneRays(X_BL, ray_directions_L, lidar_range_m, self._config)
        n = max(4, round(self._config.window_m / self._config.resolution_m))
        self._window = RollingWindow(self._config.resolution_m, (n, n), 0.0)
        self._cloud_port = self.DeclareAbstractInputPort("point_cloud", Value(PointCloud()))
        self._poses_port = self.DeclareAbstractInputPort("body_poses", Value([RigidTransform()]))
        self._drops_index = self.DeclareDiscreteState(np.zeros(self._window.size))
        state = np.zeros(_STATE_SIZE)
        state[[_DISTANCE, _AWAY_X, _AWAY_Y]] = np.nan
        self._state_index = self.DeclareDiscreteState(state)
        self.DeclareVectorOutputPort("crossing_side", BasicVector(1), self._calc_side,
                                     {self.discrete_state_ticket(self._state_index)})
        self.DeclareVectorOutputPort("edge", BasicVector(4), self._calc_edge,
                                     {self.discrete_state_ticket(self._state_index)})
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, offset_s, self._update)

    @property
    def config(self) -> PerceivedCrossingSideConfig:
        return self._config

    def _calc_side(self, context, output) -> None:
        output.SetAtIndex(0, context.get_discrete_state(self._state_index).GetAtIndex(_SIDE))

    def _calc_edge(self, context, output) -> None:
        state = context.get_discrete_state(self._state_index).get_value()
        output.SetFromVector(state[[_SEEN, _DISTANCE, _AWAY_X, _AWAY_Y]])

    def _update(self, context, discrete_state) -> None:
        config, window = self._config, self._window
        state = context.get_discrete_state(self._state_index).get_value().copy()
        if state[_HELD] != 0.0:
            return  # Held for good: the state stays as it is (Drake hands the update the current one).
        drops = context.get_discrete_state(self._drops_index).get_value().reshape(window.shape)
        X_WB = self._poses_port.Eval(context)[self._chassis_index]
        xy = X_WB.translation()[:2]
        origin = window.window_origin(xy)
        if state[_WINDOW_VALID]:
            drops = window.roll(drops, state[_WX:_WY + 1].astype(int), origin)
        state[_WX:_WINDOW_VALID + 1] = [*origin, 1.0]
        cloud = self._cloud_port.Eval(context)
        if cloud.size() == len(self._rays.plane_hit_B):
            dropped, ground = self._rays.classify(cloud.xyzs())
            drops = _mark(window, drops, origin, X_WB, self._rays.plane_hit_B, dropped, ground)
        edge = _edge(window, drops, origin, xy, config)
        if edge is not None:
            distance, away = edge
            side = approach_side(self._goal_xy - xy, -away, np.array([-away[1], away[0]]),
                                 config.straight_across_deg)
            tilt = math.degrees(math.acos(np.clip(X_WB.rotation().matrix()[2, 2], -1.0, 1.0)))
            state[[_SIDE, _SEEN, _DISTANCE, _AWAY_X, _AWAY_Y]] = [side, 1.0, distance, *away]
            if distance <= config.approach_margin_m or tilt >= config.hold_tilt_deg:
                state[_HELD] = side
        discrete_state.set_value(self._drops_index, drops.reshape(-1))
        discrete_state.set_value(self._state_index, state)


class _PlaneRays:
    """The lidar's rays that meet the plane under the wheels within range, where they meet it
    (fixed in the chassis frame B), and which of them a cloud shows passing over a drop."""

    def __init__(self, X_BL: RigidTransform, ray_directions_L: np.ndarray, lidar_range_m: float,
                 config: PerceivedCrossingSideConfig):
        rays_B = open_rays_B(np.asarray(ray_directions_L, dtype=float), X_BL)
        p_BL = X_BL.translation()
        # The chassis origin rides at the wheels' axle height (as the `mppi` map's footprint).
        plane_z_B = -robot.WHEEL_RADIUS_M
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (plane_z_B - p_BL[2]) / rays_B[:, 2]
        hit_B = p_BL + t[:, None] * rays_B
        usable = np.isfinite(t) & (t > 0) & (t <= config.range_fraction * lidar_range_m)
        usable &= ~within_chassis_in_plan(config.robot_margin_m)(np.nan_to_num(hit_B).T)
        self._indices = np.flatnonzero(usable)
        self.plane_hit_B = np.full((len(rays_B), 3), np.nan)
        self.plane_hit_B[self._indices] = hit_B[self._indices]
        self._R_BL = X_BL.rotation().matrix()
        self._p_BL = p_BL
        self._plane_z_B = plane_z_B
        self._drop_depth_m = config.drop_depth_m

    def classify(self, xyzs_L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Indices of the usable rays that passed over a drop, and of those that met the plane."""
        # A ray without a return holds NaN, which the height above the plane keeps.
        height = self._R_BL[2] @ xyzs_L[:, self._indices] + (self._p_BL[2] - self._plane_z_B)
        with np.errstate(invalid="ignore"):
            dropped = ~(height >= -self._drop_depth_m)
            ground = np.abs(height) <= self._drop_depth_m
        return self._indices[dropped], self._indices[ground]


def _mark(window: RollingWindow, drops: np.ndarray, origin: np.ndarray, X_WB: RigidTransform,
          plane_hit_B: np.ndarray, dropped: np.ndarray, ground: np.ndarray) -> np.ndarray:
    """`drops` with the cells where `dropped` rays meet the plane counted, and those where
    `ground` rays do cleared."""
    R_WB, p_WB = X_WB.rotation().matrix(), X_WB.translation()
    drops = drops.reshape(-1).copy()
    for indices, clear in ((ground, True), (dropped, False)):
        if len(indices) == 0:
            continue
        xy_W = plane_hit_B[indices] @ R_WB[:2].T + p_WB[:2]
        iy, ix, inside = window.world_to_cell(origin, xy_W)
        flat = iy[inside] * window.shape[1] + ix[inside]
        if clear:
            drops[flat] = 0.0
        else:
            drops += np.bincount(flat, minlength=window.size)
    return drops.reshape(window.shape)


def _edge(window: RollingWindow, drops: np.ndarray, origin: np.ndarray, xy: np.ndarray,
          config: PerceivedCrossingSideConfig) -> tuple[float, np.ndarray] | None:
    """(distance to the nearest drop cell (m), unit direction across the edge away from the
    ditch) from the drop cells near the robot; None while fewer than `min_cells` are seen."""
    iy, ix = np.nonzero(drops >= config.min_marks)
    if len(iy) < config.min_cells:
        return None
    xs, ys = window.cell_centers(origin)
    cells = np.column_stack([xs[ix], ys[iy]])
    distances = np.linalg.norm(cells - xy, axis=1)
    nearest = float(distances.min())
    band = cells[distances <= nearest + config.band_m]
    centroid = band.mean(axis=0)
    if len(band) >= config.min_cells:
        _, vectors = np.linalg.eigh(np.cov((band - centroid).T))
        away = vectors[:, 0]  # The band's least spread: across the edge.
    else:
        away = xy - centroid
    if float(away @ (xy - centroid)) < 0.0:
        away = -away
    norm = float(np.linalg.norm(away))
    if norm == 0.0:
        return None
    return nearest, away / norm
