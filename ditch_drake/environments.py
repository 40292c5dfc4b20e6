"""The named environments and their start/goal tasks, loaded from YAML data."""

import dataclasses
import functools
import math
import types
import typing
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np
import yaml
from pydrake.common.yaml import yaml_load_typed

from ditch_drake.errors import ConfigError, TerrainError
from ditch_drake.terrain import DitchTerrain, TerrainParams


@dataclass
class Task:
    """One start/goal pair: start [x m, y m, yaw deg], goal [x m, y m]."""

    name: str = ""
    start: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    goal: list[float] = field(default_factory=lambda: [0.0, 0.0])


@dataclass
class Environment:
    """A terrain and its tasks."""

    description: str = ""
    terrain: TerrainParams = field(default_factory=TerrainParams)
    tasks: list[Task] = field(default_factory=list)


@dataclass
class EnvironmentLibrary:
    """The schema of an environments YAML file."""

    environments: dict[str, Environment] = field(default_factory=dict)


DEFAULT_ENVIRONMENTS_FILE = "environments.yaml"


def _default_path() -> Path:
    return Path(str(resources.files("ditch_drake") / "data" / DEFAULT_ENVIRONMENTS_FILE))


def load_typed_yaml(path: str | Path, schema: type, what: str):
    """A YAML file read into the dataclass `schema` with Drake's `yaml_load_typed`.

    Raises:
        ConfigError: the file cannot be read, is not YAML, or has unknown keys or wrong
            types (a typo'd key is an error, not ignored); the message names `what` and the file.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as error:
        raise ConfigError(f"cannot read {what} {path}: {error}") from error
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as error:
        raise ConfigError(f"malformed YAML in {path}: {error}") from error
    if root is None:
        raise ConfigError(f"{what} {path} is empty; expected a mapping of {schema.__name__}'s fields")
    _check_node(root, schema, f"{what} {path}", "")
    try:
        return yaml_load_typed(schema=schema, data=text)
    except (RuntimeError, ValueError, TypeError, AssertionError) as error:
        raise ConfigError(f"invalid {what} {path}: {error}") from error


_SCALAR_TAGS = {int: ("int",), float: ("int", "float"), bool: ("bool",), str: ("str", "int", "float", "bool")}


def _check_node(node, schema, where: str, key: str) -> None:
    """Raises ConfigError naming the key, its line, the bad value and the expected type, for a
    YAML node that does not fit `schema` (a dataclass, a scalar type, list, dict or Optional).
    Types it does not know are left to `yaml_load_typed`."""
    line = node.start_mark.line + 1
    name = key or "the top level"
    origin, arguments = typing.get_origin(schema), typing.get_args(schema)
    if origin in (typing.Union, types.UnionType):
        if node.tag == "tag:yaml.org,2002:null" and type(None) in arguments:
            return
        options = [argument for argument in arguments if argument is not type(None)]
        if len(options) == 1:
            _check_node(node, options[0], where, key)
        return
    if dataclasses.is_dataclass(schema):
        if not isinstance(node, yaml.MappingNode):
            raise ConfigError(f"{where}, line {line}: {name} is {_describe(node)}; expected a mapping of "
                              f"{schema.__name__}'s fields")
        field_types = typing.get_type_hints(schema)
        for key_node, value_node in node.value:
            if key_node.value not in field_types:
                raise ConfigError(f"{where}, line {key_node.start_mark.line + 1}: unknown key "
                                  f"{_join(key, key_node.value)!r}; expected one of {sorted(field_types)}")
            _check_node(value_node, field_types[key_node.value], where, _join(key, key_node.value))
        return
    if origin is list:
        if not isinstance(node, yaml.SequenceNode):
            raise ConfigError(f"{where}, line {line}: {name} is {_describe(node)}; expected a list")
        for index, item in enumerate(node.value):
            _check_node(item, arguments[0] if arguments else typing.Any, where, f"{key}[{index}]")
        return
    if origin is dict:
        if not isinstance(node, yaml.MappingNode):
            raise ConfigError(f"{where}, line {line}: {name} is {_describe(node)}; expected a mapping")
        for key_node, value_node in node.value:
            _check_node(value_node, arguments[1] if arguments else typing.Any, where, _join(key, key_node.value))
        return
    if schema in _SCALAR_TAGS:
        tag = node.tag.rsplit(":", 1)[-1] if isinstance(node, yaml.ScalarNode) else None
        if tag not in _SCALAR_TAGS[schema]:
            raise ConfigError(f"{where}, line {line}: {name} is {_describe(node)}; expected {schema.__name__}")


def _join(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else str(key)


def _describe(node) -> str:
    if isinstance(node, yaml.ScalarNode):
        return f"{node.value!r} ({node.tag.rsplit(':', 1)[-1]})"
    return "a list" if isinstance(node, yaml.SequenceNode) else "a mapping"


def load_environments(path: str | Path | None = None) -> dict[str, Environment]:
    """Loads and validates an environments file (the packaged one by default).

    Raises:
        ConfigError: the file cannot be read or parsed, has unknown fields, or
            holds a value out of range; the message names the file and the value.
    """
    path = Path(path) if path is not None else _default_path()
    library = load_typed_yaml(path, EnvironmentLibrary, "environments file")
    if not library.environments:
        raise ConfigError(f"environments file {path} defines no environments")
    for name, environment in library.environments.items():
        try:
            _validate_environment(environment)
        except (TerrainError, ConfigError) as error:
            raise ConfigError(f"environment {name!r} in {path}: {error}") from error
    return library.environments


def _validate_environment(environment: Environment) -> None:
    terrain = DitchTerrain(environment.terrain)
    if not environment.tasks:
        raise ConfigError("has no tasks")
    for task in environment.tasks:
        if len(task.start) != 3 or len(task.goal) != 2 or not np.all(np.isfinite(task.start + task.goal)):
            raise ConfigError(f"task {task.name!r}: start must be [x, y, yaw_deg] and goal [x, y], "
                              f"finite; got start={task.start}, goal={task.goal}")
        for label, xy in (("start", task.start[:2]), ("goal", task.goal)):
            clearance = float(terrain.nearest_on_course(np.array(xy))[0]) - terrain.hinge_distance_m
            if clearance < 1.0:
                raise ConfigError(f"task {task.name!r}: {label} {xy} must be on flat ground at least 1 m "
                                  f"from the ditch's edge (it is {clearance:.2f} m)")
        if not crosses_ditch(terrain, task.start[:2], task.goal):
            raise ConfigError(f"task {task.name!r}: start {task.start[:2]} and goal {task.goal} "
                              "are not on opposite sides of the ditch")


def crosses_ditch(terrain: DitchTerrain, start_xy, goal_xy) -> bool:
    """Whether the straight line from start to goal passes through the ditch's bottom."""
    samples = np.linspace(np.asarray(start_xy, float), np.asarray(goal_xy, float), 400)
    return bool(np.any(terrain.nearest_on_course(samples)[0] <= terrain.toe_distance_m + 1e-6))


@functools.cache
def _packaged_environments() -> dict[str, Environment]:
    return load_environments()


def environment_names() -> list[str]:
    """Names of the packaged environments."""
    return list(_packaged_environments())


def get_environment(name: str, path: str | Path | None = None) -> Environment:
    """A named environment from the packaged file, or from `path`.

    Raises:
        ConfigError: the name is unknown; the message lists the known names.
    """
    environments = _packaged_environments() if path is None else load_environments(path)
    if name not in environments:
        raise ConfigError(f"unknown environment {name!r}: expected one of {sorted(environments)}")
    return environments[name]


def get_task(environment: Environment, task: int | str) -> Task:
    """A task of `environment` by index or name."""
    names = [t.name for t in environment.tasks]
    if isinstance(task, str):
        if task not in names:
            raise ConfigError(f"unknown task {task!r}: expected one of {names}")
        return environment.tasks[names.index(task)]
    if not 0 <= task < len(environment.tasks):
        raise ConfigError(f"task index {task} is out of range: expected 0..{len(environment.tasks) - 1}")
    return environment.tasks[task]


def start_yaw_rad(task: Task) -> float:
    return math.radians(task.start[2])
