"""The named environments and their start/goal tasks, loaded from YAML data."""

import functools
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from ditch_drake.common.config_yaml import load_typed_yaml
from ditch_drake.common.errors import ConfigError, TerrainError
from ditch_drake.world.terrain import DitchTerrain, TerrainParams


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
    return Path(str(resources.files("ditch_drake.world") / DEFAULT_ENVIRONMENTS_FILE))


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


def get_environment(name: str, path: str | Path | None = None,
                    inline: dict[str, Environment] | None = None) -> Environment:
    """A named environment: from `inline` definitions (a scenario's own, validated here) if
    it is one of them, else from the file at `path` if it is one of its, else a packaged one
    (a file of one's own adds to the packaged environments; its names come first).

    Raises:
        ConfigError: the name is unknown (the message lists the known names), or an inline
            definition is out of range.
    """
    if inline and name in inline:
        try:
            _validate_environment(inline[name])
        except (TerrainError, ConfigError) as error:
            raise ConfigError(f"environment {name!r} defined in the scenario: {error}") from error
        return inline[name]
    environments = load_environments(path) if path else {}
    if name in environments:
        return environments[name]
    packaged = _packaged_environments()
    if name not in packaged:
        known = [*environments, *(inline or {}), *packaged]
        where = f" (in {path} or packaged)" if path else ""
        raise ConfigError(f"unknown environment {name!r}{where}: expected one of {known}")
    return packaged[name]


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
