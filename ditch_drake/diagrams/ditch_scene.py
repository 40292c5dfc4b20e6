"""The Husky and a ditch in one MultibodyPlant, with drive and episode monitor."""

import ctypes
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np
from pydrake.common import MemoryFile
from pydrake.common.eigen_geometry import Quaternion_
from pydrake.geometry import (
    Box,
    Convex,
    GeometryInstance,
    InMemoryMesh,
    MakePhongIllustrationProperties,
    Mesh,
    Meshcat,
    PerceptionProperties,
    ProximityProperties,
    RenderLabel,
    Rgba,
    Role,
    SceneGraph,
)
from pydrake.lcm import DrakeLcm
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import (
    AddMultibodyPlant,
    CoulombFriction,
    MultibodyPlant,
    MultibodyPlantConfig,
)
from pydrake.multibody.tree import JointActuatorIndex, ModelInstanceIndex, PdControllerGains, QuaternionFloatingJoint
from pydrake.symbolic import Expression, Variable, cos, sin
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.lcm import LcmInterfaceSystem
from pydrake.visualization import ApplyVisualizationConfig, VisualizationConfig

from ditch_drake.spec import robot
from ditch_drake.spec.schedule import ScheduleConfig
from ditch_drake.systems.episode_monitor import EpisodeConfig, EpisodeMonitor
from ditch_drake.systems.skid_steer_drive import SkidSteerDrive
from ditch_drake.world.box_mesh import FACE_CHOICES, boxes_obj
from ditch_drake.world.environments import ConfigError, Environment, Task, get_environment, get_task
from ditch_drake.world.terrain import BoxPiece, ConvexPiece, DitchTerrain

TERRAIN_COLORS = {
    "ground": np.array([0.45, 0.62, 0.33, 1.0]),
    "wall": np.array([0.55, 0.42, 0.28, 1.0]),
    "floor": np.array([0.48, 0.37, 0.25, 1.0]),
    "barrier": np.array([0.62, 0.62, 0.66, 1.0]),
}


def DefaultPlantConfig() -> MultibodyPlantConfig:
    """Point contact on box pieces with a 20 ms discrete step (docs/concepts/physics.md)."""
    return MultibodyPlantConfig(time_step=0.02, contact_model="point", discrete_contact_approximation="lagged")


@dataclass
class StartJitter:
    """Uniform start-pose perturbation half-widths (m, deg), drawn from the context's seed."""

    xy_m: float = 0.25
    yaw_deg: float = 3.0


@dataclass
class SceneConfig:
    """What `MakeDitchDiagram` builds.

    Attributes:
        environment: a name from the environments file.
        task: index of the environment's start/goal task.
        environments_file: a YAML file of environments; empty for the packaged one.
        environments: environments defined inline, in the schema of one entry of the
            environments file; `environment` may name one of them.
        plant: Drake's own plant configuration.
        start_jitter: seeded start perturbation (see `SetEpisodeSeed`).
        episode: when the episode ends.
        schedule: the control period and each stage's offset, passed down to every block.
    """

    environment: str = "wide"
    task: int = 0
    environments_file: str = ""
    environments: dict[str, Environment] = field(default_factory=dict)
    plant: MultibodyPlantConfig = field(default_factory=DefaultPlantConfig)
    start_jitter: StartJitter = field(default_factory=StartJitter)
    episode: EpisodeConfig = field(default_factory=EpisodeConfig)
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)


@dataclass
class DitchScene:
    """Handles to the parts of a built scene."""

    plant: MultibodyPlant
    scene_graph: SceneGraph
    husky: ModelInstanceIndex
    drive: SkidSteerDrive
    monitor: EpisodeMonitor
    terrain: DitchTerrain
    environment: Environment
    task: Task
    episode: EpisodeConfig
    schedule: ScheduleConfig
    environment_name: str = ""
    task_index: int = 0


def models_package_xml() -> Path:
    """The `package.xml` of `models_sdf/` (installed as `ditch_drake.models_sdf`)."""
    return Path(str(resources.files("ditch_drake.models_sdf") / "package.xml"))


def MakeParser(plant: MultibodyPlant) -> Parser:
    """A parser that resolves `package://ditch_drake/...` to `models_sdf/`."""
    parser = Parser(plant)
    parser.package_map().AddPackageXml(str(models_package_xml()))
    return parser


def AddDitchTerrain(plant: MultibodyPlant, terrain: DitchTerrain) -> int:
    """Welds the terrain and its walls to the world: `DitchTerrain.collision_pieces` as
    collision geometry (named `terrain_*`), `DitchTerrain.box_pieces` for illustration as one
    mesh per kind of piece (`terrain_<kind>`: what Meshcat shows), and the walls' boxes
    (`barrier_*`) for collision, illustration and perception. The terrain's perception
    geometry (what cameras see) is the lidar's to add, with the faces it renders
    (`AddTerrainPerception`, called by `AddLidar`).

    The collision set is the smaller one: SceneGraph's collision filter costs memory and time
    with the square of the number of collision geometries (see `collision_pieces`); every
    geometry registered costs time growing with those already registered, so the visual
    pieces go in as a few meshes (`ditch_drake.world.box_mesh`).

    Returns the number of visual pieces.
    """
    ground_friction = CoulombFriction(robot.TERRAIN_FRICTION, robot.TERRAIN_FRICTION)
    properties = ProximityProperties()
    properties.AddProperty("material", "coulomb_friction", ground_friction)
    walls = [(f"barrier_{index}", piece) for index, piece in enumerate(terrain.wall_pieces())]
    collision = [(f"terrain_{piece.kind}_{index}", piece) for index, piece in enumerate(terrain.collision_pieces())]
    world = plant.world_body()
    for name, piece in collision + walls:
        plant.RegisterCollisionGeometry(world, _piece_pose(piece), _piece_shape(piece, name), name, properties)
    visual = terrain.box_pieces()
    for kind, boxes in _boxes_by_kind(visual).items():
        name = f"terrain_{kind}"
        mesh = Mesh(InMemoryMesh(mesh_file=MemoryFile(boxes_obj(boxes, "all"), ".obj", f"{name}.obj")))
        instance = GeometryInstance(RigidTransform(), mesh, name)
        instance.set_illustration_properties(MakePhongIllustrationProperties(TERRAIN_COLORS[kind]))
        plant.RegisterVisualGeometry(world, instance)
    for name, piece in walls:
        plant.RegisterVisualGeometry(world, _piece_pose(piece), Box(*piece.size), name, TERRAIN_COLORS[piece.kind])
    return len(visual) + len(walls)


# The terrain's perception geometry: `terrain_perception_<kind>` meshes or, unmerged,
# `terrain_perception_<kind>_<index>` boxes.
TERRAIN_PERCEPTION_PREFIX = "terrain_perception_"


def AddTerrainPerception(scene: "DitchScene", faces: str | None = "up") -> int:
    """Adds the terrain's pieces (`DitchTerrain.box_pieces`) to `scene`'s scene graph for
    perception (every camera's renderer), unless an earlier call did.

    `faces`: the faces of the boxes rendered, as one mesh per kind of piece
    (`ditch_drake.world.box_mesh.boxes_obj`: "up", "top" or "all"); None: every box on its
    own. The properties are those `MultibodyPlant` gives the world's visual geometry: the
    piece's colour and the world body's render label. Must run before a Context is created.

    From above, "up" and "top" see the depth the whole boxes show in all but a few pixels in
    a hundred thousand (slivers of box sides at the sine's bends and the crater's rim;
    `tests/test_lidar.py`); "top", half the triangles, renders faster, but those pixels reach
    the policies' images and move some rollouts a little, so the default stays "up", with
    which every recorded result was made.

    Raises:
        ValueError: `faces` is not None, "top", "up" or "all".

    Returns:
        The number of geometries added (0: the terrain had its perception geometry already).
    """
    if faces is not None and faces not in FACE_CHOICES:
        raise ValueError(f"faces={faces!r} must be one of {FACE_CHOICES} or None")
    scene_graph, plant = scene.scene_graph, scene.plant
    source_id = plant.get_source_id()
    inspector = scene_graph.model_inspector()
    for geometry_id in inspector.GetGeometries(inspector.world_frame_id(), Role.kPerception):
        if inspector.GetName(geometry_id).rpartition("::")[2].startswith(TERRAIN_PERCEPTION_PREFIX):
            return 0
    label = RenderLabel(int(plant.world_body().index()))
    added = 0
    for kind, boxes in _boxes_by_kind(scene.terrain.box_pieces()).items():
        properties = PerceptionProperties()
        properties.AddProperty("phong", "diffuse", Rgba(*TERRAIN_COLORS[kind]))
        properties.AddProperty("label", "id", label)
        name = f"{TERRAIN_PERCEPTION_PREFIX}{kind}"
        if faces is None:
            instances = [GeometryInstance(RigidTransform(pose), Box(*size), f"{name}_{index}")
                         for index, (size, pose) in enumerate(boxes)]
        else:
            mesh = InMemoryMesh(mesh_file=MemoryFile(boxes_obj(boxes, faces), ".obj", f"{name}.obj"))
            instances = [GeometryInstance(RigidTransform(), Mesh(mesh), name)]
        for instance in instances:
            geometry_id = scene_graph.RegisterAnchoredGeometry(source_id, instance)
            scene_graph.AssignRole(source_id, geometry_id, PerceptionProperties(properties))
        added += len(instances)
    return added


def _boxes_by_kind(pieces: list[BoxPiece]) -> dict[str, list[tuple[np.ndarray, np.ndarray]]]:
    """(size, X_WP as 3 x 4) of the pieces, by kind in the order each kind first appears."""
    boxes: dict[str, list] = {}
    for piece in pieces:
        boxes.setdefault(piece.kind, []).append((piece.size, _piece_pose(piece).GetAsMatrix34()))
    return boxes


def _piece_pose(piece: BoxPiece | ConvexPiece) -> RigidTransform:
    if isinstance(piece, ConvexPiece):  # its vertices about their centroid: GJK's numbers stay small
        return RigidTransform(piece.vertices_W.mean(axis=0))
    return RigidTransform(RotationMatrix(piece.R_WP), piece.p_WP)


def _piece_shape(piece: BoxPiece | ConvexPiece, name: str) -> Box | Convex:
    if isinstance(piece, ConvexPiece):
        return Convex((piece.vertices_W - piece.vertices_W.mean(axis=0)).T, name)
    return Box(*piece.size)


def ReleaseSceneGraphModelCache(system) -> None:
    """Frees the copy of the geometry model that a SceneGraph caches whenever it sets a
    Context's parameters (Drake's "augmented model"): a third copy, beside the model and the
    Context's own, of every collision filter entry, which cost as much as 230 MiB a diagram.

    `system`: a SceneGraph, or a Diagram whose SceneGraphs to release. Call it after the
    Context is set (`StartEpisode` does, after `SetRandomContext`): the next Context or
    random draw makes the copy again (as fast as copying the cache), and nothing else
    changes. (Asking SceneGraph for its model's collision filter manager drops the cache
    and changes no filter.) glibc keeps the freed pages, so they are handed back to the
    system (`malloc_trim`) where that exists.
    """
    graphs = [system] if isinstance(system, SceneGraph) else [
        child for child in system.GetSystems() if isinstance(child, SceneGraph)]
    for scene_graph in graphs:
        scene_graph.collision_filter_manager()
    if graphs:
        try:
            ctypes.CDLL(None).malloc_trim(0)
        except (OSError, AttributeError):  # not glibc
            pass


def load_model_file(plant: MultibodyPlant, path: str | Path) -> list[ModelInstanceIndex]:
    """Parses an SDF/URDF file into `plant`; a parse failure names the file (and line).

    Raises:
        ConfigError: the file is missing or does not parse.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"model file {path} does not exist")
    try:
        return MakeParser(plant).AddModels(str(path))
    except RuntimeError as error:
        raise ConfigError(f"model file {path} failed to parse: {error}") from error


def AddHusky(plant: MultibodyPlant) -> ModelInstanceIndex:
    """Adds the Husky from `models_sdf/husky.sdf` with velocity-controlled wheels.

    The chassis gets an explicit quaternion floating joint so that start-pose
    distributions can be attached to it.
    """
    (husky,) = load_model_file(plant, MakeParser(plant).package_map().GetPath("ditch_drake") + "/husky.sdf")
    chassis = plant.GetBodyByName("chassis", husky)
    plant.AddJoint(QuaternionFloatingJoint("husky_floating", plant.world_frame(), chassis.body_frame()))
    # GetJointActuatorIndices() is empty before Finalize(), so scan all actuators.
    for index in range(plant.num_actuators()):
        actuator = plant.get_mutable_joint_actuator(JointActuatorIndex(index))
        if actuator.model_instance() == husky:
            actuator.set_controller_gains(PdControllerGains(p=0.0, d=robot.WHEEL_SPEED_GAIN_NMS))
    return husky


def chassis_height_on_flat_ground() -> float:
    """z of the chassis frame B when the wheels rest on flat ground at z = 0 (m)."""
    return robot.WHEEL_RADIUS_M


def SetStartPoseDistribution(plant: MultibodyPlant, husky: ModelInstanceIndex, task: Task,
                             jitter: StartJitter) -> None:
    """Nominal start pose as the default; seeded uniform jitter for random contexts."""
    x, y, yaw_deg = task.start
    z = chassis_height_on_flat_ground() + 0.005
    joint = plant.GetJointByName("husky_floating", husky)
    joint.SetDefaultPose(RigidTransform(RotationMatrix.MakeZRotation(math.radians(yaw_deg)), [x, y, z]))
    u = [Variable(f"start_jitter_{axis}", Variable.Type.RANDOM_UNIFORM) for axis in "xyw"]
    joint.set_random_translation_distribution([
        x + jitter.xy_m * (2 * u[0] - 1), y + jitter.xy_m * (2 * u[1] - 1), Expression(z)])
    half_yaw = (math.radians(yaw_deg) + math.radians(jitter.yaw_deg) * (2 * u[2] - 1)) / 2
    joint.set_random_quaternion_distribution(
        Quaternion_[Expression](cos(half_yaw), Expression(0), Expression(0), sin(half_yaw)))


def AddDitchScene(builder: DiagramBuilder, config: SceneConfig, meshcat: Meshcat | None = None) -> DitchScene:
    """Adds plant, scene graph, drive and episode monitor for `config` to `builder`.

    The drive's `command` input is left for the caller to connect or export.
    """
    environment = get_environment(config.environment, config.environments_file or None, config.environments)
    task = get_task(environment, config.task)
    if config.plant.time_step <= 0:
        raise ConfigError(f"plant.time_step={config.plant.time_step} must be > 0: the scene needs a discrete plant")
    terrain = DitchTerrain(environment.terrain)
    plant, scene_graph = AddMultibodyPlant(config.plant, builder)
    AddDitchTerrain(plant, terrain)
    husky = AddHusky(plant)
    plant.Finalize()
    SetStartPoseDistribution(plant, husky, task, config.start_jitter)

    wheel_is_left = [
        plant.get_joint_actuator(index).joint().name().endswith("left_wheel_joint")
        for index in plant.GetJointActuatorIndices(husky)
    ]
    drive = builder.AddNamedSystem("skid_steer_drive", SkidSteerDrive(wheel_is_left))
    builder.Connect(drive.GetOutputPort("wheel_desired_state"), plant.get_desired_state_input_port(husky))

    chassis = plant.GetBodyByName("chassis", husky)
    monitor = builder.AddNamedSystem("episode_monitor", EpisodeMonitor(
        chassis.index(), task.goal, config.episode, period_s=config.schedule.control_period_s))
    builder.Connect(plant.get_body_poses_output_port(), monitor.GetInputPort("body_poses"))

    if meshcat is not None:
        # The visualization's LCM messages (for Drake's Meldis) stay in this process: on the default
        # UDP multicast bus, LCM warned every newcomer about the kernel's receive buffer size.
        lcm = DrakeLcm("memq://")
        builder.AddNamedSystem("visualization_lcm", LcmInterfaceSystem(lcm))  # Owns `lcm`.
        ApplyVisualizationConfig(VisualizationConfig(publish_contacts=False), builder, meshcat=meshcat, lcm=lcm)
    return DitchScene(plant, scene_graph, husky, drive, monitor, terrain, environment, task, config.episode,
                      config.schedule, config.environment, config.task)


def MakeDitchDiagram(config: SceneConfig, meshcat: Meshcat | None = None) -> tuple[Diagram, DitchScene]:
    """A diagram of the scene whose `command` input port ([v m/s, w rad/s]) any controller drives.

    Exported ports: input `command`; outputs `husky_state` (plant state of the
    Husky), `body_poses`, `episode_state`, `query_object`.
    """
    builder = DiagramBuilder()
    scene = AddDitchScene(builder, config, meshcat)
    builder.ExportInput(scene.drive.GetInputPort("command"), "command")
    builder.ExportOutput(scene.plant.get_state_output_port(scene.husky), "husky_state")
    builder.ExportOutput(scene.plant.get_body_poses_output_port(), "body_poses")
    builder.ExportOutput(scene.monitor.GetOutputPort("episode_state"), "episode_state")
    builder.ExportOutput(scene.scene_graph.get_query_output_port(), "query_object")
    diagram = builder.Build()
    diagram.set_name(f"ditch_scene_{config.environment}")
    return diagram, scene


def chassis_pose(diagram: Diagram, scene: DitchScene, context) -> RigidTransform:
    """X_WB of the chassis in a root `context` of `diagram`."""
    plant_context = scene.plant.GetMyContextFromRoot(context)
    return scene.plant.EvalBodyPoseInWorld(plant_context, scene.plant.GetBodyByName("chassis", scene.husky))
