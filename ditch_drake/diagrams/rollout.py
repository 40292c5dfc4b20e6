"""A scene plus a controller, and running seeded episodes on it."""

import contextlib
import dataclasses
import math
import sys
import typing
from collections.abc import Callable
from dataclasses import dataclass, field

from pydrake.common import RandomGenerator
from pydrake.geometry import Meshcat
from pydrake.systems.analysis import Simulator, SimulatorStatus
from pydrake.systems.framework import Context, Diagram, DiagramBuilder, EventStatus, OutputPort, System
from tqdm import tqdm

from ditch_drake.common.config_yaml import WRITTEN_WHEN_SET
from ditch_drake.common.errors import ConfigError
from ditch_drake.diagrams.ditch_scene import AddDitchScene, DitchScene, ReleaseSceneGraphModelCache, SceneConfig
from ditch_drake.diagrams.lidar_rig import AddLidar, LidarHandles
from ditch_drake.diagrams.observation import AddObservation, ConnectObservation, Observation, ObservationConfig
from ditch_drake.learning.checkpoint import CheckpointError, environment_model
from ditch_drake.learning.ensemble_network import DEFAULT_PRECISION
from ditch_drake.learning.inference import check_precision, check_runtime, load_policy
from ditch_drake.learning.onnx_policy import is_onnx_path
from ditch_drake.perception.lidar_model import LidarConfig
from ditch_drake.planning.costmap import CostmapConfig
from ditch_drake.planning.elevation_map import ElevationGrid, ElevationMapConfig
from ditch_drake.planning.mppi import MppiPlannerConfig
from ditch_drake.systems.crossing_side_agreement import CrossingSideAgreement
from ditch_drake.systems.dwa_controller import DwaConfig, DwaController
from ditch_drake.systems.edge_angle_driver import EdgeAngleDriver, EdgeAngleDriverConfig
from ditch_drake.systems.elevation_mapper import ElevationMapper
from ditch_drake.systems.episode_monitor import EpisodeOutcome
from ditch_drake.systems.expert import ExpertDriver, ExpertVariation, draw_expert_style
from ditch_drake.systems.halt_counter import HaltCounter
from ditch_drake.systems.handover_counter import HandoverCounter, handover_capacity
from ditch_drake.systems.mppi_controller import MppiController
from ditch_drake.systems.oracle_crossing_side import OracleCrossingSide
from ditch_drake.systems.perceived_crossing_side import PerceivedCrossingSide, PerceivedCrossingSideConfig
from ditch_drake.systems.policy import DEFAULT_UNCERTAINTY_SIGNAL, LearnedPolicy
from ditch_drake.systems.skid_steer_drive import ConstantCommand
from ditch_drake.systems.target_crossing_side import TargetCrossingSide
from ditch_drake.systems.teleop import ActionQuantizer
from ditch_drake.systems.tip_risk import TipRisk, TipRiskConfig
from ditch_drake.systems.window_search import WindowSearch, WindowSearchConfig


@dataclass
class ConstantCommandConfig:
    """Drive a fixed command [v m/s, w rad/s]: the straight-line driver, flat-ground tests."""

    command: list[float] = field(default_factory=lambda: [1.0, 0.0])

    def validate(self) -> None:
        if len(self.command) != 2 or not all(math.isfinite(value) for value in self.command):
            raise ConfigError(f"constant command {self.command} must be finite [v m/s, w rad/s]")


@dataclass
class ExpertConfig:
    """The scripted expert with the variation drawn from `style_seed`, through the action quantizer.

    Attributes:
        style_seed: seeds the expert's style; None: the episode's seed (a batch evaluation
            builds the expert of each seed), or 0 where no episode seed is known.
        variation: the ranges the style is drawn from.
    """

    style_seed: int | None = None
    variation: ExpertVariation = field(default_factory=ExpertVariation)


# Where a side-conditioned clone's crossing side comes from (`LearnedPolicyConfig.crossing_side`).
CROSSING_SIDE_SOURCES = ("perceived", "oracle")


@dataclass
class LearnedWindowSearchConfig(WindowSearchConfig):
    """`WindowSearchConfig` with the learned policy's own defaults.

    Attributes:
        edge_standoff_m: farther from the edge than the `mppi` baseline's: the policy drives at
            1 m/s and turns at most 0.85 rad/s, so a search that turns back along the edge
            turns in a circle 2.4 m across, which it may take toward the ditch (at 0.8 m it
            went over a 70 deg wall there; at 2.5 m it turned on the top).
    """

    edge_standoff_m: float = 2.5


@dataclass
class LearnedPolicyConfig:
    """The behavioural clone of a checkpoint on the observation blocks.

    Attributes:
        checkpoint: a shipped model's name (`ditch_drake.learning.checkpoint.SHIPPED_MODELS`,
            e.g. "wide"), the path of a checkpoint file (.pt, or a .onnx of `ditch-drake
            export-policy`, which needs runtime "onnxruntime"), or "" for the shipped model of
            the environment it drives in.
        observation: the perception blocks feeding it (their defaults match the demonstrations').
        crossing_side: where a clone trained in one side's frame (`ModelConfig.canonical_side`)
            is told the side to cross on: "perceived" (`PerceivedCrossingSide`, from the lidar's
            points and the pose) or "oracle" (`OracleCrossingSide`, from the analytic ditch: a
            privileged input, for the ablation). Other checkpoints ignore it.
        runtime: what runs the network (`ditch_drake.learning.inference.RUNTIMES`): "torch"
            (PyTorch), or "onnxruntime" (ONNX Runtime, one thread; a .pt checkpoint is exported
            to ONNX in memory when the diagram is built; needs `pip install -e '.[onnx]'`).
            The softmax, mirror and argmax around it are the same; the labels may differ where
            two logits tie to within the runtimes' float32 rounding (about 1e-5).
        search: with it, a `WindowSearch` on an elevation map fused from the observation's lidar
            (`ElevationMapper`, the `mppi` baseline's map) gives the goal sensor its target in
            place of the goal (a way in and out of a ditch crossable only in places; the goal
            still ends the run), and a side-conditioned clone is told the side toward that
            target (`TargetCrossingSide`; needs crossing_side "perceived"); None: the goal.
        precision: what an ensemble file's network computes in
            (`ditch_drake.learning.ensemble_network.PRECISIONS`): "float32", or
            "bfloat16_image" (its image branch in bfloat16: faster on a CPU that runs bfloat16
            natively, refused on one that does not; a label may differ from float32's where
            two logits nearly tie). A single clone runs in float32 only.
        tip_risk: with it, a "tip_risk" block (`TipRisk`) reads the policy's command, the pose
            and the elevation map fused from the observation's lidar (the search's, or an
            `ElevationMapper` of its own), and gives minus the tip margin now and along the
            commanded arc: a risk signal that `ditch-drake gate-signals --risk` records beside
            the uncertainty signals. It drives nothing. None: no such block.
    """

    checkpoint: str = ""
    observation: ObservationConfig = field(default_factory=ObservationConfig)
    crossing_side: str = "perceived"
    runtime: str = "torch"
    search: LearnedWindowSearchConfig | None = field(default=None, metadata=WRITTEN_WHEN_SET)
    precision: str = field(default=DEFAULT_PRECISION, metadata=WRITTEN_WHEN_SET)
    tip_risk: TipRiskConfig | None = field(default=None, metadata=WRITTEN_WHEN_SET)

    def validate(self) -> None:
        if self.crossing_side not in CROSSING_SIDE_SOURCES:
            raise ConfigError(f"learned crossing_side={self.crossing_side!r}: expected one of "
                              f"{list(CROSSING_SIDE_SOURCES)}")
        if self.search is not None:
            self.search.validate()
            if self.crossing_side != "perceived":
                raise ConfigError(f"learned crossing_side={self.crossing_side!r} with a search: expected 'perceived' "
                                  "(the side toward the search's target is read from the perceived edge)")
        check_runtime(self.runtime, self.checkpoint)
        check_precision(self.precision, self.checkpoint)
        if self.tip_risk is not None:
            self.tip_risk.validate()

    def with_checkpoint(self, checkpoint: str) -> "LearnedPolicyConfig":
        """This config naming `checkpoint`; a .onnx file also sets runtime "onnxruntime", the only
        one that runs it, so that `--checkpoint policy.onnx` is taken wherever a checkpoint is
        (`ditch_drake.diagrams.controllers.with_checkpoint`)."""
        runtime = "onnxruntime" if is_onnx_path(checkpoint) else self.runtime
        return dataclasses.replace(self, checkpoint=checkpoint, runtime=runtime)


def with_crossing_side(config, crossing_side: str) -> LearnedPolicyConfig:
    """The learned policy's `config` told its side by `crossing_side` ("perceived" or "oracle").

    Raises:
        ConfigError: a config of another controller, or an unknown source.
    """
    if not isinstance(config, LearnedPolicyConfig):
        raise ConfigError(f"crossing_side {crossing_side!r} with a {type(config).__name__}: expected it only with "
                          "the learned policy")
    config = dataclasses.replace(config, crossing_side=crossing_side)
    config.validate()
    return config


@dataclass
class DwaBaselineConfig:
    """The move_base baseline (`DwaController`) on its own lidar.

    Attributes:
        planner: costmap, global and local planner parameters.
        lidar: the lidar feeding the costmap (the same sensor the learned policy sees).
    """

    planner: DwaConfig = field(default_factory=DwaConfig)
    lidar: LidarConfig = field(default_factory=LidarConfig)


@dataclass
class MppiBaselineConfig:
    """The rollover-aware MPPI baseline (`MppiController`) on its own lidar.

    Attributes:
        planner: MPPI's samples, horizon, costs, tip-margin thresholds and seed.
        elevation_map: the rolling elevation grid fused from the lidar.
        goal_tolerance_m: it stops for good within this planar distance of the goal (m).
        lidar: the lidar feeding the map (the same sensor the learned policy sees).
        search: with it, a `WindowSearch` on the map gives the planner its target in place of
            the goal (a way in and out of a ditch crossable only in places); None: the goal.
    """

    planner: MppiPlannerConfig = field(default_factory=MppiPlannerConfig)
    elevation_map: ElevationMapConfig = field(default_factory=ElevationMapConfig)
    goal_tolerance_m: float = 1.0
    lidar: LidarConfig = field(default_factory=LidarConfig)
    search: WindowSearchConfig | None = field(default=None, metadata=WRITTEN_WHEN_SET)

    def validate(self) -> None:
        """Raises ConfigError naming the first value out of range (`MppiController` checks these when built)."""
        self.planner.validate()
        self.elevation_map.validate()
        if not self.goal_tolerance_m >= 0:
            raise ConfigError(f"mppi goal_tolerance_m={self.goal_tolerance_m!r}: expected >= 0")


@dataclass
class RolloutConfig:
    """A scene and the controller that drives it (any registered controller's config)."""

    scene: SceneConfig = field(default_factory=SceneConfig)
    controller: typing.Any = field(default_factory=EdgeAngleDriverConfig)


def head_on_config() -> EdgeAngleDriverConfig:
    """The scripted driver straight into the ditch, perpendicular to its edge: the rollover reference."""
    return EdgeAngleDriverConfig(wall_angle_deg=90.0, climb_angle_deg=None)


def paper_dwa_config() -> DwaBaselineConfig:
    """The paper's move_base (section 4.2): the `dwa` block with the paper's slope cost.

    Cost rises with slope from the normals' z, flat ground costs 0 and no slope is lethal
    (`lethal_slope_deg=inf`: 252 at 90 deg, 107 on the ditches' 55 deg walls); vertical
    obstacles still are, by the height their points span in a cell (`max_step_height`, 0.3 m:
    see `ditch_drake.planning.costmap`). No hidden-drop marking (`negative_obstacle_depth=0`):
    the paper's layer had only the normal-based cost, so the unseen wall below a ditch's edge
    stays unknown, which the global planner crosses at the highest non-lethal weight
    (`allow_unknown`) and the DWA at cost 252 (`unknown_is_lethal` False): it drives into a
    ditch when that is cheaper than the way around, or when walls leave no way around.
    """
    costmap = CostmapConfig(lethal_slope_deg=math.inf, negative_obstacle_depth=0.0, max_step_height=0.3)
    return DwaBaselineConfig(planner=DwaConfig(costmap=costmap))


def AddController(builder: DiagramBuilder, scene: DitchScene, config) -> System:
    """Adds the registered controller whose config `config` is, and connects its command to the drive.

    Every controller's command output is [v m/s, w rad/s]; the learned policy, the DWA
    baseline and the scripted drivers plug in here the same way (`ditch_drake.diagrams.controllers`).
    A "halt_counter" (`AddHaltCounter`) counts the command's halts per region of the ditch.

    Raises:
        ConfigError: a config of no registered controller.
    """
    from ditch_drake.diagrams.controllers import entry_for_config

    command = entry_for_config(config).add(builder, scene, config)
    builder.Connect(command, scene.drive.GetInputPort("command"))
    AddHaltCounter(builder, scene, command)
    AddCrossingSideAgreement(builder, scene)
    AddHandoverCounter(builder, scene)
    return command.get_system()


def AddHandoverCounter(builder: DiagramBuilder, scene: DitchScene) -> HandoverCounter | None:
    """Adds a "handover_counter" (`HandoverCounter`) on the builder's "shared_control" gate, if it
    has one: the rollout's record then says what share of the control steps the fallback drove
    and in which regions of the ditch the handovers began. An instrument beside the controller,
    given the analytic ditch as the halt counter is; it drives nothing."""
    if not builder.HasSubsystemNamed("shared_control"):
        return None
    gate = builder.GetSubsystemByName("shared_control")
    schedule = scene.schedule
    counter = builder.AddNamedSystem("handover_counter", HandoverCounter(
        scene.terrain, scene.task.start[:2], scene.plant.GetBodyByName("chassis", scene.husky).index(),
        max_handovers=handover_capacity(scene.episode.time_limit_s, schedule.control_period_s),
        period_s=schedule.control_period_s))
    builder.Connect(gate.GetOutputPort("who_drives"), counter.GetInputPort("who_drives"))
    builder.Connect(scene.plant.get_body_poses_output_port(), counter.GetInputPort("body_poses"))
    return counter


def AddCrossingSideAgreement(builder: DiagramBuilder, scene: DitchScene) -> CrossingSideAgreement | None:
    """Adds a "crossing_side_agreement" (`CrossingSideAgreement`) on the builder's
    "perceived_crossing_side", if it has one: the rollout's record then says how often the
    perceived side equalled the oracle's. An instrument beside the controller, given the
    analytic ditch as the halt counter is; it drives nothing."""
    if not builder.HasSubsystemNamed("perceived_crossing_side"):
        return None
    side = builder.GetSubsystemByName("perceived_crossing_side")
    schedule = scene.schedule
    agreement = builder.AddNamedSystem("crossing_side_agreement", CrossingSideAgreement(
        scene.terrain, scene.task.goal, scene.plant.GetBodyByName("chassis", scene.husky).index(),
        period_s=schedule.control_period_s, offset_s=schedule.controller_offset_s))
    builder.Connect(side.GetOutputPort("crossing_side"), agreement.GetInputPort("crossing_side"))
    builder.Connect(scene.plant.get_body_poses_output_port(), agreement.GetInputPort("body_poses"))
    return agreement


def AddHaltCounter(builder: DiagramBuilder, scene: DitchScene, command: OutputPort) -> HaltCounter:
    """Adds the "halt_counter" on `command`, the port that drives the robot (see `HaltCounter`)."""
    chassis = scene.plant.GetBodyByName("chassis", scene.husky)
    # At the episode monitor's tick (offset 0): an event time the simulator already stops
    # at, so counting changes no other system's results.
    counter = builder.AddNamedSystem("halt_counter", HaltCounter(
        scene.terrain, scene.task.start[:2], chassis.index(), period_s=scene.schedule.control_period_s,
        offset_s=0.0))
    builder.Connect(command, counter.GetInputPort("command"))
    builder.Connect(scene.plant.get_body_poses_output_port(), counter.GetInputPort("body_poses"))
    return counter


# Each controller's builder adds its blocks to a scene and returns the command output port
# ([v m/s, w rad/s]); `AddController` connects it to the drive.


def AddEdgeAngleDriver(builder: DiagramBuilder, scene: DitchScene, config: EdgeAngleDriverConfig) -> OutputPort:
    chassis = scene.plant.GetBodyByName("chassis", scene.husky)
    # It reads only the chassis pose, so it acts at the tick itself (offset 0).
    controller = builder.AddNamedSystem("edge_angle_driver", EdgeAngleDriver(
        scene.terrain, scene.task.goal, chassis.index(), config, period_s=scene.schedule.control_period_s))
    builder.Connect(scene.plant.get_body_poses_output_port(), controller.GetInputPort("body_poses"))
    return controller.GetOutputPort("command")


def AddConstantCommand(builder: DiagramBuilder, scene: DitchScene, config: ConstantCommandConfig) -> OutputPort:
    config.validate()
    return builder.AddNamedSystem("constant_command", ConstantCommand(config.command)).get_output_port()


def AddExpert(builder: DiagramBuilder, scene: DitchScene, config: ExpertConfig) -> OutputPort:
    """The scripted expert through the action quantizer; the quantizer's `command` drives."""
    chassis = scene.plant.GetBodyByName("chassis", scene.husky)
    style = draw_expert_style(0 if config.style_seed is None else config.style_seed, config.variation)
    expert = builder.AddNamedSystem("expert", ExpertDriver(
        scene.terrain, scene.task.goal, chassis.index(), style, period_s=scene.schedule.control_period_s,
        offset_s=scene.schedule.controller_offset_s))
    builder.Connect(scene.plant.get_body_poses_output_port(), expert.GetInputPort("body_poses"))
    quantizer = builder.AddNamedSystem("action_quantizer", ActionQuantizer())
    builder.Connect(expert.GetOutputPort("raw_command"), quantizer.GetInputPort("raw_command"))
    return quantizer.GetOutputPort("command")


def AddLearnedController(builder: DiagramBuilder, scene: DitchScene, config: LearnedPolicyConfig) -> OutputPort:
    """The learned policy on its observation blocks; with `config.search` or `config.tip_risk`,
    an "elevation_mapper" (`AddElevationMapper`); with `config.search`, a "window_search" on its
    map, whose target the goal sensor reads in place of the goal (and the crossing side is told
    toward); with `config.tip_risk`, a "tip_risk" block on its map and the policy's command."""
    config.validate()
    checkpoint = config.checkpoint or environment_model(scene.environment.based_on or scene.environment_name)
    observation = AddObservation(builder, scene, config.observation, goal_input=config.search is not None)
    target_xy = None
    mapper = None
    if config.search is not None or config.tip_risk is not None:
        mapper = AddElevationMapper(builder, scene, observation)
    if config.search is not None:
        target_xy = AddWindowSearch(builder, scene, mapper.grid, mapper.GetOutputPort("elevation_map"), config.search,
                                    offset_s=scene.schedule.stacker_offset_s)
        builder.Connect(target_xy, observation.goal.GetInputPort("goal_xy"))
    command = AddLearnedPolicy(builder, scene, observation, checkpoint, config.crossing_side,
                               config.runtime, target_xy=target_xy, precision=config.precision).GetOutputPort("command")
    if config.tip_risk is not None:
        AddTipRisk(builder, scene, mapper, command, config.tip_risk)
    return command


def AddElevationMapper(builder: DiagramBuilder, scene: DitchScene, observation: Observation) -> ElevationMapper:
    """Adds an "elevation_mapper" (`ElevationMapper`, the `mppi` baseline's map) on the
    observation's lidar, updating at the frame stacker's offset: after the lidar's tick, so that
    the map fuses this step's cloud."""
    schedule = scene.schedule
    mapper = builder.AddNamedSystem("elevation_mapper", ElevationMapper(
        scene.plant.GetBodyByName("chassis", scene.husky).index(), observation.lidar.X_BL, ElevationMapConfig(),
        period_s=schedule.control_period_s, offset_s=schedule.stacker_offset_s))
    builder.Connect(observation.lidar.converter.GetOutputPort("organized_points"), mapper.GetInputPort("point_cloud"))
    builder.Connect(scene.plant.get_body_poses_output_port(), mapper.GetInputPort("body_poses"))
    return mapper


def AddTipRisk(builder: DiagramBuilder, scene: DitchScene, mapper: ElevationMapper, command: OutputPort,
               config: TipRiskConfig) -> TipRisk:
    """Adds a "tip_risk" block (`TipRisk`) on `mapper`'s map, the chassis pose and `command`
    (the arc it predicts along); returns it."""
    risk = builder.AddNamedSystem("tip_risk", TipRisk(
        scene.plant.GetBodyByName("chassis", scene.husky).index(), mapper.grid, config))
    builder.Connect(mapper.GetOutputPort("elevation_map"), risk.GetInputPort("elevation_map"))
    builder.Connect(scene.plant.get_body_poses_output_port(), risk.GetInputPort("body_poses"))
    builder.Connect(command, risk.GetInputPort("command"))
    return risk


def AddWindowSearch(builder: DiagramBuilder, scene: DitchScene, grid: ElevationGrid, elevation_map: OutputPort,
                    config: WindowSearchConfig, offset_s: float) -> OutputPort:
    """Adds a "window_search" (`WindowSearch`) on `elevation_map` (of `grid`), updating at
    `offset_s` in the control step; returns its `target_xy` output."""
    search = builder.AddNamedSystem("window_search", WindowSearch(
        scene.task.goal, scene.plant.GetBodyByName("chassis", scene.husky).index(), grid, config,
        period_s=scene.schedule.control_period_s, offset_s=offset_s))
    builder.Connect(elevation_map, search.GetInputPort("elevation_map"))
    builder.Connect(scene.plant.get_body_poses_output_port(), search.GetInputPort("body_poses"))
    return search.GetOutputPort("target_xy")


def AddDwaController(builder: DiagramBuilder, scene: DitchScene, config: DwaBaselineConfig) -> OutputPort:
    chassis = scene.plant.GetBodyByName("chassis", scene.husky)
    lidar = AddLidar(builder, scene, config.lidar)
    controller = builder.AddNamedSystem("dwa", DwaController(
        scene.task.goal, chassis.index(), lidar.X_BL, config.planner, period_s=scene.schedule.control_period_s,
        offset_s=scene.schedule.controller_offset_s, ray_directions_L=lidar.converter.ray_directions_L))
    builder.Connect(lidar.converter.GetOutputPort("organized_points"), controller.GetInputPort("point_cloud"))
    builder.Connect(scene.plant.get_body_poses_output_port(), controller.GetInputPort("body_poses"))
    return controller.GetOutputPort("command")


def AddMppiController(builder: DiagramBuilder, scene: DitchScene, config: MppiBaselineConfig,
                      lidar: LidarHandles | None = None) -> OutputPort:
    """The MPPI baseline on its own lidar, or on `lidar` (one already in the scene, of the same
    `config.lidar`: the shared controller's fallback reads the policy's).

    Raises:
        ConfigError: a planner or map value out of range, naming the key.
    """
    chassis = scene.plant.GetBodyByName("chassis", scene.husky)
    lidar = lidar if lidar is not None else AddLidar(builder, scene, config.lidar)
    controller = builder.AddNamedSystem("mppi", MppiController(
        scene.task.goal, chassis.index(), lidar.X_BL, config.planner, config.elevation_map,
        goal_tolerance_m=config.goal_tolerance_m, period_s=scene.schedule.control_period_s,
        offset_s=scene.schedule.controller_offset_s, target_input=config.search is not None))
    builder.Connect(lidar.converter.GetOutputPort("organized_points"), controller.GetInputPort("point_cloud"))
    builder.Connect(scene.plant.get_body_poses_output_port(), controller.GetInputPort("body_poses"))
    if config.search is not None:
        target_xy = AddWindowSearch(builder, scene, controller.grid, controller.GetOutputPort("elevation_map"),
                                    config.search, offset_s=scene.schedule.controller_offset_s)
        builder.Connect(target_xy, controller.GetInputPort("target_xy"))
    return controller.GetOutputPort("command")


def AddLearnedPolicy(builder: DiagramBuilder, scene: DitchScene, observation: Observation,
                     checkpoint: str, crossing_side: str = "perceived", runtime: str = "torch",
                     uncertainty_signal: str = DEFAULT_UNCERTAINTY_SIGNAL,
                     target_xy: OutputPort | None = None, precision: str = DEFAULT_PRECISION) -> LearnedPolicy:
    """Adds the behavioural clone of `checkpoint` (a shipped name or a path; an ensemble file runs
    all its members) fed by `observation`, its network run by `runtime`
    (`LearnedPolicyConfig.runtime`) in `precision` (`LearnedPolicyConfig.precision`), its
    `uncertainty` output the signal `uncertainty_signal`,
    and, for a clone trained in one side's frame, the block that tells it the side to cross on
    (`AddCrossingSide` of `crossing_side`: "perceived" or "oracle"; toward `target_xy` where
    one is given, a route-level target such as `WindowSearch`'s).

    Raises:
        ConfigError: an unknown or uninstalled runtime, or one that does not run the checkpoint;
            a precision the checkpoint or the CPU does not run; an unknown signal, or a
            disagreement signal with a single clone.
        CheckpointError: the checkpoint does not load, or expects other input sizes than the blocks give.
    """
    schedule = observation.schedule
    policy = builder.AddNamedSystem(
        "learned_policy", LearnedPolicy(load_policy(checkpoint, runtime, precision=precision),
                                        offset_s=schedule.controller_offset_s, period_s=schedule.control_period_s,
                                        uncertainty_signal=uncertainty_signal))
    for name, port in observation.ports.items():
        expected = policy.GetInputPort(name).size()
        if port.size() != expected:
            raise CheckpointError(
                f"checkpoint {checkpoint!r} expects {name} of {expected} values; the observation "
                f"blocks give {port.size()} (a model trained on another input shape)")
    ConnectObservation(builder, observation, policy)
    if policy.HasInputPort("crossing_side"):
        side = AddCrossingSide(builder, scene, observation, crossing_side, target_xy=target_xy)
        builder.Connect(side.GetOutputPort("crossing_side"), policy.GetInputPort("crossing_side"))
    return policy


def AddCrossingSide(builder: DiagramBuilder, scene: DitchScene, observation: Observation,
                    source: str = "perceived", config: PerceivedCrossingSideConfig | None = None,
                    target_xy: OutputPort | None = None) -> System:
    """Adds the block that tells a side-conditioned clone which side along the edge to cross on,
    named after its source: "perceived_crossing_side" (`PerceivedCrossingSide`, on the
    observation's lidar and the chassis pose) or "oracle_crossing_side" (`OracleCrossingSide`,
    on the scene's analytic ditch: privileged). Either holds its side from the control step it
    commits, and the controller reads it in the same step. `AddController` measures a perceived
    side against the oracle's (`AddCrossingSideAgreement`).

    With `target_xy` (a route-level target the controller drives toward, such as
    `WindowSearch`'s), the side is the rule's toward that target on the perceived edge: a
    "target_crossing_side" (`TargetCrossingSide`) beside the perceived block, returned in its
    place.

    Raises:
        ConfigError: an unknown source, or a target with the oracle's.
    """
    if target_xy is not None and source != "perceived":
        raise ConfigError(f"crossing side source {source!r} with a target: expected 'perceived'")
    schedule = scene.schedule
    chassis = scene.plant.GetBodyByName("chassis", scene.husky).index()
    if source == "perceived":
        lidar = observation.lidar
        side = builder.AddNamedSystem("perceived_crossing_side", PerceivedCrossingSide(
            scene.task.goal, chassis, lidar.X_BL, lidar.converter.ray_directions_L, lidar.converter.config.range_m, config,
            period_s=schedule.control_period_s, offset_s=schedule.stacker_offset_s))
        builder.Connect(lidar.converter.GetOutputPort("organized_points"), side.GetInputPort("point_cloud"))
    elif source == "oracle":
        side = builder.AddNamedSystem("oracle_crossing_side", OracleCrossingSide(
            scene.terrain, scene.task.goal, chassis, period_s=schedule.control_period_s,
            offset_s=schedule.controller_offset_s))
    else:
        raise ConfigError(f"crossing side source {source!r}: expected one of {list(CROSSING_SIDE_SOURCES)}")
    builder.Connect(scene.plant.get_body_poses_output_port(), side.GetInputPort("body_poses"))
    if target_xy is None:
        return side
    toward = builder.AddNamedSystem("target_crossing_side", TargetCrossingSide(
        chassis, side.config.straight_across_deg))
    builder.Connect(side.GetOutputPort("edge"), toward.GetInputPort("edge"))
    builder.Connect(target_xy, toward.GetInputPort("target_xy"))
    builder.Connect(scene.plant.get_body_poses_output_port(), toward.GetInputPort("body_poses"))
    return toward


def MakeRolloutDiagram(config: RolloutConfig, meshcat: Meshcat | None = None) -> tuple[Diagram, DitchScene]:
    """The scene of `config.scene` driven by the controller of `config.controller`."""
    builder = DiagramBuilder()
    scene = AddDitchScene(builder, config.scene, meshcat)
    AddController(builder, scene, config.controller)
    diagram = builder.Build()
    diagram.set_name(f"rollout_{config.scene.environment}_task{config.scene.task}")
    return diagram, scene


def StartEpisode(simulator: Simulator, diagram: Diagram, seed: int,
                 before_start: Callable[[Context], None] | None = None,
                 after_start: Callable[[Context], None] | None = None) -> None:
    """Puts `simulator` at the seeded random start of an episode: time 0, `SetRandomContext(seed)`,
    `before_start`, `Initialize`, `after_start`.

    `RunEpisode`'s first half, on its own for the measurements that advance the simulator
    themselves (the bench's timed runs, the calibration's flat-ground tracking).

    Args:
        simulator: a Simulator of `diagram`; one serves many episodes, each from a fresh start.
        diagram: the diagram whose random context (start jitter, sensor noise) `seed` draws.
        seed: seeds Drake's `RandomGenerator`.
        before_start: called with the root Context after the random draw and before
            `Initialize`, to change the start (the expert's style, the robot's pose).
        after_start: called with the root Context after `Initialize` (and its publishes),
            before the first step (the replay starts Meshcat's recording there).
    """
    context = simulator.get_mutable_context()
    context.SetTime(0.0)
    diagram.SetRandomContext(context, RandomGenerator(seed))
    ReleaseSceneGraphModelCache(diagram)
    if before_start is not None:
        before_start(context)
    simulator.Initialize()
    if after_start is not None:
        after_start(context)


def RunEpisode(simulator: Simulator, diagram: Diagram, scene: DitchScene, seed: int,
               progress: str | None = None, before_start: Callable[[Context], None] | None = None,
               after_start: Callable[[Context], None] | None = None,
               watch: Callable[[Context], bool | None] | None = None, watch_period_s: float | None = None,
               end_time_s: float | None = None) -> EpisodeOutcome:
    """Runs one episode from a seeded random start until the monitor ends it: the one episode
    sequence of every path that runs one (evaluation, replay, demonstrations and DAgger, the
    benchmarks, the calibration, the DWA page).

    `StartEpisode` (time 0, `SetRandomContext(seed)`, `before_start`, `Initialize`,
    `after_start`), then `AdvanceTo` until the scene's episode monitor terminates the
    simulation, `watch` asks to stop, or the end time. The Simulator's monitor, where
    `progress` or `watch` uses it, is cleared afterwards.

    Args:
        simulator: a Simulator of `diagram`; one serves many episodes, each from a fresh start.
        diagram: the diagram whose random context (start jitter, sensor noise) `seed` draws.
        scene: the scene whose episode monitor ends and judges the episode.
        seed: seeds Drake's `RandomGenerator`.
        progress: a description for a progress bar of simulated time on stderr (None: none).
            It watches the steps through the Simulator's monitor and changes nothing.
        before_start: called with the root Context after the random draw and before
            `Initialize`, to change the start (the expert's style, the robot's pose).
        after_start: called with the root Context after `Initialize` (and its publishes),
            before the first step (the replay starts Meshcat's recording there).
        watch: called with the root Context as the episode runs, to look at it; returning True
            ends the episode there (its outcome then says "running" unless the monitor had
            ended it). When it is called is up to `watch_period_s`.
        watch_period_s: with `watch`, advance in chunks of this many simulated seconds (the
            last one cut at the end time) and call `watch` after each. None: call `watch` after
            `Initialize` and after every simulator step, as the Simulator's monitor.
        end_time_s: advance at most to this time (s); None: the time limit + 1 s, a backstop,
            since the monitor ends every episode at its time limit.

    Returns:
        The episode monitor's outcome when the run stopped.

    Raises:
        ValueError: a `watch_period_s` that is not positive, or one without `watch`.
    """
    if watch_period_s is not None and (watch is None or not watch_period_s > 0):
        raise ValueError(f"watch_period_s={watch_period_s!r} needs a watch and must be positive")
    end_s = scene.episode.time_limit_s + 1.0 if end_time_s is None else end_time_s
    bar = None if progress is None else tqdm(total=round(scene.episode.time_limit_s), desc=progress,
                                             unit="sim s", file=sys.stderr, leave=False)
    step_watch = watch if watch_period_s is None else None
    context = simulator.get_mutable_context()
    with bar if bar is not None else contextlib.nullcontext():
        if bar is not None or step_watch is not None:

            def monitor(root_context: Context) -> EventStatus:
                if bar is not None:
                    bar.update(int(root_context.get_time()) - bar.n)
                if step_watch is not None and step_watch(root_context):
                    return EventStatus.ReachedTermination(diagram, "the episode's watch ended it")
                return EventStatus.DidNothing()

            # Set before `Initialize`, which calls the monitor too.
            simulator.set_monitor(monitor)
        try:
            StartEpisode(simulator, diagram, seed, before_start, after_start)
            if watch_period_s is None:
                simulator.AdvanceTo(end_s)
            else:
                while True:
                    status = simulator.AdvanceTo(min(context.get_time() + watch_period_s, end_s))
                    stop = watch(context)
                    if (stop or status.reason() == SimulatorStatus.ReturnReason.kReachedTerminationCondition
                            or context.get_time() >= end_s):
                        break
        finally:
            if bar is not None or step_watch is not None:
                simulator.clear_monitor()
    return scene.monitor.outcome(scene.monitor.GetMyContextFromRoot(context))
