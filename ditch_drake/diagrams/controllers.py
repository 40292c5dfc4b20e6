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

Privilege is declared: each controller states what it reads beyond the robot's sensors, its
pose and the goal (`register_controller(..., privileged=("terrain",))`; the names and the words
the results pages use for them are `PRIVILEGED_INPUTS`), and is given only that. A controller
that does not declare "terrain" gets, in its `ControllerSite` and in the scene its builder
function sees, a stand-in for the analytic ditch that raises `ConfigError` naming the controller
on any use, so that reading the answer fails when the diagram is built rather than passing
unmarked. Its records carry what it declared (`RolloutRecord.privileged`), which every results
table marks.
"""

import dataclasses
import importlib
from dataclasses import dataclass, field
from typing import Any

from ditch_drake.common.errors import ConfigError

# What a controller may declare it reads beyond its sensors, its pose and the goal, and the
# words the results tables mark its rows with.
PRIVILEGED_INPUTS = {"terrain": "analytic terrain"}


@dataclass
class ControllerSite:
    """What a registered LeafSystem block may need of the scene it drives in.

    Attributes:
        terrain: the ditch (`ditch_drake.world.terrain.DitchTerrain`): analytic heights, slopes;
            for a controller that does not declare "terrain" privileged, an `UndeclaredInput`
            that raises `ConfigError` on any use.
        goal_xy: the task's goal [x m, y m].
        chassis_body_index: the chassis body's index in the plant's `body_poses`.
        schedule: the control period and offsets (`ditch_drake.spec.schedule.ScheduleConfig`).
    """

    terrain: Any
    goal_xy: Any
    chassis_body_index: Any
    schedule: Any


class UndeclaredInputError(ConfigError):
    """A controller read a privileged input it did not declare (a batch stops at the first)."""


class UndeclaredInput:
    """What a controller that has not declared a privileged input gets in its place: any
    attribute raises `ConfigError` naming the controller and how to declare the input.

    `rendered`: the scene's real terrain where the stand-in replaces it in the scene a builder
    function sees, so that the sensors the builder adds still render the ditch
    (`box_pieces`, which `AddLidar` gives the scene graph, and which the scene graph holds
    anyway); None in a `ControllerSite` and for the environment's terrain parameters.
    """

    __slots__ = ("_controller", "_input", "_rendered")

    def __init__(self, controller: str, name: str, rendered=None):
        object.__setattr__(self, "_controller", controller)
        object.__setattr__(self, "_input", name)
        object.__setattr__(self, "_rendered", rendered)

    def box_pieces(self):
        """The terrain's boxes as the sensors render them (`AddTerrainPerception`)."""
        if self._rendered is None:
            raise self._undeclared("box_pieces")
        return self._rendered.box_pieces()

    def _undeclared(self, attribute: str):
        return UndeclaredInputError(
            f"controller {self._controller!r} reads the {PRIVILEGED_INPUTS[self._input]} ({self._input}.{attribute}) "
            f"without declaring it: register it with privileged=({self._input!r},) "
            f"(register_controller(..., privileged=...)), and its results are marked privileged")

    def __getattr__(self, attribute: str):
        if attribute.startswith("__"):  # Python's own protocols (copy, pickle) look for these.
            raise AttributeError(attribute)
        raise self._undeclared(attribute)

    def __setattr__(self, attribute: str, value):
        raise self._undeclared(attribute)

    def __repr__(self) -> str:
        return f"UndeclaredInput({self._controller!r}, {self._input!r})"


def controller_view(scene, controller: str, privileged: tuple[str, ...]):
    """`scene` as controller `controller`, which declared `privileged`, may see it: without
    "terrain", its analytic terrain and its environment's terrain parameters are
    `UndeclaredInput`s (the scene's other parts, and the scene itself, are unchanged)."""
    if "terrain" in privileged:
        return scene
    environment = dataclasses.replace(scene.environment, terrain=UndeclaredInput(controller, "terrain"))
    return dataclasses.replace(scene, terrain=UndeclaredInput(controller, "terrain", rendered=scene.terrain),
                               environment=environment)


def privileged_words(names) -> str:
    """What the results tables call the privileged inputs `names` ("analytic terrain")."""
    return ", ".join(PRIVILEGED_INPUTS.get(name, name) for name in names)


def _check_privileged_names(controller: str, names) -> tuple[str, ...]:
    """`names` as a tuple of known privileged inputs.

    Raises:
        ConfigError: not a tuple or list of names of `PRIVILEGED_INPUTS`, naming the controller.
    """
    if isinstance(names, str) or not isinstance(names, (tuple, list)):
        raise ConfigError(f"controller {controller!r}: privileged={names!r}; expected a tuple of names among "
                          f"{list(PRIVILEGED_INPUTS)} (e.g. ('terrain',)), a function of the config giving one, "
                          "or \"module:function\"")
    unknown = [name for name in names if name not in PRIVILEGED_INPUTS]
    if unknown:
        raise ConfigError(f"controller {controller!r}: privileged input {unknown[0]!r}; expected one of "
                          f"{list(PRIVILEGED_INPUTS)}")
    return tuple(names)


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
        privileged: what it reads beyond its sensors, its pose and the goal: a tuple of names of
            `PRIVILEGED_INPUTS` (e.g. ("terrain",)), or `(config) -> tuple` for a controller
            whose privilege depends on its config, or "module:function"; () for none.
    """

    name: str
    description: str
    config: Any
    builder: Any
    default: Any = None
    per_seed: Any = None
    privileged: Any = ()
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

    def privileged_inputs(self, config) -> tuple[str, ...]:
        """What the controller of `config` declares it reads beyond its sensors, its pose and the goal.

        Raises:
            ConfigError: a declaration that gives anything but names of `PRIVILEGED_INPUTS`.
        """
        declared = self._get("privileged")
        return _check_privileged_names(self.name, declared(config) if callable(declared) else declared)

    def add(self, builder, scene, config):
        """Adds the controller's blocks to `scene`, given only the privileged inputs it declares
        (`controller_view`); returns the command output port.

        Raises:
            ConfigError: the controller reads an input it did not declare, naming it.
        """
        from pydrake.systems.framework import LeafSystem

        block = self._get("builder")
        privileged = self.privileged_inputs(config)
        if isinstance(block, type) and issubclass(block, LeafSystem):
            return _add_block(builder, scene, config, block, self.name, privileged)
        return block(builder, controller_view(scene, self.name, privileged), config)


_REGISTRY: dict[str, ControllerEntry] = {}
# The package's own controllers' names, once they are registered (at the end of this module).
_BUILT_IN: frozenset[str] = frozenset()


def register_controller(name: str, config, builder, description: str, default=None,
                        per_seed=None, privileged=()) -> ControllerEntry:
    """Registers a controller under `name` (see the module docstring); returns its entry.

    `privileged`: what it reads beyond its sensors, its pose and the goal
    (`ControllerEntry.privileged`); only that is given to it.

    Raises:
        ConfigError: `name` is one of the package's own controllers, is taken by another
            controller, or is not a lower_snake_case word; `privileged` names an unknown input.
    """
    if not isinstance(name, str) or not name.replace("_", "").isalnum() or name != name.lower():
        raise ConfigError(f"controller name {name!r}: expected lower_snake_case")
    # Replacing a built-in would change what every recorded rollout of that name means.
    if name in _BUILT_IN:
        raise ConfigError(f"controller name {name!r} is one of the package's own controllers "
                          f"{sorted(_BUILT_IN)}; expected another name")
    if not callable(privileged) and not (isinstance(privileged, str) and ":" in privileged):
        privileged = _check_privileged_names(name, privileged)
    entry = ControllerEntry(name, description, config, builder, default, per_seed, privileged)
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
    if name not in _REGISTRY:
        raise ConfigError(f"unknown controller {name!r}; expected one of {controller_names()}")
    return _REGISTRY[name]


def entry_for_config(config) -> ControllerEntry:
    """The first registered entry whose config type `config` is.

    Raises:
        ConfigError: a config of no registered controller.
    """
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
    if checkpoint and hasattr(config, "checkpoint"):  # A field, or a property of a nested policy's (shared).
        config = with_checkpoint(config, checkpoint)
    return entry.for_seed(config, seed) if seed is not None else config


def with_checkpoint(config, checkpoint: str):
    """`config` naming `checkpoint`: through the config's own `with_checkpoint` where it has one
    (the learned policy's: a .onnx file also sets its runtime), else its `checkpoint` replaced."""
    method = getattr(config, "with_checkpoint", None)
    return method(checkpoint) if callable(method) else dataclasses.replace(config, checkpoint=checkpoint)


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


def _add_block(builder, scene, config, block: type, name: str, privileged: tuple[str, ...]):
    """Builds a registered LeafSystem block and wires its inputs by name (module docstring)."""
    chassis = scene.plant.GetBodyByName("chassis", scene.husky)
    terrain = scene.terrain if "terrain" in privileged else UndeclaredInput(name, "terrain")
    site = ControllerSite(terrain, scene.task.goal, chassis.index(), scene.schedule)
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


def _learned_privileged(config) -> tuple[str, ...]:
    # The oracle side is read from the analytic ditch (`OracleCrossingSide`); a clone without a
    # side input ignores the setting, and is declared by it all the same (it could read it).
    return ("terrain",) if config.crossing_side == "oracle" else ()


register_controller(
    "learned", "ditch_drake.diagrams.rollout:LearnedPolicyConfig", "ditch_drake.diagrams.rollout:AddLearnedController",
    "the behavioural-cloning policy of a checkpoint (--checkpoint; default: the environment's shipped model)",
    privileged="ditch_drake.diagrams.controllers:_learned_privileged")
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
    per_seed="ditch_drake.diagrams.controllers:_expert_for_seed", privileged=("terrain",))
register_controller(
    "edge_angle", "ditch_drake.systems.edge_angle_driver:EdgeAngleDriverConfig",
    "ditch_drake.diagrams.rollout:AddEdgeAngleDriver",
    "the scripted shallow-angle driver with fixed angles (the physics reference)", privileged=("terrain",))
register_controller(
    "head_on", "ditch_drake.systems.edge_angle_driver:EdgeAngleDriverConfig",
    "ditch_drake.diagrams.rollout:AddEdgeAngleDriver",
    "the scripted driver straight into the ditch, perpendicular to its edge (rolls over)",
    default="ditch_drake.diagrams.rollout:head_on_config", privileged=("terrain",))
register_controller(
    "constant", "ditch_drake.diagrams.rollout:ConstantCommandConfig", "ditch_drake.diagrams.rollout:AddConstantCommand",
    "a fixed command [v m/s, w rad/s] (flat-ground tests)")
register_controller(
    "shared", "ditch_drake.diagrams.shared_controller:SharedControlControllerConfig",
    "ditch_drake.diagrams.shared_controller:AddSharedController",
    "the learned policy gated by its tip risk or its uncertainty: a fallback (the expert, or mppi) drives there",
    per_seed="ditch_drake.diagrams.shared_controller:shared_for_seed",
    privileged="ditch_drake.diagrams.shared_controller:shared_privileged")
_BUILT_IN = frozenset(_REGISTRY)
