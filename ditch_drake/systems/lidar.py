"""The lidar's LeafSystem: the depth cameras' images -> point clouds in the lidar frame L.

The lidar's settings, frames and camera geometry are in `ditch_drake.perception.lidar_model`;
`ditch_drake.diagrams.lidar_rig.AddLidar` adds the cameras and this system to a scene.
"""

import math

import numpy as np
from pydrake.common import RandomDistribution
from pydrake.common.value import Value
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.perception import BaseField, Fields, PointCloud
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem
from pydrake.systems.sensors import ImageDepth32F

from ditch_drake.perception.lidar_model import (
    PIXEL_CENTER,
    LidarConfig,
    chassis_box_interval,
    lidar_camera_info,
    lidar_camera_poses,
)
from ditch_drake.spec import robot


class DepthImagesToLidarCloud(LeafSystem):
    """Merges the lidar cameras' depth images into point clouds in the lidar frame L.

    In a periodic unrestricted update (`period_s`, offset `offset_s`) it reads
    every depth image, turns pixels into points along precomputed rays, applies range noise
    and dropout, and keeps a return only if it is finite, within [min_range_m, range_m] of
    the sensor, inside the field of view and outside the chassis box grown by
    `self_filter_margin_m` (a precomputed per-ray interval test). Rendering happens only
    here: `RgbdSensor` outputs render when evaluated, and only this update pulls them, so
    the cameras render at the control rate, not at every physics step. A forced
    unrestricted update event runs the same update (`ExecuteForcedEvents`).

    State: the organized cloud lives in the Context as abstract state, and `organized_points`
    hands it out (`DeclareStateOutputPort`). A `PointCloud` is a C++ value, cloned in C++ (a
    memcpy, no Python deep copy) when the update copies the state; consumers take
    `PointCloud`s, so discrete state would only add a conversion on every read.
    `point_cloud` (the returns alone) is computed from that state when it is read and cached
    until the next update: the learned policy's loop never reads it, so it costs nothing
    there. Before the first update the organized cloud is all NaN and `point_cloud` empty.

    Noise: with `noise_std_m` or `dropout_probability` > 0 each update draws from a numpy
    generator seeded with (`config.seed`, the two `noise_seed` samples). A Python LeafSystem
    cannot override `SetRandomState`, so the samples come from the Drake `RandomSource` that
    `AddLidar` connects: `diagram.SetRandomContext(context, RandomGenerator(seed))` seeds it,
    and the same seed gives the same clouds. (A default Context uses the source's own seed:
    repeatable for one built diagram, not across rebuilds.)

    .. pydrake_system::

        name: DepthImagesToLidarCloud
        input_ports:
        - depth_image_0
        - ...
        - noise_seed (only with noise or dropout)
        output_ports:
        - point_cloud
        - organized_points

    Ports:
        depth_image_i: camera i's `ImageDepth32F` (m along its optical axis; 0 too close,
            inf too far), camera 0 leftmost.
        noise_seed: two uniform samples in [0, 1), renewed every control step.
        point_cloud: the returns as a `PointCloud` (xyz only) in L, without NaNs.
        organized_points: a `PointCloud` of exactly rows * cols points in L, rows = height,
            cols = num_cameras * width: point r * cols + c is pixel row r (top, i.e. highest,
            first) of the panorama's column c (leftmost first; camera i has columns
            i * width ... (i + 1) * width - 1). NaN where there is no (kept) return.
            `NormalImageConverter(organized_shape=self.organized_shape)` reads it directly.
    """

    def __init__(self, config: LidarConfig | None = None, X_BL: RigidTransform | None = None,
                 period_s: float = robot.CONTROL_PERIOD_S, offset_s: float = 0.0):
        """Args:
            config: the lidar; None for `LidarConfig()`.
            X_BL: the lidar frame in the chassis body frame; None: p_BL = LIDAR_MOUNT_XYZ_M.
            period_s: update period (s), the control rate.
            offset_s: time of the first update (s); builders pass `ScheduleConfig.lidar_offset_s`.

        Raises:
            ValueError: a config value out of range (named).
        """
        super().__init__()
        self._config = config = config if config is not None else LidarConfig()
        config.validate()
        X_BL = X_BL if X_BL is not None else RigidTransform(robot.LIDAR_MOUNT_XYZ_M)
        self._make_rays(config, X_BL)

        self._image_ports = [
            self.DeclareAbstractInputPort(f"depth_image_{i}", Value(ImageDepth32F())) for i in range(config.num_cameras)
        ]
        self._seed_port = None
        if config.noisy:
            self._seed_port = self.DeclareVectorInputPort("noise_seed", BasicVector(2), RandomDistribution.kUniform)
        organized = PointCloud(self._unit_rays_L.shape[1], Fields(BaseField.kXYZs))
        organized.mutable_xyzs()[:] = np.nan
        self._organized_index = self.DeclareAbstractState(Value(organized))
        self.DeclareAbstractOutputPort(
            "point_cloud",
            lambda: Value(PointCloud(0, Fields(BaseField.kXYZs))),
            self._calc_returns,
            prerequisites_of_calc={self.abstract_state_ticket(self._organized_index)},
        )
        self.DeclareStateOutputPort("organized_points", self._organized_index)
        self.DeclarePeriodicUnrestrictedUpdateEvent(period_s, offset_s, self._update)
        self.DeclareForcedUnrestrictedUpdateEvent(self._update)

    def _make_rays(self, config: LidarConfig, X_BL: RigidTransform) -> None:
        """Precomputes per pixel of the panorama: unit ray in L, depth-to-range factor, field
        of view mask, and the range interval in which the ray is inside the chassis box."""
        info = lidar_camera_info(config, X_BL)
        u, v = np.meshgrid(np.arange(config.width), np.arange(config.height))
        ray_C = np.stack(
            [
                (u + PIXEL_CENTER - info.center_x()) / info.focal_x(),
                (v + PIXEL_CENTER - info.center_y()) / info.focal_y(),
                np.ones(u.shape),
            ],
            axis=-1,
        )
        rays = [ray_C @ X_LC.rotation().matrix().T for X_LC in lidar_camera_poses(config)]
        rays_L = np.concatenate(rays, axis=1)  # (height, num_cameras * width, 3); p_L = depth * ray
        self._organized_shape = rays_L.shape[:2]
        rays_L = rays_L.reshape(-1, 3)
        self._depth_to_range = np.linalg.norm(rays_L, axis=1)
        unit_L = rays_L / self._depth_to_range[:, None]
        self._unit_rays_L = np.ascontiguousarray(unit_L.T)  # (3, rows * cols)

        R_LS = RotationMatrix.MakeYRotation(math.radians(config.pitch_deg)).matrix()
        ray_S = unit_L @ R_LS  # rows are R_SL @ u_L
        azimuth = np.arctan2(ray_S[:, 1], ray_S[:, 0])
        elevation = np.arctan2(ray_S[:, 2], np.hypot(ray_S[:, 0], ray_S[:, 1]))
        tolerance = 1e-9
        self._in_fov = (np.abs(azimuth) <= math.radians(config.horizontal_fov_deg) / 2 + tolerance) & (
            np.abs(elevation) <= math.radians(config.vertical_fov_deg) / 2 + tolerance
        )

        direction_B = unit_L @ X_BL.rotation().matrix().T
        self._self_enter, self._self_leave = chassis_box_interval(
            X_BL.translation(), direction_B, config.self_filter_margin_m
        )

    @property
    def config(self) -> LidarConfig:
        """The lidar's configuration."""
        return self._config

    @property
    def organized_shape(self) -> tuple[int, int]:
        """(rows, cols) of `organized_points`: (height, num_cameras * width)."""
        return tuple(int(n) for n in self._organized_shape)

    @property
    def ray_directions_L(self) -> np.ndarray:
        """(rows * cols, 3) unit direction in L of each `organized_points` ray; NaN rows for the
        rays outside the field of view (they never return). A ray inside it that has no point
        saw nothing within range (or only the robot itself)."""
        return np.where(self._in_fov[:, None], self._unit_rays_L.T, np.nan)

    def organized_points_from_depths(
        self, depths: list[np.ndarray], rng: np.random.Generator | None = None
    ) -> np.ndarray:
        """The lidar's returns for the cameras' depth arrays, organized as `organized_points`.

        Args:
            depths: each camera's (height, width) or (height, width, 1) depth (m), leftmost first.
            rng: draws the range noise and dropout when the config has them; None: noise-free.

        Returns:
            (3, rows * cols) positions in L (m), like `PointCloud.xyzs()`; NaN where no return is kept.
        """
        distance, keep = self._ranges(depths, rng)
        return self._unit_rays_L * np.where(keep, distance, np.nan)  # The rays are finite: NaN ranges, NaN points.

    def _ranges(self, depths: list[np.ndarray], rng: np.random.Generator | None) -> tuple[np.ndarray, np.ndarray]:
        """Each ray's range (m) for the cameras' depth arrays, and whether its return is kept."""
        config = self._config
        rows = self._organized_shape[0]
        panorama = np.concatenate([np.reshape(d, (rows, config.width)) for d in depths], axis=1)
        distance = panorama.reshape(-1) * self._depth_to_range  # 0: too close, inf: too far
        if rng is not None and config.noise_std_m > 0:
            noise = rng.normal(0.0, config.noise_std_m, distance.shape)
            distance = np.where(distance > 0, distance + noise, np.nan)
        keep = self._in_fov & (distance >= max(config.min_range_m, 1e-9)) & (distance <= config.range_m)
        keep &= (distance < self._self_enter) | (distance > self._self_leave)  # self-returns
        if rng is not None and config.dropout_probability > 0:
            keep &= rng.random(distance.shape) >= config.dropout_probability
        return distance, keep

    def _rng(self, context) -> np.random.Generator | None:
        if self._seed_port is None:
            return None
        u = self._seed_port.Eval(context)
        return np.random.default_rng([int(self._config.seed), int(u[0] * 2**32), int(u[1] * 2**32)])

    def _update(self, context, state) -> EventStatus:
        depths = [port.Eval(context).data for port in self._image_ports]
        distance, keep = self._ranges(depths, self._rng(context))
        xyzs = state.get_mutable_abstract_state(self._organized_index).get_mutable_value().mutable_xyzs()
        # `organized_points_from_depths` written straight into the cloud: the float64 products
        # are rounded to the cloud's float32 as they are stored, as an assignment would round them.
        np.multiply(self._unit_rays_L, np.where(keep, distance, np.nan), out=xyzs, casting="same_kind")
        return EventStatus.Succeeded()

    def _calc_returns(self, context, output) -> None:
        points = context.get_abstract_state(self._organized_index).get_value().xyzs()
        returns = np.compress(~np.isnan(points[0]), points, axis=1)
        cloud = output.get_mutable_value()
        cloud.resize(returns.shape[1])
        cloud.mutable_xyzs()[:] = returns
