"""A scene plus a controller, and running seeded episodes on it."""

import math
import sys
import typing
from dataclasses import dataclass, field

from pydrake.common import RandomGenerator
from pydrake.geometry import Meshcat
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Diagram, DiagramBuilder, EventStatus, System
from pydrake.systems.primitives import ConstantVectorSource
from tqdm import tqdm

from ditch_drake import schedule
from ditch_drake.diagrams.ditch_scene import AddDitchScene, DitchScene, SceneConfig
from ditch_drake.diagrams.observation import AddObservation, ConnectObservation, Observation, ObservationConfig
from ditch_drake.errors import ConfigError
from ditch_drake.learning.checkpoint import CheckpointError, load_checkpoint, resolve_checkpoint_path
from ditch_drake.systems.dwa import DwaConfig, DwaController
from ditch_drake.systems.edge_angle_driver import EdgeAngleDriver, EdgeAngleDriverConfig
from ditch_drake.systems.episode_monitor import EpisodeOutcome
from ditch_drake.systems.expert import ExpertDriver, ExpertVariation, draw_expert_style
from ditch_drake.systems.lidar import AddLidar, LidarConfig
from ditch_drake.systems.policy import LearnedPolicy
from ditch_drake.systems.teleop import ActionQuantizer


@dataclass
class ConstantCommandConfig:
    """Drive a fixed command [v m/s, w rad/s]: the straight-line driver, flat-ground tests."""

    command: list[float] = field(default_factory=lambda: [1.0, 0.0])


@dataclass
class ExpertConfig:
    """The scripted expert with the variation drawn from `style_seed`, through the action quantizer."""

    style_seed: int = 0
    variation: ExpertVariation = field(default_factory=ExpertVariation)


@dataclass
class LearnedPolicyConfig:
    """The behavioural clone of a checkpoint on the observation blocks.

    Attributes:
        checkpoint: a shipped model's name (`ditch_drake.learning.checkpoint.SHIPPED_MODELS`,
            e.g. "wide") or the path of a checkpoint file.
        observation: the perception blocks feeding it (their defaults match the demonstrations').
    """

    checkpoint: str = "wide"
    observation: ObservationConfig = field(default_factory=ObservationConfig)


@dataclass
class DwaBaselineConfig:
    """The move_base baseline (`DwaController`) on its own lidar.

    Attributes:
        planner: costmap, global and local planner parameters.
        lidar: the lidar feeding the costmap (the same sensor the learned policy sees).
    """

    planner: DwaConfig = field(default_factory=DwaConfig)
    lidar: LidarConfig = field(default_factory=LidarConfig)


ControllerConfig = EdgeAngleDriverConfig | ConstantCommandConfig | ExpertConfig | LearnedPolicyConfig | DwaBaselineConfig


@dataclass
class RolloutConfig:
    """A scene and the controller that drives it."""

    scene: SceneConfig = field(default_factory=SceneConfig)
    controller: ControllerConfig = field(default_factory=EdgeAngleDriverConfig)


def AddController(builder: DiagramBuilder, scene: DitchScene, config: ControllerConfig) -> System:
    """Adds the controller that `config` names and connects its command to the drive.

    Every controller's command output is [v m/s, w rad/s]; the learned policy and
    the DWA baseline plug in here the same way.
    """
    if isinstance(config, EdgeAngleDriverConfig):
        chassis = scene.plant.GetBodyByName("chassis", scene.husky)
        controller = builder.AddNamedSystem(
            "edge_angle_driver", EdgeAngleDriver(scene.terrain, scene.task.goal, chassis.index(), config))
        builder.Connect(scene.plant.get_body_poses_output_port(), controller.GetInputPort("body_poses"))
        command = controller.GetOutputPort("command")
    elif isinstance(config, ConstantCommandConfig):
        if len(config.command) != 2 or not all(math.isfinite(value) for value in config.command):
            raise ConfigError(f"constant command {config.command} must be finite [v m/s, w rad/s]")
        controller = builder.AddNamedSystem("constant_command", ConstantVectorSource(config.command))
        command = controller.get_output_port()
    elif isinstance(config, ExpertConfig):
        chassis = scene.plant.GetBodyByName("chassis", scene.husky)
        style = draw_expert_style(config.style_seed, config.variation)
        controller = builder.AddNamedSystem(
            "expert", ExpertDriver(scene.terrain, scene.task.goal, chassis.index(), style))
        builder.Connect(scene.plant.get_body_poses_output_port(), controller.GetInputPort("body_poses"))
        quantizer = builder.AddNamedSystem("action_quantizer", ActionQuantizer())
        builder.Connect(controller.GetOutputPort("raw_command"), quantizer.GetInputPort("raw_command"))
        command = quantizer.GetOutputPort("command")
    elif isinstance(config, LearnedPolicyConfig):
        controller = AddLearnedPolicy(builder, AddObservation(builder, scene, config.observation), config.checkpoint)
        command = controller.GetOutputPort("command")
    elif isinstance(config, DwaBaselineConfig):
        chassis = scene.plant.GetBodyByName("chassis", scene.husky)
        lidar = AddLidar(builder, scene, config.lidar)
        controller = builder.AddNamedSystem("dwa", DwaController(
            scene.task.goal, chassis.index(), lidar.X_BL, config.planner, offset_s=schedule.CONTROLLER_OFFSET_S,
            ray_directions_L=lidar.converter.ray_directions_L))
        builder.Connect(lidar.converter.GetOutputPort("organized_points"), controller.GetInputPort("point_cloud"))
        builder.Connect(scene.plant.get_body_poses_output_port(), controller.GetInputPort("body_poses"))
        command = controller.GetOutputPort("command")
    else:
        raise ConfigError(f"unknown controller config {type(config).__name__}: expected one of "
                          f"{[kind.__name__ for kind in typing.get_args(ControllerConfig)]}")
    builder.Connect(command, scene.drive.GetInputPort("command"))
    return controller


def AddLearnedPolicy(builder: DiagramBuilder, observation: Observation, checkpoint: str) -> LearnedPolicy:
    """Adds the behavioural clone of `checkpoint` (a shipped name or a path) fed by `observation`.

    Raises:
        CheckpointError: the checkpoint expects other input sizes than the blocks give.
    """
    policy = builder.AddNamedSystem(
        "learned_policy", LearnedPolicy(load_checkpoint(resolve_checkpoint_path(checkpoint)),
                                        offset_s=schedule.CONTROLLER_OFFSET_S))
    for name, port in observation.ports.items():
        expected = policy.GetInputPort(name).size()
        if port.size() != expected:
            raise CheckpointError(
                f"checkpoint {checkpoint!r} expects {name} of {expected} values; the observation "
                f"blocks give {port.size()} (a model trained on another input shape)")
    ConnectObservation(builder, observation, policy)
    return policy


def MakeRolloutDiagram(config: RolloutConfig, meshcat: Meshcat | None = None) -> tuple[Diagram, DitchScene]:
    """The scene of `config.scene` driven by the controller of `config.controller`."""
    builder = DiagramBuilder()
    scene = AddDitchScene(builder, config.scene, meshcat)
    AddController(builder, scene, config.controller)
    diagram = builder.Build()
    diagram.set_name(f"rollout_{config.scene.environment}_task{config.scene.task}")
    return diagram, scene


def RunEpisode(simulator: Simulator, diagram: Diagram, scene: DitchScene, seed: int,
               progress: str | None = None) -> EpisodeOutcome:
    """Runs one episode from a seeded random start until the monitor ends it.

    Args:
        progress: a description for a progress bar of simulated time on stderr (None: none).
            It watches the steps through the Simulator's monitor and changes nothing.
    """
    context = simulator.get_mutable_context()
    context.SetTime(0.0)
    diagram.SetRandomContext(context, RandomGenerator(seed))
    simulator.Initialize()
    # The monitor terminates the simulation; the bound is only a backstop.
    end_s = scene.episode.time_limit_s + 1.0
    if progress is None:
        simulator.AdvanceTo(end_s)
    else:
        with tqdm(total=round(scene.episode.time_limit_s), desc=progress, unit="sim s", file=sys.stderr,
                  leave=False) as bar:

            def show(root_context) -> EventStatus:
                bar.update(int(root_context.get_time()) - bar.n)
                return EventStatus.DidNothing()

            simulator.set_monitor(show)
            try:
                simulator.AdvanceTo(end_s)
            finally:
                simulator.clear_monitor()
    return scene.monitor.outcome(scene.monitor.GetMyContextFromRoot(context))
