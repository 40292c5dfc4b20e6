"""The lidar in a scene: its depth cameras, its `DepthImagesToLidarCloud`, and the scene-graph
edits that make rendering them cheap.

Rendering cost (CPU: Mesa's llvmpipe through EGL): a `RenderEngineVtk` image costs about
0.4 ms plus 10-35 us per actor, and the ditch is 600-2000 boxes (about 20 ms an image). So
`AddLidar` merges the terrain's boxes into one mesh per colour holding only their upward
faces (`MergeAnchoredPerceptionBoxes`), and hides the lidar's own housing, inside which
the cameras sit (`RemoveSensorHousings`). Both change what every Drake camera sees; see
their docstrings.
"""

import os
from dataclasses import dataclass

import numpy as np
from pydrake.common import MemoryFile, RandomDistribution
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
from pydrake.math import RigidTransform
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import RandomSource
from pydrake.systems.sensors import RgbdSensor

from ditch_drake.perception.lidar_model import (
    TERRAIN_FACE_CHOICES,
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
    The fences of a walled field (geometry named `barrier_*`, `AddDitchTerrain`) stay boxes:
    they stand up, and their sides are what the lidar sees of them. The boxes merged lose
    only their perception role; collision and illustration (Meshcat) are untouched. Each mesh copies the perception properties (label, colour) of its first
    box. Must run before a Context is created; a second call finds no boxes and does
    nothing.

    Raises:
        ValueError: `faces` is not "top", "up" or "all".

    Returns:
        The number of boxes merged.
    """
    if faces not in TERRAIN_FACE_CHOICES:
        raise ValueError(f"faces={faces!r} must be one of {TERRAIN_FACE_CHOICES}")
    inspector = scene_graph.model_inspector()
    groups: dict[tuple, list] = {}
    for geometry_id in inspector.GetGeometries(inspector.world_frame_id(), Role.kPerception):
        if not inspector.BelongsToSource(geometry_id, source_id) or not isinstance(
            inspector.GetShape(geometry_id), Box
        ) or inspector.GetName(geometry_id).rpartition("::")[2].startswith(UNMERGED_PREFIX):
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


# Anchored boxes whose (unscoped) names start with this are never merged: the walls' boxes.
UNMERGED_PREFIX = "barrier_"

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
