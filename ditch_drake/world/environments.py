"""The named environments and their start/goal tasks, loaded from YAML data."""

import functools
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from ditch_drake.common.config_yaml import load_typed_yaml
from ditch_drake.common.errors import ConfigError, TerrainError
from ditch_drake.world.terrain import DitchTerrain, TerrainParams

# How far a task's start and goal must keep from the ditch's edge and from any wall (m).
TASK_CLEARANCE_M = 1.0


@dataclass
class Task:
    """One start/goal pair: start [x m, y m, yaw deg], goal [x m, y m]."""

    name: str = ""
    start: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    goal: list[float] = field(default_factory=lambda: [0.0, 0.0])


@dataclass
class Environment:
    """A terrain and its tasks.

    Attributes:
        description: one line for people.
        terrain: the ditch (and its walls, if fenced).
        tasks: start/goal pairs on opposite sides of the ditch.
        based_on: the environment this one varies ("wide" for "wide_walled"): the same ditch
            and tasks; its shipped model is the learned policy's default here, and reports
            pair the two. "": none.
    """

    description: str = ""
    terrain: TerrainParams = field(default_factory=TerrainParams)
    tasks: list[Task] = field(default_factory=list)
    based_on: str = ""


@dataclass
class EnvironmentLibrary:
    """The schema of an environments YAML file."""

    environments: dict[str, Environment] = field(default_factory=dict)


DEFAULT_ENVIRONMENTS_FILE = "environments.yaml"


def _default_path() -> Path:
    return Path(str(resources.files("ditch_drake.world") / DEFAULT_ENVIRONMENTS_FILE))


def load_environments(path: str | Path | None = None, prove_walls: bool = True) -> dict[str, Environment]:
    """Loads and validates an environments file (the packaged one by default).

    `prove_walls`: also prove, for each walled environment, that its walls leave no way
    round the ditch (`ditch_drake.world.bypass`, up to a second per environment), and for each
    one whose walls vary in slope, that each task has a way in and a way out
    (`ditch_drake.world.ingress`); the packaged file is read without them for listing names,
    and each of its environments is proven when first used (`get_environment`).

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
            validate_environment(environment, prove_walls)
        except (TerrainError, ConfigError) as error:
            raise ConfigError(f"environment {name!r} in {path}: {error}") from error
    names = set(library.environments) | (set() if path == _default_path() else set(environment_names(variants=True)))
    for name, environment in library.environments.items():
        if environment.based_on and environment.based_on not in names:
            raise ConfigError(f"environment {name!r} in {path}: based_on={environment.based_on!r} names no "
                              f"environment; expected one of {sorted(names)}")
    return library.environments


def validate_environment(environment: Environment, prove_walls: bool = True) -> None:
    """Raises TerrainError or ConfigError unless the terrain builds, its walls' windows are wider
    than the robot (`ingress.check_windows`), every task's start and goal keep
    `TASK_CLEARANCE_M` from the ditch's edge and the walls and lie on opposite sides, and (with
    `prove_walls`) no route bypasses a walled ditch and each task of a ditch whose walls vary
    in slope has a way in and out (`prove_routes`)."""
    terrain = DitchTerrain(environment.terrain)
    if terrain.sectioned:
        from ditch_drake.world.ingress import check_windows  # scipy's image module: see prove_no_bypass

        check_windows(terrain)
    if not environment.tasks:
        raise ConfigError("has no tasks")
    for task in environment.tasks:
        if len(task.start) != 3 or len(task.goal) != 2 or not np.all(np.isfinite(task.start + task.goal)):
            raise ConfigError(f"task {task.name!r}: start must be [x, y, yaw_deg] and goal [x, y], "
                              f"finite; got start={task.start}, goal={task.goal}")
        for label, xy in (("start", task.start[:2]), ("goal", task.goal)):
            clearance = float(terrain.beyond_edge_m(np.array(xy)))
            if clearance < TASK_CLEARANCE_M:
                raise ConfigError(f"task {task.name!r}: {label} {xy} must be on flat ground at least "
                                  f"{TASK_CLEARANCE_M:g} m from the ditch's edge (it is {clearance:.2f} m)")
            to_wall = float(terrain.distance_to_walls(np.array(xy)))
            if to_wall < TASK_CLEARANCE_M:
                raise ConfigError(f"task {task.name!r}: {label} {xy} is {to_wall:.2f} m from a wall: expected at "
                                  f"least {TASK_CLEARANCE_M:g} m (a wall crosses the task)")
        if not crosses_ditch(terrain, task.start[:2], task.goal):
            raise ConfigError(f"task {task.name!r}: start {task.start[:2]} and goal {task.goal} "
                              "are not on opposite sides of the ditch")
    if prove_walls:
        prove_routes(environment, terrain)


def prove_routes(environment: Environment, terrain: DitchTerrain | None = None) -> None:
    """Raises ConfigError, naming the task, unless no route of a walled environment bypasses its
    ditch (`prove_no_bypass`) and each task of a ditch whose walls vary in slope has a way in
    and a way out (`prove_ways_in_and_out`)."""
    terrain = terrain or DitchTerrain(environment.terrain)
    prove_no_bypass(environment, terrain)
    prove_ways_in_and_out(environment, terrain)


def prove_ways_in_and_out(environment: Environment, terrain: DitchTerrain | None = None) -> None:
    """Raises ConfigError, naming the task, unless each task of a ditch whose walls vary in
    slope has a way from its start down to the floor and one from the floor up to its goal
    (`ditch_drake.world.ingress`); nothing for a ditch without sections."""
    from ditch_drake.world.ingress import check_ways_in_and_out, traversable_grid

    terrain = terrain or DitchTerrain(environment.terrain)
    if terrain.sectioned:
        grid = traversable_grid(terrain)
        _check_each_task(environment, lambda task: check_ways_in_and_out(terrain, task.start[:2], task.goal, grid))


def prove_no_bypass(environment: Environment, terrain: DitchTerrain | None = None) -> None:
    """Raises ConfigError, naming the task, unless every route of every task of a walled
    environment crosses its ditch (`ditch_drake.world.bypass`); nothing for an open one."""
    # Imported here: scipy's image and graph modules would cost `ditch-drake --help` half a second.
    from ditch_drake.world.bypass import check_no_bypass, rasterize_field

    terrain = terrain or DitchTerrain(environment.terrain)
    if terrain.walled:
        grid = rasterize_field(terrain)
        _check_each_task(environment, lambda task: check_no_bypass(terrain, task.start[:2], task.goal, grid))


def _check_each_task(environment: Environment, check) -> None:
    """Runs `check(task)` for each task, naming the task in the ConfigError of the first that fails."""
    for task in environment.tasks:
        try:
            check(task)
        except ConfigError as error:
            raise ConfigError(f"task {task.name!r}: {error}") from error


def crosses_ditch(terrain: DitchTerrain, start_xy, goal_xy) -> bool:
    """Whether the straight line from start to goal passes through the ditch's bottom."""
    samples = np.linspace(np.asarray(start_xy, float), np.asarray(goal_xy, float), 400)
    return bool(np.any(terrain.nearest_on_course(samples)[0] <= terrain.toe_distance_m + 1e-6))


@functools.cache
def _packaged_environments() -> dict[str, Environment]:
    return load_environments(prove_walls=False)


@functools.cache
def _proven_packaged(name: str) -> Environment:
    environment = _packaged_environments()[name]
    try:
        prove_routes(environment)
    except ConfigError as error:
        raise ConfigError(f"environment {name!r} in {_default_path()}: {error}") from error
    return environment


def _file_key(path: Path) -> tuple:
    try:
        stat = path.stat()
    except OSError:
        return (str(path.resolve()), None, None)
    return (str(path.resolve()), stat.st_mtime_ns, stat.st_size)


def _file_environments(path: Path) -> dict[str, Environment]:
    """An environments file's environments, validated but not yet proven (`load_environments`
    with `prove_walls` False), read once per version of the file: a benchmark's file holds a
    hundred ditches, and each rollout's worker asks for one of them."""
    return _cached_file_environments(_file_key(path))


@functools.lru_cache(maxsize=8)
def _cached_file_environments(key: tuple) -> dict[str, Environment]:
    return load_environments(key[0], prove_walls=False)


@functools.lru_cache(maxsize=512)
def _cached_proof(key: tuple, name: str) -> Environment:
    environment = _cached_file_environments(key)[name]
    try:
        prove_routes(environment)
    except ConfigError as error:
        raise ConfigError(f"environment {name!r} in {key[0]}: {error}") from error
    return environment


def _proven_from_file(path: Path, name: str) -> Environment:
    """A file's environment, its routes proven (`prove_routes`, once per version of the file)."""
    return _cached_proof(_file_key(path), name)


def environment_names(variants: bool = False) -> list[str]:
    """Names of the packaged environments: the paper's four, and with `variants` also those
    based on them (`Environment.based_on`: the walled ones, and the search ones based on
    `wide_walled`)."""
    return [name for name, environment in _packaged_environments().items() if variants or not environment.based_on]


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
            validate_environment(inline[name])
        except (TerrainError, ConfigError) as error:
            raise ConfigError(f"environment {name!r} defined in the scenario: {error}") from error
        return inline[name]
    environments = _file_environments(Path(path)) if path else {}
    if name in environments:
        return _proven_from_file(Path(path), name)
    packaged = _packaged_environments()
    if name not in packaged:
        known = [*environments, *(inline or {}), *packaged]
        where = f" (in {path} or packaged)" if path else ""
        raise ConfigError(f"unknown environment {name!r}{where}: expected one of {known}")
    return _proven_packaged(name)


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
