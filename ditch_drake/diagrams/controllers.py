"""The registry of controllers: the one list that the command line, scenarios, batch
evaluation, the demo and experiments read.

A controller is a config dataclass, a builder that adds its blocks to a scene and returns
their `command` output port ([v m/s, w rad/s]), and one `register_controller` line. The
built-in ones are registered below by "module:attribute" strings, so that this module
imports nothing heavy and `ditch-drake --help` lists them at once; `ControllerEntry`
imports a module only when its config or builder is first used. A user registers hers with
the objects themselves (docs/tutorials/your_controller.md):

    register_controller("mine", MyConfig, AddMine, "what it does")

where `AddMine(builder, scene, config) -> OutputPort` may also be a `LeafSystem` subclass:
then the registry builds `MyBlock(config, ControllerSite(...))` and connects each of its
input ports that it recognizes by name (`body_poses`, `point_cloud`, and the observation
stacks `image_stack`, `imu_stack`, `distance_stack`, `bearing_stack`), and the block's
`command` output drives.
"""

import dataclasses
import importlib
from dataclasses import dataclass, field
from typing import Any


@dataclass
class ControllerSite:
    """What a registered LeafSystem block may need of the scene it drives in.

    Attributes:
        terrain: the ditch (`ditch_drake.world.terrain.DitchTerrain`): analytic heights, slopes.
        goal_xy: the task's goal [x m, y m].
        chassis_body_index: the chassis body's index in the plant's `body_poses`.
        schedule: the control period and offsets (`ditch_drake.spec.schedule.ScheduleConfig`).
    """

    terrain: Any
    goal_xy: Any
    chassis_body_index: Any
    schedule: Any


def _resolve(reference):
    """The object named by "module:attribute", or `reference` itself."""
    if not isinstance(reference, str):
        return reference
    module, _, attribute = reference.partition(":")
    return getattr(importlib.import_module(module), attribute)


@dataclass
class ControllerEntry:
    """One registered controller.

    Attributes:
        name: what the command line and results call it.
        description: one line for `--help`.
        config: its config dataclass (or "module:Class").
        builder: `(builder, scene, config) -> OutputPort`, or a LeafSystem subclass built
            as `Block(config, ControllerSite)` and wired by port name (or "module:attribute").
        default: a function giving its default config (None: `config()`), or "module:function".
        per_seed: `(config, seed) -> config`, for a controller whose diagram depends on the
            episode's seed (the expert draws its style from it), or "module:function"; None: not.
    """

    name: str
    description: str
    config: Any
    builder: Any
    default: Any = None
    per_seed: Any = None
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def _get(self, attribute: str):
        if attribute not in self._cache:
            self._cache[attribute] = _resolve(getattr(self, attribute))
        return self._cache[attribute]

    @property
    def config_type(self) -> type:
        return self._get("config")

    def default_config(self):
        default = self._get("default")
        return default() if default is not None else self.config_type()

    def for_seed(self, config, seed: int):
        """The config that an episode of `seed` builds (the same config for most controllers)."""
        per_seed = self._get("per_seed")
        return per_seed(config, seed) if per_seed is not None else config

    def add(self, builder, scene, config):
        """Adds the controller's blocks to `scene`; returns the command output port."""
        from pydrake.systems.framework import LeafSystem

        block = self._get("builder")
        if isinstance(block, type) and issubclass(block, LeafSystem):
            return _add_block(builder, scene, config, block, self.name)
        return block(builder, scene, config)


_REGISTRY: dict[str, ControllerEntry] = {}
# The package's own controllers' names, once they are registered (at the end of this module).
_BUILT_IN: frozenset[str] = frozenset()


def register_controller(name: str, config, builder, description: str, default=None,
                        per_seed=None) -> ControllerEntry:
    """Registers a controller under `name` (see the module docstring); returns its entry.

    Raises:
        ConfigError: `name` is one of the package's own controllers, is taken by another
            controller, or is not a lower_snake_case word.
    """
    from ditch_drake.common.errors import ConfigError

    if not isinstance(name, str) or not name.replace("_", "").isalnum() or name != name.lower():
        raise ConfigError(f"controller name {name!r}: expected lower_snake_case")
    # Replacing a built-in would change what every recorded rollout of that name means.
    if name in _BUILT_IN:
        raise ConfigError(f"controller name {name!r} is one of the package's own controllers "
                          f"{sorted(_BUILT_IN)}; expected another name")
    entry = ControllerEntry(name, description, config, builder, default, per_seed)
    known = _REGISTRY.get(name)
    if known is not None and (known.config, known.builder) != (config, builder):
        raise ConfigError(f"controller {name!r} is already registered with config {known.config}; expected "
                          "another name")
    _REGISTRY[name] = entry
    return entry


def controller_names() -> list[str]:
    return list(_REGISTRY)


def controller_descriptions() -> dict[str, str]:
    return {name: entry.description for name, entry in _REGISTRY.items()}


def get_controller(name: str) -> ControllerEntry:
    """The entry of `name`.

    Raises:
        ConfigError: an unknown name, naming the known ones.
    """
    from ditch_drake.common.errors import ConfigError

    if name not in _REGISTRY:
        raise ConfigError(f"unknown controller {name!r}; expected one of {controller_names()}")
    return _REGISTRY[name]


def entry_for_config(config) -> ControllerEntry:
    """The first registered entry whose config type `config` is.

    Raises:
        ConfigError: a config of no registered controller.
    """
    from ditch_drake.common.errors import ConfigError

    for entry in _REGISTRY.values():
        if type(config) is entry.config_type:
            return entry
    raise ConfigError(f"{type(config).__name__} is the config of no registered controller; expected one of "
                      f"{sorted({entry.config_type.__name__ for entry in _REGISTRY.values()})}")


def controller_config_types() -> tuple[type, ...]:
    """Every registered config type, once each, in registration order (the scenario's union)."""
    types = []
    for entry in _REGISTRY.values():
        if entry.config_type not in types:
            types.append(entry.config_type)
    return tuple(types)


def controller_config(name: str, checkpoint: str = "", seed: int | None = None):
    """The default config of controller `name`; a learned policy's `checkpoint` set, and the
    expert's style drawn from `seed` when one is given.

    Raises:
        ConfigError: an unknown name.
    """
    entry = get_controller(name)
    config = entry.default_config()
    if checkpoint and any(f.name == "checkpoint" for f in dataclasses.fields(config)):
        config = dataclasses.replace(config, checkpoint=checkpoint)
    return entry.for_seed(config, seed) if seed is not None else config


def check_controller_config(config) -> ControllerEntry:
    """The entry of a registered controller's config, after checking every value of it the
    controller's blocks would check when built: each nested config's `validate()` and no NaN.
    Cheap (nothing is built), so a batch checks its config before any rollout rather than
    recording each rollout as an error.

    Raises:
        ConfigError: a config of no registered controller, or a value out of range, naming
            the controller and the value.
    """
    from ditch_drake.common.checks import check_no_nan
    from ditch_drake.common.errors import ConfigError

    entry = entry_for_config(config)
    check_no_nan(config, f"controller {entry.name!r} config")
    for part in _nested_configs(config):
        validate = getattr(part, "validate", None)
        if callable(validate):
            try:
                validate()
            except (ValueError, TypeError) as error:  # Some configs raise plain ValueError.
                raise ConfigError(f"controller {entry.name!r}: {error}") from error
    return entry


def _nested_configs(config):
    """`config` and every dataclass inside it (fields, lists, dicts), outermost first."""
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        yield config
        for f in dataclasses.fields(config):
            yield from _nested_configs(getattr(config, f.name))
    elif isinstance(config, (list, tuple)):
        for item in config:
            yield from _nested_configs(item)
    elif isinstance(config, dict):
        for item in config.values():
            yield from _nested_configs(item)


def config_checkpoint(config) -> str:
    """The checkpoint a controller's config names ("" if it has none)."""
    return str(getattr(config, "checkpoint", "") or "")


_PORT_SOURCES = ("body_poses", "point_cloud", "image_stack", "imu_stack", "distance_stack", "bearing_stack")


def _add_block(builder, scene, config, block: type, name: str):
    """Builds a registered LeafSystem block and wires its inputs by name (module docstring)."""
    from ditch_drake.common.errors import ConfigError

    chassis = scene.plant.GetBodyByName("chassis", scene.husky)
    site = ControllerSite(scene.terrain, scene.task.goal, chassis.index(), scene.schedule)
    system = builder.AddNamedSystem(name, block(config, site))
    inputs = [system.get_input_port(i).get_name() for i in range(system.num_input_ports())]
    unknown = [port for port in inputs if port not in _PORT_SOURCES]
    if unknown or not system.HasOutputPort("command"):
        raise ConfigError(f"controller {name!r}: {block.__name__} needs a 'command' output and inputs among "
                          f"{list(_PORT_SOURCES)}; it has inputs {inputs}")
    if "body_poses" in inputs:
        builder.Connect(scene.plant.get_body_poses_output_port(), system.GetInputPort("body_poses"))
    observation = None
    if any(port.endswith("_stack") for port in inputs):
        from ditch_drake.diagrams.observation import AddObservation

        observation = AddObservation(builder, scene)
        for port in inputs:
            if port in observation.ports:
                builder.Connect(observation.ports[port], system.GetInputPort(port))
    if "point_cloud" in inputs:
        if observation is not None:
            lidar = observation.lidar
        else:
            from ditch_drake.diagrams.lidar_rig import AddLidar

            lidar = AddLidar(builder, scene)
        builder.Connect(lidar.converter.GetOutputPort("organized_points"), system.GetInputPort("point_cloud"))
    return system.GetOutputPort("command")


def _expert_for_seed(config, seed: int):
    return dataclasses.replace(config, style_seed=seed) if config.style_seed is None else config


register_controller(
    "learned", "ditch_drake.diagrams.rollout:LearnedPolicyConfig", "ditch_drake.diagrams.rollout:AddLearnedController",
    "the behavioural-cloning policy of a checkpoint (--checkpoint; default: the environment's shipped model)")
register_controller(
    "dwa", "ditch_drake.diagrams.rollout:DwaBaselineConfig", "ditch_drake.diagrams.rollout:AddDwaController",
    "the move_base-style baseline: slope costmap, Dijkstra global plan, DWA local planner")
register_controller(
    "dwa_paper", "ditch_drake.diagrams.rollout:DwaBaselineConfig", "ditch_drake.diagrams.rollout:AddDwaController",
    "the paper's move_base: the dwa block with cost rising with slope, no slope lethal, walls lethal",
    default="ditch_drake.diagrams.rollout:paper_dwa_config")
register_controller(
    "mppi", "ditch_drake.diagrams.rollout:MppiBaselineConfig", "ditch_drake.diagrams.rollout:AddMppiController",
    "the rollover-aware MPPI baseline: elevation map, predicted attitude and tip margin per sample")
register_controller(
    "expert", "ditch_drake.diagrams.rollout:ExpertConfig", "ditch_drake.diagrams.rollout:AddExpert",
    "the scripted shallow-angle expert that made the demonstrations (its style drawn from the seed)",
    per_seed="ditch_drake.diagrams.controllers:_expert_for_seed")
register_controller(
    "edge_angle", "ditch_drake.systems.edge_angle_driver:EdgeAngleDriverConfig",
    "ditch_drake.diagrams.rollout:AddEdgeAngleDriver",
    "the scripted shallow-angle driver with fixed angles (the physics reference)")
register_controller(
    "head_on", "ditch_drake.systems.edge_angle_driver:EdgeAngleDriverConfig",
    "ditch_drake.diagrams.rollout:AddEdgeAngleDriver",
    "the scripted driver straight into the ditch, perpendicular to its edge (rolls over)",
    default="ditch_drake.diagrams.rollout:head_on_config")
register_controller(
    "constant", "ditch_drake.diagrams.rollout:ConstantCommandConfig", "ditch_drake.diagrams.rollout:AddConstantCommand",
    "a fixed command [v m/s, w rad/s] (flat-ground tests)")
_BUILT_IN = frozenset(_REGISTRY)
