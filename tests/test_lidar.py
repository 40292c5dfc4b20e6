"""The lidar (`ditch_drake.systems.lidar`): rendered depth -> point cloud in the lidar frame L."""

import math
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from pydrake.common import RandomGenerator
from pydrake.geometry import Role
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import CacheIndex, Diagram, DiagramBuilder
from pydrake.systems.sensors import ImageDepth32F

from ditch_drake.diagrams.ditch_scene import AddDitchScene, AddTerrainPerception, DitchScene, SceneConfig
from ditch_drake.diagrams.lidar_rig import AddLidar, LidarHandles
from ditch_drake.perception.lidar_model import LidarConfig, lidar_camera_info, lidar_camera_poses
from ditch_drake.spec import robot
from ditch_drake.systems.lidar import DepthImagesToLidarCloud
from ditch_drake.world.box_mesh import boxes_obj


@dataclass
class Setup:
    diagram: Diagram
    scene: DitchScene
    lidar: LidarHandles


def _build(environment: str, config: LidarConfig | None = None) -> Setup:
    builder = DiagramBuilder()
    scene = AddDitchScene(builder, SceneConfig(environment=environment))
    lidar = AddLidar(builder, scene, config)
    return Setup(builder.Build(), scene, lidar)


@pytest.fixture(scope="module")
def wide() -> Setup:
    return _build("wide")


@pytest.fixture(scope="module")
def crater() -> Setup:
    return _build("crater")


def _chassis(setup: Setup):
    return setup.scene.plant.GetBodyByName("chassis", setup.scene.husky)


def _scan(setup: Setup, X_WB: RigidTransform | None = None, context=None):
    """Sets the chassis pose (None: the task's start), forces the lidar update.

    Returns (p_L (3, n), organized (3, rows * cols), X_WL).
    """
    context = context if context is not None else setup.diagram.CreateDefaultContext()
    plant = setup.scene.plant
    plant_context = plant.GetMyMutableContextFromRoot(context)
    if X_WB is not None:
        plant.SetFreeBodyPose(plant_context, _chassis(setup), X_WB)
    converter = setup.lidar.converter
    converter_context = converter.GetMyMutableContextFromRoot(context)
    converter.ExecuteForcedEvents(converter_context)
    cloud = converter.GetOutputPort("point_cloud").Eval(converter_context)
    organized = converter.GetOutputPort("organized_points").Eval(converter_context)
    X_WL = plant.EvalBodyPoseInWorld(plant_context, _chassis(setup)) @ setup.lidar.X_BL
    return cloud.xyzs().astype(float), organized.xyzs().astype(float), X_WL


def _on_hinge_nose_down(setup: Setup, pitch_deg: float = 35.0) -> RigidTransform:
    """Facing +y across the ditch from the south, chassis origin over the hinge line, nose down."""
    y = -setup.scene.terrain.hinge_distance_m
    z = float(setup.scene.terrain.height(np.array([0.0, y]))) + 0.2
    return RigidTransform(RollPitchYaw(0.0, math.radians(pitch_deg), math.pi / 2), [0.0, y, z])


def _inside_chassis_box(p_L: np.ndarray, X_BL: RigidTransform, margin_m: float) -> np.ndarray:
    p_B = X_BL.multiply(p_L)
    half = robot.CHASSIS_SIZE_M[:, None] / 2 + margin_m
    return np.all(np.abs(p_B - robot.chassis_center_in_body_frame()[:, None]) <= half, axis=0)


@pytest.mark.parametrize("environment", ["wide", "crater"])
def test_cloud_is_within_range_and_field_of_view(environment, request):
    setup = request.getfixturevalue(environment)
    config = setup.lidar.converter.config
    p_L, organized, _ = _scan(setup)
    assert p_L.shape[1] > 500
    distance = np.linalg.norm(p_L, axis=0)
    assert distance.max() <= config.range_m + 1e-5
    assert distance.min() >= config.min_range_m - 1e-5
    # Azimuth and elevation in the sensor frame S (L pitched down by pitch_deg).
    p_S = RotationMatrix.MakeYRotation(math.radians(config.pitch_deg)).inverse().multiply(p_L)
    azimuth = np.degrees(np.arctan2(p_S[1], p_S[0]))
    elevation = np.degrees(np.arctan2(p_S[2], np.hypot(p_S[0], p_S[1])))
    assert np.abs(azimuth).max() <= config.horizontal_fov_deg / 2 + 1e-3
    assert np.abs(elevation).max() <= config.vertical_fov_deg / 2 + 1e-3
    # Both halves of the field of view return (two cameras, leftmost first).
    assert (azimuth > 30).any() and (azimuth < -30).any()
    # The organized cloud: rows * cols points, NaN where no return; its returns are the cloud.
    rows, cols = setup.lidar.converter.organized_shape
    assert organized.shape == (3, rows * cols)
    assert cols == config.num_cameras * config.width
    returned = ~np.isnan(organized[0])
    np.testing.assert_array_equal(organized[:, returned], p_L)
    grid = organized.reshape(3, rows, cols)
    left = grid[1, :, : cols // 2]
    right = grid[1, :, cols // 2 :]
    assert np.nanmin(left) > np.nanmax(right)  # +y (left) in the left half


def test_point_cloud_follows_every_update(wide):
    # `point_cloud` is computed from the organized state when read: empty before the first
    # update, and the returns of the newest update after each, in one Context.
    context = wide.diagram.CreateDefaultContext()
    converter = wide.lidar.converter
    converter_context = converter.GetMyContextFromRoot(context)
    assert converter.GetOutputPort("point_cloud").Eval(converter_context).size() == 0
    sizes = []
    for X_WB in (None, _on_hinge_nose_down(wide)):
        p_L, organized, _ = _scan(wide, X_WB, context)
        np.testing.assert_array_equal(p_L, organized[:, ~np.isnan(organized[0])])
        sizes.append(p_L.shape[1])
    assert sizes[0] > 500 and sizes[1] > 500 and sizes[0] != sizes[1]


def test_no_point_inside_the_chassis_box():
    # Rendered: uncropped, so the cameras' lower rows see the chassis top.
    config = LidarConfig(width=32, height=24, crop_self_occluded=False)
    setup = _build("wide", config)
    context = setup.diagram.CreateDefaultContext()
    p_L, _, _ = _scan(setup, context=context)
    depths = [
        sensor.depth_image_32F_output_port().Eval(sensor.GetMyContextFromRoot(context)).data
        for sensor in setup.lidar.sensors
    ]
    assert sum(((d > 0) & (d < 0.3)).sum() for d in depths) > 50  # the chassis top is in view
    assert p_L.shape[1] > 100
    assert not _inside_chassis_box(p_L, setup.lidar.X_BL, 0.01).any()


def test_converter_drops_self_returns_of_any_depth():
    # A LeafSystem test: every pixel at one depth; rays that end inside the chassis box are dropped.
    config = LidarConfig(width=24, height=16, crop_self_occluded=False)
    # A mount just above the chassis top, so that the steep rays end inside the chassis.
    X_BL = RigidTransform([0.40, 0.0, 0.42])
    converter = DepthImagesToLidarCloud(config, X_BL)
    context = converter.CreateDefaultContext()
    info = lidar_camera_info(config, X_BL)
    u, v = np.meshgrid(np.arange(config.width) + 0.5, np.arange(config.height) + 0.5)
    ray_C = np.stack([(u - info.center_x()) / info.focal_x(), (v - info.center_y()) / info.focal_y(), np.ones(u.shape)])
    for depth in (0.12, 0.2, 0.28):
        image = ImageDepth32F(config.width, config.height)
        image.mutable_data[:] = depth
        for i in range(config.num_cameras):
            converter.GetInputPort(f"depth_image_{i}").FixValue(context, image)
        converter.ExecuteForcedEvents(context)
        p_L = converter.GetOutputPort("point_cloud").Eval(context).xyzs().astype(float)
        raw = np.concatenate(
            [X_LC.rotation().multiply(depth * ray_C.reshape(3, -1)) for X_LC in lidar_camera_poses(config)], axis=1
        )
        inside = _inside_chassis_box(raw, X_BL, config.self_filter_margin_m)
        assert inside.sum() > 10  # without the filter these would be returns
        assert 0 < p_L.shape[1] <= raw.shape[1] - inside.sum()
        assert not _inside_chassis_box(p_L, X_BL, config.self_filter_margin_m - 1e-4).any()


@pytest.mark.parametrize(
    ("environment", "on_hinge", "tolerance_m"),
    # Flat ground is exact (a ray model half a pixel off errs by up to 4 cm at 4 m); on the
    # walls the terrain's box pieces follow the analytic height within about 3 cm.
    [("wide", False, 0.005), ("crater", False, 0.005), ("wide", True, 0.03), ("crater", True, 0.03)],
)
def test_points_lie_on_the_terrain(environment, on_hinge, tolerance_m, request):
    setup = request.getfixturevalue(environment)
    X_WB = _on_hinge_nose_down(setup) if on_hinge else None
    p_L, _, X_WL = _scan(setup, X_WB)
    assert p_L.shape[1] > 100
    p_W = X_WL.multiply(p_L)
    height = setup.scene.terrain.height(p_W[:2].T)
    np.testing.assert_array_less(np.abs(p_W[2] - height), tolerance_m)


def _random_terrain_poses(terrain, count: int, seed: int, max_tilt_deg: float = 40.0) -> list[RigidTransform]:
    """Chassis poses 0.25 m above the terrain, z along its normal (tilts up to `max_tilt_deg`), random yaw."""
    rng = np.random.default_rng(seed)
    low, high = terrain.bounds_xy()
    poses = []
    while len(poses) < count:
        xy = rng.uniform(low, high)
        normal = terrain.normal(xy[None])[0]
        if normal[2] < math.cos(math.radians(max_tilt_deg)):
            continue
        yaw = rng.uniform(-math.pi, math.pi)
        heading = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        x = heading - normal * normal.dot(heading)
        x /= np.linalg.norm(x)
        R_WB = RotationMatrix(np.column_stack([x, np.cross(normal, x), normal]))
        poses.append(RigidTransform(R_WB, [*xy, float(terrain.height(xy[None])[0]) + 0.25]))
    return poses


@pytest.mark.parametrize("faces", ["up", "top"])
@pytest.mark.parametrize("environment", ["sine", "crater"])
def test_merged_terrain_mesh_renders_like_the_boxes(environment, faces):
    # The lidar renders only some faces of the terrain's boxes; every face of every box must see the same.
    exact = _build(environment, LidarConfig(terrain_faces="all"))
    merged = _build(environment, LidarConfig(terrain_faces=faces))
    poses = _random_terrain_poses(merged.scene.terrain, count=25, seed=1)
    differ = total = 0
    for X_WB in poses:
        _, organized_exact, _ = _scan(exact, X_WB)
        _, organized_merged, _ = _scan(merged, X_WB)
        same = (np.isnan(organized_exact) & np.isnan(organized_merged)) | (
            np.abs(organized_exact - organized_merged) < 1e-4
        )
        differ += (~same.all(axis=0)).sum()
        total += same.shape[1]
        assert np.isfinite(organized_merged).all(axis=0).sum() > 100
    assert differ <= 1e-3 * total


def test_terrain_perception_rejects_unknown_faces():
    builder = DiagramBuilder()
    scene = AddDitchScene(builder, SceneConfig(environment="wide"))
    with pytest.raises(ValueError, match="faces='bottom'"):
        AddTerrainPerception(scene, faces="bottom")


def test_terrain_perception_is_added_once_by_the_first_lidar():
    builder = DiagramBuilder()
    scene = AddDitchScene(builder, SceneConfig(environment="wide"))
    assert AddTerrainPerception(scene, faces="top") == 3  # floor, wall and ground meshes
    assert AddTerrainPerception(scene, faces=None) == 0
    AddLidar(builder, scene, LidarConfig(merge_terrain_geometry=False))
    inspector = scene.scene_graph.model_inspector()
    names = [inspector.GetName(g) for g in inspector.GetGeometries(inspector.world_frame_id(), Role.kPerception)]
    assert sorted(n for n in names if n.startswith("terrain_")) == [
        "terrain_perception_floor", "terrain_perception_ground", "terrain_perception_wall"]


def test_unmerged_terrain_renders_every_box():
    setup = _build("crater", LidarConfig(merge_terrain_geometry=False))
    inspector = setup.scene.scene_graph.model_inspector()
    perceived = [g for g in inspector.GetGeometries(inspector.world_frame_id(), Role.kPerception)
                 if inspector.GetName(g).startswith("terrain_perception_")]
    assert len(perceived) == len(setup.scene.terrain.box_pieces())
    assert np.isfinite(_scan(setup)[1]).all(axis=0).sum() > 100


def test_sees_into_the_ditch_from_its_edge(wide):
    p_L, _, X_WL = _scan(wide, _on_hinge_nose_down(wide))
    p_W = X_WL.multiply(p_L)
    assert (p_W[2] < -1.0).sum() >= 50


def test_noise_is_repeatable_per_seed():
    config = LidarConfig(width=32, height=24, noise_std_m=0.05, dropout_probability=0.2)
    setup = _build("wide", config)
    assert setup.lidar.noise_seed_source is not None

    def scan(seed: int) -> np.ndarray:
        context = setup.diagram.CreateDefaultContext()
        setup.diagram.SetRandomContext(context, RandomGenerator(seed))
        p_L, _, _ = _scan(
            setup, X_WB=RigidTransform(RotationMatrix.MakeZRotation(math.pi / 2), [0, -11, 0.17]), context=context
        )
        return p_L

    first, again, other = scan(7), scan(7), scan(8)
    np.testing.assert_array_equal(first, again)
    assert first.shape != other.shape or not np.array_equal(first, other)
    assert np.linalg.norm(first, axis=0).max() <= config.range_m + 1e-5


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("range_m", 0.0),
        ("range_m", -1.0),
        ("horizontal_fov_deg", 180.0),
        ("vertical_fov_deg", 200.0),
        ("width", 0),
        ("num_cameras", 0),
        ("dropout_probability", 1.0),
        ("noise_std_m", -0.1),
        ("min_range_m", 5.0),
        ("rasterizer_threads", -1),
        ("terrain_faces", "bottom"),
    ],
)
def test_bad_config_names_the_value(field, value):
    with pytest.raises(ValueError, match=rf"{field}={value!r}"):
        DepthImagesToLidarCloud(LidarConfig(**{field: value}))


def test_rasterizer_threads_are_set_for_the_process_unless_already_set(monkeypatch):
    monkeypatch.delenv("LP_NUM_THREADS", raising=False)
    _build("crater", LidarConfig(rasterizer_threads=None))
    assert "LP_NUM_THREADS" not in os.environ
    _build("crater")
    assert os.environ["LP_NUM_THREADS"] == "0"
    monkeypatch.setenv("LP_NUM_THREADS", "2")
    _build("crater", LidarConfig(rasterizer_threads=0))
    assert os.environ["LP_NUM_THREADS"] == "2"


_RENDER_ONE_CLOUD = """
import sys, numpy as np
from pydrake.systems.framework import DiagramBuilder
from ditch_drake.diagrams.ditch_scene import AddDitchScene, SceneConfig
from ditch_drake.diagrams.lidar_rig import AddLidar
builder = DiagramBuilder()
lidar = AddLidar(builder, AddDitchScene(builder, SceneConfig(environment="sine", task=1)))
diagram = builder.Build()
context = diagram.CreateDefaultContext()
converter_context = lidar.converter.GetMyMutableContextFromRoot(context)
lidar.converter.ExecuteForcedEvents(converter_context)
np.save(sys.argv[1], lidar.converter.GetOutputPort("organized_points").Eval(converter_context).xyzs())
"""


def test_rasterizer_threads_do_not_change_the_cloud(tmp_path):
    # Mesa reads LP_NUM_THREADS once per process, so each setting renders in a process of its own.
    clouds = []
    for threads in ("0", "2"):
        path = tmp_path / f"cloud_{threads}.npy"
        subprocess.run([sys.executable, "-c", _RENDER_ONE_CLOUD, str(path)], check=True,
                       env={**os.environ, "LP_NUM_THREADS": threads}, timeout=120)
        clouds.append(np.load(path))
    assert np.isfinite(clouds[0]).any()
    np.testing.assert_array_equal(clouds[0], clouds[1])


def _output_cache_entry(system, port_name: str):
    """The cache entry of `system`'s output port `port_name` (found by its description)."""
    for index in range(64):
        entry = system.get_cache_entry(CacheIndex(index))
        if entry is not None and f"({port_name})" in entry.description():
            return entry
    raise LookupError(port_name)


def test_renders_only_at_the_control_rate(wide):
    simulator = Simulator(wide.diagram)
    context = simulator.get_mutable_context()
    wide.scene.drive.GetInputPort("command").FixValue(wide.scene.drive.GetMyContextFromRoot(context), [1.0, 0.0])
    sensor = wide.lidar.sensors[0]
    sensor_context = sensor.GetMyContextFromRoot(context)
    # The depth output's cache entry holds the last rendered image: mark it after every
    # physics step and count the steps after which a render has overwritten the mark.
    entry = _output_cache_entry(sensor, "depth_image_32f")
    simulator.Initialize()
    image = entry.get_cache_entry_value(sensor_context).GetMutableValueOrThrow()
    plant_step = wide.scene.plant.time_step()
    renders, steps = 0, round(1.0 / plant_step)
    for k in range(1, steps + 1):
        image.mutable_data[0, 0, 0] = -1.0
        simulator.AdvanceTo(k * plant_step)
        renders += bool(image.data[0, 0, 0] != -1.0)
    control_ticks = round(1.0 / robot.CONTROL_PERIOD_S)
    assert steps == 50
    assert control_ticks - 1 <= renders <= control_ticks + 1


@pytest.mark.parametrize("faces, triangles", [("all", 12), ("up", 2), ("top", 2)])
def test_box_mesh_keeps_the_faces_asked_for(faces, triangles):
    tilted = RigidTransform(RollPitchYaw(0.0, 0.3, 0.0), [1.0, 2.0, -0.5]).GetAsMatrix34()
    flat = RigidTransform([0.0, 0.0, -0.5]).GetAsMatrix34()
    obj = boxes_obj([(np.array([1.0, 2.0, 1.0]), flat)], faces)
    assert obj.count("\nf ") == triangles
    # A tilted box shows its top and one end face upwards; "top" keeps only the top.
    tilted_obj = boxes_obj([(np.array([1.0, 2.0, 1.0]), tilted)], faces)
    assert tilted_obj.count("\nf ") == {"all": 12, "up": 4, "top": 2}[faces]
    with pytest.raises(ValueError, match="faces='side'"):
        boxes_obj([(np.array([1.0, 1.0, 1.0]), flat)], "side")


@pytest.mark.parametrize("noisy", [False, True])
def test_update_stores_the_organized_points_of_recorded_depths_bit_for_bit(noisy):
    # Depth images the lidar's cameras rendered in a learned rollout (`ditch-drake evaluate --env
    # wide --task 1 --seed 300`, control steps `rollout_steps`). The update writes the points
    # straight into the cloud; they must be the float32 of the float64 points that the code
    # before that change computed and assigned.
    depths = np.load(Path(__file__).parent / "data" / "lidar_depths_recorded.npz")["depths"]
    config = LidarConfig(noise_std_m=0.02, dropout_probability=0.1) if noisy else LidarConfig()
    converter = DepthImagesToLidarCloud(config)
    context = converter.CreateDefaultContext()
    if noisy:
        converter.GetInputPort("noise_seed").FixValue(context, [0.25, 0.75])
    for cameras in depths:
        for i, depth in enumerate(cameras):
            image = ImageDepth32F(config.width, config.height)
            image.mutable_data[:] = depth
            converter.GetInputPort(f"depth_image_{i}").FixValue(context, image)
        distance, keep = converter._ranges(list(cameras), converter._rng(context))
        before = np.where(keep, converter._unit_rays_L * np.where(keep, distance, 0.0), np.nan)
        assert 0 < keep.sum() < keep.size
        converter.ExecuteForcedEvents(context)
        stored = converter.GetOutputPort("organized_points").Eval(context).xyzs()
        assert stored.tobytes() == np.asarray(before, dtype=np.float32).tobytes()
        if not noisy:
            assert converter.organized_points_from_depths(list(cameras)).tobytes() == before.tobytes()
