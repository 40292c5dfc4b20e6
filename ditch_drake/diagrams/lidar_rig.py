"""The lidar in a scene: its depth cameras, its `DepthImagesToLidarCloud`, and the scene-graph
edits that make rendering them cheap.

Rendering cost (CPU: Mesa's llvmpipe through EGL): a `RenderEngineVtk` image costs about
0.4 ms plus 10-35 us per actor, and the ditch is 600-2000 boxes (about 20 ms an image). So
`AddLidar` gives the terrain its perception geometry as one mesh per kind of piece holding
only the boxes' upward faces (`AddTerrainPerception`), and hides the lidar's own housing,
inside which the cameras sit (`RemoveSensorHousings`). Both change what every Drake camera
sees; see their docstrings.
"""

import os
from dataclasses import dataclass

import numpy as np
from pydrake.common import RandomDistribution
from pydrake.geometry import (
    ClippingRange,
    DepthRange,
    DepthRenderCamera,
    FrameId,
    MakeRenderEngineVtk,
    RenderCameraCore,
    RenderEngineVtkParams,
    Role,
    SceneGraph,
    SourceId,
)
from pydrake.math import RigidTransform
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import RandomSource
from pydrake.systems.sensors import RgbdSensor

from ditch_drake.common.native_libraries import load_triton_before_mesa
from ditch_drake.diagrams.ditch_scene import AddTerrainPerception
from ditch_drake.perception.lidar_model import (
    LidarConfig,
    lidar_camera_info,
    lidar_camera_poses,
)
from ditch_drake.systems.lidar import DepthImagesToLidarCloud


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


def AddLidar(builder: DiagramBuilder, scene, config: LidarConfig | None = None, name: str = "lidar") -> LidarHandles:
    """Adds the lidar's cameras and converter to a scene built by `AddDitchScene`.

    The cameras are `RgbdSensor`s (depth only, `RenderEngineVtk`) on the chassis body at the
    `lidar_mount` pose, named `{name}_camera_{i}`; the converter is named `name` and, with
    noise, its seed source `{name}_noise_seed`. The renderer `config.renderer_name` is added
    to the scene graph if missing, the lidar's own housing is hidden from cameras
    (`RemoveSensorHousings`), and the terrain gets its perception geometry
    (`AddTerrainPerception`: one mesh per kind of piece with `config.terrain_faces`, or every
    box with `merge_terrain_geometry` False; the first lidar's choice holds for every
    renderer of the scene). Mesa's
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
    AddTerrainPerception(scene, config.terrain_faces if config.merge_terrain_geometry else None)
    if config.rasterizer_threads is not None:
        os.environ.setdefault("LP_NUM_THREADS", str(config.rasterizer_threads))
    if not scene_graph.HasRenderer(config.renderer_name):
        load_triton_before_mesa()  # Before Mesa's LLVM: see ditch_drake.common.native_libraries.
        scene_graph.AddRenderer(config.renderer_name, MakeRenderEngineVtk(RenderEngineVtkParams()))
    info = lidar_camera_info(config, X_BL)
    near_m = 0.01
    core_clipping = ClippingRange(near_m, config.range_m + 0.1)
    schedule = scene.schedule
    converter = builder.AddNamedSystem(name, DepthImagesToLidarCloud(
        config, X_BL, period_s=schedule.control_period_s, offset_s=schedule.lidar_offset_s))
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
            f"{name}_noise_seed", RandomSource(RandomDistribution.kUniform, 2, schedule.control_period_s)
        )
        builder.Connect(source.get_output_port(0), converter.GetInputPort("noise_seed"))
    return LidarHandles(converter, sensors, source, X_BL, config.renderer_name)
