"""The simulated lidar (SPEC "Robot"): depth cameras rendered by Drake, merged into one cloud.

The lidar is modelled by `num_cameras` depth-only pinhole cameras (`RgbdSensor` with a
`DepthRenderCamera`, rendered headless by `RenderEngineVtk`) side by side at the Husky's
`lidar_mount` frame. `DepthImagesToLidarCloud` turns their depth images into points at the
control rate and keeps the returns inside the lidar's field of view and range. `AddLidar`
wires it all into a scene from `AddDitchScene`.

Frames:
    B: the chassis body frame (`ditch_drake.robot`).
    L: the lidar frame, `lidar_mount` of `models_sdf/husky.sdf`: fixed to the chassis at
        p_BL = `robot.LIDAR_MOUNT_XYZ_M`, axes parallel to B (+x forward, +y left, +z up).
        **The clouds are expressed in L.** (R_BL = I: a consumer that wants B, such as
        `NormalImageConverter`, needs no rotation.)
    S: the sensor's aim, L pitched down by `pitch_deg` about +y_L. The field of view is
        |azimuth| <= horizontal_fov / 2 and |elevation| <= vertical_fov / 2 in S.
    C_i: camera i (Drake's convention: +z along the optical axis, +x right, +y down), S
        yawed by yaw_i about +z_S, camera 0 leftmost. Each camera spans an equal share of the
        horizontal field of view; its vertical field of view is widened so that the image
        corners still reach the full elevation, and the rays outside the field of view are
        masked out once, when the system is built.

Pitch: the default 30 deg down points the 80 deg vertical field of view from 10 deg above
the horizon (the far side when the robot noses down into a ditch) to 70 deg below it. The
chassis top hides every ray steeper than about 34 deg below the horizon straight ahead
(19 deg at +-60 deg azimuth), so on flat ground the lidar sees the ground from about
0.75 m in front of the bumper (1.25 m ahead of B) out to the 4 m range, which meets flat
ground 8.4 deg below the horizon. The rows below the lowest ray that can clear the chassis
would only ever see the chassis, so they are not rendered (`crop_self_occluded`): the same
pixels then cover the useful band twice as densely. Consequence for the ditches: standing
level at the edge of a 55 deg wall the lidar sees nothing inside the ditch within 4 m (the
wall falls away more steeply than the steepest ray that clears the chassis, and the floor
is farther than 4 m); it sees down the wall once the chassis pitches nose-down over the
hinge (by about 25 deg or more).

Rendering cost (CPU: Mesa's llvmpipe through EGL): a `RenderEngineVtk` image costs about
0.4 ms plus 10-35 us per actor, and the ditch is 600-2000 boxes (about 20 ms an image). So
`AddLidar` merges the terrain's boxes into one mesh per colour holding only their upward
faces (`MergeAnchoredPerceptionBoxes`), and hides the lidar's own housing, inside which
the cameras sit (`RemoveSensorHousings`). Both change what every Drake camera sees; see
their docstrings.
"""

import math
import os
from dataclasses import dataclass

import numpy as np
from pydrake.common import MemoryFile, RandomDistribution
from pydrake.common.value import Value
from pydrake.geometry import (
    Box,
    ClippingRange,
    DepthRange,
    DepthRenderCamera,
    FrameId,
    GeometryInstance,
    InMemoryMesh,
    MakeRenderEngineVtk,
    Mesh,
    PerceptionProperties,
    RenderCameraCore,
    RenderEngineVtkParams,
    Rgba,
    Role,
    SceneGraph,
    SourceId,
)
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.plant import MultibodyPlant
from pydrake.perception import BaseField, Fields, PointCloud
from pydrake.systems.framework import BasicVector, DiagramBuilder, EventStatus, LeafSystem
from pydrake.systems.primitives import RandomSource
from pydrake.systems.sensors import CameraInfo, ImageDepth32F, RgbdSensor

from ditch_drake import robot, schedule

# `RenderEngineVtk` (Drake 1.51) renders pixel (u, v) along the ray through the image point
# (u + 0.5, v + 0.5) of the `CameraInfo` pinhole model (the principal point counted from the
# image's corner), not through (u, v) as the `CameraInfo` docs have it: measured on flat
# ground, the returns are exact with this offset and up to half a pixel off without it.
PIXEL_CENTER = 0.5

# The choices of `MergeAnchoredPerceptionBoxes`'s `faces` (and `LidarConfig.terrain_faces`).
_FACE_CHOICES = ("top", "up", "all")

# Drake's camera frame C in a frame F with +x forward, +y left, +z up: columns are C's axes.
_R_FC = RotationMatrix(np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]))


@dataclass
class LidarConfig:
    """The lidar: field of view, range, cameras, noise.

    Attributes:
        width: pixels per camera across (columns). The default 2 cameras of 64 x 48 give
            about 2200 returns on flat ground for 1.1-3 ms an update on one CPU core.
        height: pixels per camera down (rows).
        num_cameras: pinhole cameras side by side, each spanning horizontal_fov_deg / num_cameras.
        horizontal_fov_deg: total horizontal field of view, in (0, 180).
        vertical_fov_deg: vertical field of view, in (0, 180).
        pitch_deg: downward pitch of the field of view's centre below L's horizon, in (-90, 90).
        range_m: largest distance from the sensor of a return (m), > 0.
        min_range_m: returns closer than this are dropped (the housing; m), in [0, range_m).
        noise_std_m: standard deviation of Gaussian noise added to each return's range (m).
        dropout_probability: chance that a return is dropped, in [0, 1).
        seed: mixed into every noise draw with the seed from `SetRandomContext`.
        self_filter_margin_m: the chassis box grows by this on every side before returns
            inside it are dropped (m).
        period_s: update period (s), the control rate.
        offset_s: time of the first update (s); see `ditch_drake.schedule`.
        crop_self_occluded: leave out the image rows below the lowest ray that can miss the
            chassis: they only ever see the chassis top (see `lidar_camera_info`).
        renderer_name: the SceneGraph renderer the cameras use (added if missing).
        merge_terrain_geometry: merge the anchored perception boxes for fast rendering.
        terrain_faces: which of the merged boxes' faces are rendered: "top", "up" or "all"
            (`MergeAnchoredPerceptionBoxes`).
        rasterizer_threads: worker threads of Mesa's llvmpipe, the CPU rasterizer behind
            headless EGL (its `LP_NUM_THREADS`; 0: rasterize in the rendering thread).
            `AddLidar` sets it for the process unless `LP_NUM_THREADS` is already set;
            it takes effect only before the process's first render. For these small
            images the threads cost more than they save: with 0 the default lidar's update
            took about a quarter less wall time than with llvmpipe's default (one thread
            per core) on a quiet 2-core machine, and half with both cores busy, and a
            rollout stays on one core. None leaves Mesa's default.
    """

    width: int = 64
    height: int = 48
    num_cameras: int = 2
    horizontal_fov_deg: float = math.degrees(robot.LIDAR_HORIZONTAL_FOV_RAD)
    vertical_fov_deg: float = math.degrees(robot.LIDAR_VERTICAL_FOV_RAD)
    pitch_deg: float = 30.0
    range_m: float = robot.LIDAR_RANGE_M
    min_range_m: float = 0.1
    noise_std_m: float = 0.0
    dropout_probability: float = 0.0
    seed: int = 0
    self_filter_margin_m: float = 0.02
    period_s: float = robot.CONTROL_PERIOD_S
    offset_s: float = schedule.LIDAR_OFFSET_S
    crop_self_occluded: bool = True
    renderer_name: str = "lidar_vtk"
    merge_terrain_geometry: bool = True
    terrain_faces: str = "up"
    rasterizer_threads: int | None = 0

    def validate(self) -> None:
        """Raises ValueError naming the first field out of range."""
        checks = [
            ("width", self.width, isinstance(self.width, int) and self.width >= 2, ">= 2"),
            ("height", self.height, isinstance(self.height, int) and self.height >= 2, ">= 2"),
            ("num_cameras", self.num_cameras, isinstance(self.num_cameras, int) and self.num_cameras >= 1, ">= 1"),
            ("horizontal_fov_deg", self.horizontal_fov_deg, 0 < self.horizontal_fov_deg < 180, "in (0, 180)"),
            ("vertical_fov_deg", self.vertical_fov_deg, 0 < self.vertical_fov_deg < 180, "in (0, 180)"),
            ("pitch_deg", self.pitch_deg, -90 < self.pitch_deg < 90, "in (-90, 90)"),
            ("range_m", self.range_m, 0 < self.range_m < math.inf, "> 0 and finite"),
            ("min_range_m", self.min_range_m, 0 <= self.min_range_m < self.range_m, "in [0, range_m)"),
            ("noise_std_m", self.noise_std_m, 0 <= self.noise_std_m < math.inf, ">= 0"),
            ("dropout_probability", self.dropout_probability, 0 <= self.dropout_probability < 1, "in [0, 1)"),
            ("self_filter_margin_m", self.self_filter_margin_m, self.self_filter_margin_m >= 0, ">= 0"),
            ("period_s", self.period_s, self.period_s > 0, "> 0"),
            ("seed", self.seed, isinstance(self.seed, int) and self.seed >= 0, "an int >= 0"),
            ("terrain_faces", self.terrain_faces, self.terrain_faces in _FACE_CHOICES, f"one of {_FACE_CHOICES}"),
            ("rasterizer_threads", self.rasterizer_threads,
             self.rasterizer_threads is None or (isinstance(self.rasterizer_threads, int) and self.rasterizer_threads >= 0),
             "None or an int >= 0"),
        ]
        for name, value, ok, allowed in checks:
            if not ok:
                raise ValueError(f"LidarConfig.{name}={value!r} must be {allowed}")

    @property
    def noisy(self) -> bool:
        """Whether returns get range noise or dropout (and the system a `noise_seed` input)."""
        return self.noise_std_m > 0 or self.dropout_probability > 0


def lidar_camera_info(config: LidarConfig, X_BL: RigidTransform | None = None) -> CameraInfo:
    """Intrinsics shared by the cameras.

    Horizontally each camera spans exactly its share of the field of view. Vertically the
    image is widened so that its corners reach the full elevation, and, with
    `config.crop_self_occluded`, cut off below the lowest row in which some ray misses the
    chassis (the rows below only ever see the robot's own chassis top). The principal
    point is then above the image centre.

    Args:
        config: the lidar.
        X_BL: the lidar frame in the chassis body frame; None: p_BL = LIDAR_MOUNT_XYZ_M.
    """
    half_h = math.radians(config.horizontal_fov_deg) / config.num_cameras / 2
    half_v = math.atan(math.tan(math.radians(config.vertical_fov_deg) / 2) / math.cos(half_h))
    focal_x = config.width / 2 / math.tan(half_h)
    center_x = config.width / 2
    top, bottom = -math.tan(half_v), math.tan(half_v)  # image-plane y = (v + 0.5 - center_y) / focal_y
    if config.crop_self_occluded:
        X_BL = X_BL if X_BL is not None else RigidTransform(robot.LIDAR_MOUNT_XYZ_M)
        x = (np.arange(config.width) + PIXEL_CENTER - center_x) / focal_x
        y = np.linspace(top, bottom, 1025)
        ray_C = np.stack(np.broadcast_arrays(x[None, :], y[:, None], 1.0), axis=-1).reshape(-1, 3)
        lowest_clear = -np.inf
        for X_LC in lidar_camera_poses(config):
            direction_B = ray_C @ (X_BL.rotation() @ X_LC.rotation()).matrix().T
            enter, _ = _chassis_box_interval(X_BL.translation(), direction_B, 0.0)
            clear = np.isinf(enter).reshape(len(y), len(x)).any(axis=1)
            lowest_clear = max(lowest_clear, y[np.flatnonzero(clear)].max(initial=-np.inf))
        # One sample below the lowest clear ray; below the optical axis (0 < center_y < height).
        bottom = min(bottom, max(lowest_clear + (y[1] - y[0]), 1e-3 * (bottom - top)))
    focal_y = config.height / (bottom - top)
    return CameraInfo(config.width, config.height, focal_x, focal_y, center_x, -top * focal_y)


def _chassis_box_interval(
    origin_B: np.ndarray, direction_B: np.ndarray, margin_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Where rays p_B = origin_B + t * direction_B (n, 3) are inside the chassis box grown by
    `margin_m`: t in [enter, leave]; enter = inf and leave = -inf for rays that miss it."""
    low = robot.chassis_center_in_body_frame() - robot.CHASSIS_SIZE_M / 2 - margin_m
    high = low + robot.CHASSIS_SIZE_M + 2 * margin_m
    with np.errstate(divide="ignore", invalid="ignore"):
        t_low = (low - origin_B) / direction_B
        t_high = (high - origin_B) / direction_B
    enter = np.nan_to_num(np.minimum(t_low, t_high), nan=-np.inf).max(axis=1)
    leave = np.nan_to_num(np.maximum(t_low, t_high), nan=np.inf).min(axis=1)
    hits = (enter <= leave) & (leave >= 0)
    return np.where(hits, enter, np.inf), np.where(hits, leave, -np.inf)


def lidar_camera_poses(config: LidarConfig) -> list[RigidTransform]:
    """X_LC for each camera, leftmost first (all at L's origin)."""
    R_LS = RotationMatrix.MakeYRotation(math.radians(config.pitch_deg))
    share = math.radians(config.horizontal_fov_deg) / config.num_cameras
    yaws = [math.radians(config.horizontal_fov_deg) / 2 - (i + 0.5) * share for i in range(config.num_cameras)]
    return [RigidTransform(R_LS @ RotationMatrix.MakeZRotation(yaw) @ _R_FC) for yaw in yaws]


class DepthImagesToLidarCloud(LeafSystem):
    """Merges the lidar cameras' depth images into point clouds in the lidar frame L.

    In a periodic unrestricted update (`config.period_s`, offset `config.offset_s`) it reads
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

    def __init__(self, config: LidarConfig | None = None, X_BL: RigidTransform | None = None):
        """Args:
            config: the lidar; None for `LidarConfig()`.
            X_BL: the lidar frame in the chassis body frame; None: p_BL = LIDAR_MOUNT_XYZ_M.

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
        self.DeclarePeriodicUnrestrictedUpdateEvent(config.period_s, config.offset_s, self._update)
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
        self._self_enter, self._self_leave = _chassis_box_interval(
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
        return np.where(keep, self._unit_rays_L * np.where(keep, distance, 0.0), np.nan)

    def _rng(self, context) -> np.random.Generator | None:
        if self._seed_port is None:
            return None
        u = self._seed_port.Eval(context)
        return np.random.default_rng([int(self._config.seed), int(u[0] * 2**32), int(u[1] * 2**32)])

    def _update(self, context, state) -> EventStatus:
        depths = [port.Eval(context).data for port in self._image_ports]
        points = self.organized_points_from_depths(depths, self._rng(context))
        state.get_mutable_abstract_state(self._organized_index).get_mutable_value().mutable_xyzs()[:] = points
        return EventStatus.Succeeded()

    def _calc_returns(self, context, output) -> None:
        points = context.get_abstract_state(self._organized_index).get_value().xyzs()
        returns = np.compress(~np.isnan(points[0]), points, axis=1)
        cloud = output.get_mutable_value()
        cloud.resize(returns.shape[1])
        cloud.mutable_xyzs()[:] = returns


@dataclass
class LidarHandles:
    """What `AddLidar` added.

    Attributes:
        converter: the `DepthImagesToLidarCloud`; its `point_cloud` and `organized_points`
            outputs are the lidar's (frame L), `organized_shape` their layout.
        sensors: the `RgbdSensor` cameras, leftmost first.
        noise_seed_source: the `RandomSource` feeding `noise_seed`; None when noise-free.
        X_BL: the lidar frame L in the chassis body frame B.
        renderer_name: the SceneGraph renderer the cameras use.
    """

    converter: DepthImagesToLidarCloud
    sensors: list[RgbdSensor]
    noise_seed_source: RandomSource | None
    X_BL: RigidTransform
    renderer_name: str


def MergeAnchoredPerceptionBoxes(scene_graph: SceneGraph, source_id: SourceId, faces: str = "up") -> int:
    """Replaces `source_id`'s anchored perception `Box`es by one mesh per diffuse colour.

    A renderer then draws a few actors instead of hundreds (`RenderEngineVtk` costs 10-35 us
    per actor per image on the CPU), and fewer triangles make each image cheaper still.
    `faces` chooses the boxes' faces a mesh keeps:

    - "up" (the default): every face whose outward normal points up (world z >
      `UP_FACE_MIN_NORMAL_Z`), about a third of the ditches' triangles: for terrain pieces
      seen from above the others are buried in the neighbouring pieces.
    - "top": only each box's own +z face where it points up, a sixth of the triangles,
      about half of "up"'s: the terrain's pieces are slabs whose +z face is the ground's
      surface (`DitchTerrain.box_pieces`, `DitchTerrain.pieces_height`), and the upper end
      faces of the wall slabs that "up" adds are buried too.
    - "all": all faces, the exact boxes.

    On random robot poses on the terrain both "up" and "top" see the same depth as "all"
    in all but a few pixels in a hundred thousand (slivers of box sides that stick out at
    the sine ditch's bends and the crater's rim; `tests/test_lidar.py`). "top" renders
    faster, most in the sine ditch (`python -m ditch_drake.benchmarks.bench_lidar sine 50
    top`), but those few pixels reach the policies' images and move some rollouts a little,
    so the default stays "up", with which every recorded result of the project was made.
    The boxes lose only their perception role; collision and illustration (Meshcat) are
    untouched. Each mesh copies the perception properties (label, colour) of its first
    box. Must run before a Context is created; a second call finds no boxes and does
    nothing.

    Raises:
        ValueError: `faces` is not "top", "up" or "all".

    Returns:
        The number of boxes merged.
    """
    if faces not in _FACE_CHOICES:
        raise ValueError(f"faces={faces!r} must be one of {_FACE_CHOICES}")
    inspector = scene_graph.model_inspector()
    groups: dict[tuple, list] = {}
    for geometry_id in inspector.GetGeometries(inspector.world_frame_id(), Role.kPerception):
        if not inspector.BelongsToSource(geometry_id, source_id) or not isinstance(
            inspector.GetShape(geometry_id), Box
        ):
            continue
        properties = inspector.GetPerceptionProperties(geometry_id)
        color = properties.GetPropertyOrDefault("phong", "diffuse", Rgba(0.9, 0.9, 0.9, 1.0))
        key = (color.r(), color.g(), color.b(), color.a())
        groups.setdefault(key, []).append(geometry_id)
    for index, geometry_ids in enumerate(groups.values()):
        boxes = [(inspector.GetShape(g).size(), inspector.GetPoseInFrame(g).GetAsMatrix34()) for g in geometry_ids]
        properties = PerceptionProperties(inspector.GetPerceptionProperties(geometry_ids[0]))
        name = f"merged_perception_boxes_{index}"
        min_normal_z = -np.inf if faces == "all" else UP_FACE_MIN_NORMAL_Z
        obj = _boxes_obj(boxes, min_normal_z, top_only=faces == "top")
        mesh = InMemoryMesh(mesh_file=MemoryFile(obj, ".obj", f"{name}.obj"))
        merged = scene_graph.RegisterAnchoredGeometry(source_id, GeometryInstance(RigidTransform(), Mesh(mesh), name))
        scene_graph.AssignRole(source_id, merged, properties)
        for geometry_id in geometry_ids:
            scene_graph.RemoveRole(source_id, geometry_id, Role.kPerception)
    return sum(len(ids) for ids in groups.values())


def RemoveSensorHousings(
    scene_graph: SceneGraph, source_id: SourceId, frame_id: FrameId, p_FL: np.ndarray
) -> list[str]:
    """Removes the perception role of `frame_id`'s geometries whose bounding box holds p_FL.

    A camera at the lidar's optical centre sits inside (or on) the lidar's own housing
    (`lidar_visual` of the Husky) and would see nothing else; a real lidar looks out through
    it. The housing stays in collision and illustration. `SceneGraph` has no way to hide a
    geometry from one renderer only, so no Drake camera renders it afterwards.

    Returns:
        The names of the geometries changed.
    """
    inspector = scene_graph.model_inspector()
    removed = []
    for geometry_id in inspector.GetGeometries(frame_id, Role.kPerception):
        obb = inspector.GetObbInGeometryFrame(geometry_id)
        if obb is None or not inspector.BelongsToSource(geometry_id, source_id):
            continue
        p_O = obb.pose().inverse() @ (inspector.GetPoseInFrame(geometry_id).inverse() @ p_FL)
        if np.all(np.abs(p_O) <= obb.half_width() + 1e-3):
            scene_graph.RemoveRole(source_id, geometry_id, Role.kPerception)
            removed.append(inspector.GetName(geometry_id))
    return removed


# Faces whose outward normal's world z is at most this face sideways or down: on terrain
# pieces seen from above they are buried in the neighbouring pieces.
UP_FACE_MIN_NORMAL_Z = 1e-3

# A unit cube's faces: outward normal and four corners (signs of x, y, z), counter-clockwise.
_CUBE_FACES = [
    ((1, 0, 0), [(1, -1, -1), (1, 1, -1), (1, 1, 1), (1, -1, 1)]),
    ((-1, 0, 0), [(-1, 1, -1), (-1, -1, -1), (-1, -1, 1), (-1, 1, 1)]),
    ((0, 1, 0), [(1, 1, -1), (-1, 1, -1), (-1, 1, 1), (1, 1, 1)]),
    ((0, -1, 0), [(-1, -1, -1), (1, -1, -1), (1, -1, 1), (-1, -1, 1)]),
    ((0, 0, 1), [(-1, -1, 1), (1, -1, 1), (1, 1, 1), (-1, 1, 1)]),
    ((0, 0, -1), [(-1, 1, -1), (1, 1, -1), (1, -1, -1), (-1, -1, -1)]),
]


def _boxes_obj(
    boxes: list[tuple[np.ndarray, np.ndarray]], min_normal_z: float = -np.inf, top_only: bool = False
) -> str:
    """OBJ text of boxes given as (size, X_WG as a 3 x 4 matrix), flat-shaded, keeping only
    the faces whose outward normal has a world z component above `min_normal_z`, and with
    `top_only` only each box's own +z face."""
    signs = np.array([corners for _, corners in _CUBE_FACES], dtype=float)  # (6, 4, 3)
    normals = np.array([normal for normal, _ in _CUBE_FACES], dtype=float)  # (6, 3)
    sizes = np.array([size for size, _ in boxes])
    X = np.array([pose for _, pose in boxes])  # (n, 3, 4)
    corners = (
        np.einsum("nij,nfkj->nfki", X[:, :, :3], signs[None] * sizes[:, None, None, :] / 2) + X[:, None, None, :, 3]
    )
    face_normals = np.einsum("nij,fj->nfi", X[:, :, :3], normals)  # (n, 6, 3)
    keep = face_normals[..., 2] > min_normal_z
    if top_only:
        keep &= normals[:, 2] > 0
    corners, face_normals = corners[keep], face_normals[keep]  # (m, 4, 3), (m, 3)
    quads = 1 + 4 * np.arange(len(corners))[:, None] + np.arange(4)  # 1-based vertex indices
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in corners.reshape(-1, 3)]
    lines += [f"vn {x:.6f} {y:.6f} {z:.6f}" for x, y, z in face_normals]
    lines += [
        f"f {a}//{k} {b}//{k} {c}//{k}\nf {a}//{k} {c}//{k} {d}//{k}" for k, (a, b, c, d) in enumerate(quads, start=1)
    ]
    return "\n".join(lines) + "\n"


def AddLidar(builder: DiagramBuilder, scene, config: LidarConfig | None = None, name: str = "lidar") -> LidarHandles:
    """Adds the lidar's cameras and converter to a scene built by `AddDitchScene`.

    The cameras are `RgbdSensor`s (depth only, `RenderEngineVtk`) on the chassis body at the
    `lidar_mount` pose, named `{name}_camera_{i}`; the converter is named `name` and, with
    noise, its seed source `{name}_noise_seed`. The renderer `config.renderer_name` is added
    to the scene graph if missing, the lidar's own housing is hidden from cameras
    (`RemoveSensorHousings`), and unless `config.merge_terrain_geometry` is False the
    plant's anchored perception boxes (the terrain) are merged for rendering
    (`MergeAnchoredPerceptionBoxes`; a scene-wide change for every renderer). Mesa's
    rasterizer threads are set from `config.rasterizer_threads` (a process-wide setting;
    see `LidarConfig`). Call it before `builder.Build()`.

    Args:
        builder: the builder holding the scene.
        scene: the handles from `AddDitchScene` (uses .plant, .scene_graph, .husky).
        config: the lidar; None for `LidarConfig()`.
        name: the converter's system name and the prefix of the others.

    Returns:
        The added systems and the mount pose.

    Raises:
        ValueError: a config value out of range (named).
    """
    config = config if config is not None else LidarConfig()
    config.validate()
    plant: MultibodyPlant = scene.plant
    scene_graph: SceneGraph = scene.scene_graph
    mount = plant.GetFrameByName("lidar_mount", scene.husky)
    X_BL = mount.GetFixedPoseInBodyFrame()
    body_frame_id = plant.GetBodyFrameIdOrThrow(mount.body().index())
    RemoveSensorHousings(scene_graph, plant.get_source_id(), body_frame_id, X_BL.translation())
    if config.merge_terrain_geometry:
        MergeAnchoredPerceptionBoxes(scene_graph, plant.get_source_id(), config.terrain_faces)
    if config.rasterizer_threads is not None:
        os.environ.setdefault("LP_NUM_THREADS", str(config.rasterizer_threads))
    if not scene_graph.HasRenderer(config.renderer_name):
        scene_graph.AddRenderer(config.renderer_name, MakeRenderEngineVtk(RenderEngineVtkParams()))
    info = lidar_camera_info(config, X_BL)
    near_m = 0.01
    core_clipping = ClippingRange(near_m, config.range_m + 0.1)
    converter = builder.AddNamedSystem(name, DepthImagesToLidarCloud(config, X_BL))
    sensors = []
    for i, X_LC in enumerate(lidar_camera_poses(config)):
        core = RenderCameraCore(config.renderer_name, info, core_clipping, RigidTransform())
        camera = DepthRenderCamera(core, DepthRange(near_m, config.range_m))
        sensor = builder.AddNamedSystem(f"{name}_camera_{i}", RgbdSensor(body_frame_id, X_BL @ X_LC, camera))
        builder.Connect(scene_graph.get_query_output_port(), sensor.query_object_input_port())
        builder.Connect(sensor.depth_image_32F_output_port(), converter.GetInputPort(f"depth_image_{i}"))
        sensors.append(sensor)
    source = None
    if config.noisy:
        source = builder.AddNamedSystem(
            f"{name}_noise_seed", RandomSource(RandomDistribution.kUniform, 2, config.period_s)
        )
        builder.Connect(source.get_output_port(0), converter.GetInputPort("noise_seed"))
    return LidarHandles(converter, sensors, source, X_BL, config.renderer_name)
