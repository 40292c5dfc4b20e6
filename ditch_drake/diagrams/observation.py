"""The observation: lidar -> surface-normal image, IMU, goal sensor -> frame stacker.

`AddObservation` adds these blocks to a scene and returns the four stacked outputs
every controller consumes (`OBSERVATION_PORTS`); `ConnectObservation` wires them,
by name, into any system that has inputs of those names.
"""

from dataclasses import dataclass, field

from pydrake.systems.framework import DiagramBuilder, OutputPort, System

from ditch_drake.diagrams.ditch_scene import DitchScene
from ditch_drake.diagrams.lidar_rig import AddLidar, LidarHandles
from ditch_drake.perception.lidar_model import LidarConfig
from ditch_drake.perception.normal_image import NormalImageConfig
from ditch_drake.spec.schedule import ScheduleConfig
from ditch_drake.systems.frame_stacker import FrameStacker
from ditch_drake.systems.goal import GoalSensor
from ditch_drake.systems.imu import AddImu, Imu, ImuConfig
from ditch_drake.systems.normal_image_converter import NormalImageConverter

OBSERVATION_PORTS = ("image_stack", "imu_stack", "distance_stack", "bearing_stack")


@dataclass
class ObservationConfig:
    """The perception blocks' settings."""

    lidar: LidarConfig = field(default_factory=LidarConfig)
    normal_image: NormalImageConfig = field(default_factory=NormalImageConfig)
    imu: ImuConfig = field(default_factory=ImuConfig)


@dataclass
class Observation:
    """Handles to the perception blocks and the stacked outputs, by port name."""

    lidar: LidarHandles
    normal_image: NormalImageConverter
    imu: Imu
    goal: GoalSensor
    stacker: FrameStacker
    ports: dict[str, OutputPort]
    schedule: ScheduleConfig


def AddObservation(builder: DiagramBuilder, scene: DitchScene, config: ObservationConfig | None = None,
                   goal_input: bool = False) -> Observation:
    """Adds lidar, normal-image converter, IMU, goal sensor and frame stacker to a scene.

    The goal sensor reads the distance and bearing to the task's goal, or, with `goal_input`,
    to the point at its `goal_xy` input (left for the caller to connect: a route-level target).

    The stages run in order within each control step (`scene.schedule`, `ditch_drake.spec.schedule`).
    """
    config = config or ObservationConfig()
    plant = scene.plant
    chassis = plant.GetBodyByName("chassis", scene.husky)
    lidar = AddLidar(builder, scene, config.lidar)
    # The organized cloud keeps the depth images' pixel neighbours for fast normals.
    normal_image = builder.AddNamedSystem("normal_image", NormalImageConverter(
        config.normal_image, organized_shape=lidar.converter.organized_shape, R_BS=lidar.X_BL.rotation()))
    builder.Connect(lidar.converter.GetOutputPort("organized_points"), normal_image.GetInputPort("point_cloud"))
    imu = AddImu(builder, plant.get_body_poses_output_port(), chassis.index(), config.imu,
                 noise_period_s=scene.schedule.control_period_s)
    goal = builder.AddNamedSystem("goal_sensor", GoalSensor(chassis.index(), scene.task.goal, goal_input))
    builder.Connect(plant.get_body_poses_output_port(), goal.GetInputPort("body_poses"))
    stacker = builder.AddNamedSystem("frame_stacker", FrameStacker(
        period_s=scene.schedule.control_period_s, offset_s=scene.schedule.stacker_offset_s))
    builder.Connect(normal_image.GetOutputPort("normal_image"), stacker.GetInputPort("normal_image"))
    builder.Connect(imu.GetOutputPort("roll_pitch"), stacker.GetInputPort("roll_pitch"))
    builder.Connect(goal.GetOutputPort("distance"), stacker.GetInputPort("distance"))
    builder.Connect(goal.GetOutputPort("bearing"), stacker.GetInputPort("bearing"))
    ports = {name: stacker.GetOutputPort(name) for name in OBSERVATION_PORTS}
    return Observation(lidar, normal_image, imu, goal, stacker, ports, scene.schedule)


def ConnectObservation(builder: DiagramBuilder, observation: Observation, system: System) -> None:
    """Connects every observation port to the input of the same name on `system`."""
    for name, port in observation.ports.items():
        if system.HasInputPort(name):
            builder.Connect(port, system.GetInputPort(name))
