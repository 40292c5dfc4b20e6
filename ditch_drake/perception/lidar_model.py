"""The lidar's model (docs/design.md, "The observation"): its settings, and the geometry of the depth cameras that
emulate it (Drake has no ray casting, drake#15260). The LeafSystem that turns their images
into clouds is `ditch_drake.systems.lidar`; `ditch_drake.diagrams.lidar_rig` adds it all to a
scene.


The lidar is modelled by `num_cameras` depth-only pinhole cameras (`RgbdSensor` with a
`DepthRenderCamera`, rendered headless by `RenderEngineVtk`) side by side at the Husky's
`lidar_mount` frame. `DepthImagesToLidarCloud` (`ditch_drake.systems.lidar`) turns their depth images into points at the
control rate and keeps the returns inside the lidar's field of view and range. `AddLidar`
(`ditch_drake.diagrams.lidar_rig`) wires it all into a scene from `AddDitchScene`.

Frames:
    B: the chassis body frame (`ditch_drake.spec.robot`).
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
"""

import math
from dataclasses import dataclass

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.sensors import CameraInfo

from ditch_drake.spec import robot
from ditch_drake.world.box_mesh import FACE_CHOICES

# `RenderEngineVtk` (Drake 1.51) renders pixel (u, v) along the ray through the image point
# (u + 0.5, v + 0.5) of the `CameraInfo` pinhole model (the principal point counted from the
# image's corner), not through (u, v) as the `CameraInfo` docs have it: measured on flat
# ground, the returns are exact with this offset and up to half a pixel off without it.
PIXEL_CENTER = 0.5

# The choices of `LidarConfig.terrain_faces` (`ditch_drake.world.box_mesh.boxes_obj`'s `faces`).
TERRAIN_FACE_CHOICES = FACE_CHOICES

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
        crop_self_occluded: leave out the image rows below the lowest ray that can miss the
            chassis: they only ever see the chassis top (see `lidar_camera_info`).
        renderer_name: the SceneGraph renderer the cameras use (added if missing).
        merge_terrain_geometry: render the terrain's boxes as one mesh per kind of piece (fast)
            instead of box by box (`ditch_drake.diagrams.ditch_scene.AddTerrainPerception`).
        terrain_faces: which of the merged boxes' faces are rendered: "top", "up" or "all"
            (`ditch_drake.world.box_mesh.boxes_obj`).
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
            ("seed", self.seed, isinstance(self.seed, int) and self.seed >= 0, "an int >= 0"),
            ("terrain_faces", self.terrain_faces, self.terrain_faces in TERRAIN_FACE_CHOICES, f"one of {TERRAIN_FACE_CHOICES}"),
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
            enter, _ = chassis_box_interval(X_BL.translation(), direction_B, 0.0)
            clear = np.isinf(enter).reshape(len(y), len(x)).any(axis=1)
            lowest_clear = max(lowest_clear, y[np.flatnonzero(clear)].max(initial=-np.inf))
        # One sample below the lowest clear ray; below the optical axis (0 < center_y < height).
        bottom = min(bottom, max(lowest_clear + (y[1] - y[0]), 1e-3 * (bottom - top)))
    focal_y = config.height / (bottom - top)
    return CameraInfo(config.width, config.height, focal_x, focal_y, center_x, -top * focal_y)


def chassis_box_interval(
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
