"""A scene plus a controller, and running seeded episodes on it."""

import math
import typing
from dataclasses import dataclass, field

from pydrake.common import RandomGenerator
from pydrake.geometry import Meshcat
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Diagram, DiagramBuilder, System
from pydrake.systems.primitives import ConstantVectorSource

from ditch_drake.diagrams.ditch_scene import AddDitchScene, DitchScene, SceneConfig
from ditch_drake.environments import ConfigError
from ditch_drake.systems.edge_angle_driver import EdgeAngleDriver, EdgeAngleDriverConfig
from ditch_drake.systems.episode_monitor import EpisodeOutcome
from ditch_drake.systems.expert import ExpertDriver, ExpertVariation, draw_expert_style
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


ControllerConfig = EdgeAngleDriverConfig | ConstantCommandConfig | ExpertConfig


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
    else:
        raise ConfigError(f"unknown controller config {type(config).__name__}: expected one of "
                          f"{[kind.__name__ for kind in typing.get_args(ControllerConfig)]}")
    builder.Connect(command, scene.drive.GetInputPort("command"))
    return controller


def MakeRolloutDiagram(config: RolloutConfig, meshcat: Meshcat | None = None) -> tuple[Diagram, DitchScene]:
    """The scene of `config.scene` driven by the controller of `config.controller`."""
    builder = DiagramBuilder()
    scene = AddDitchScene(builder, config.scene, meshcat)
    AddController(builder, scene, config.controller)
    diagram = builder.Build()
    diagram.set_name(f"rollout_{config.scene.environment}_task{config.scene.task}")
    return diagram, scene


def RunEpisode(simulator: Simulator, diagram: Diagram, scene: DitchScene, seed: int) -> EpisodeOutcome:
    """Runs one episode from a seeded random start until the monitor ends it."""
    context = simulator.get_mutable_context()
    context.SetTime(0.0)
    diagram.SetRandomContext(context, RandomGenerator(seed))
    simulator.Initialize()
    # The monitor terminates the simulation; the bound is only a backstop.
    simulator.AdvanceTo(scene.episode.time_limit_s + 1.0)
    return scene.monitor.outcome(scene.monitor.GetMyContextFromRoot(context))
