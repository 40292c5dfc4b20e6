"""The benchmark's named splits, and the file of ditches a benchmark run drives in.

| split | what | use |
| --- | --- | --- |
| train | seeds 0-199 | demonstrations and DAgger rounds |
| val | seeds 1000-1049 | every choice: checkpoints, recipes, ranges |
| test | seeds 2000-2099 | the reported result only: never a choice |
| stress | seeds 3000-3099, drawn from `stress_ranges.yaml` | reported beside test, never a choice: ditches beyond the train ranges, how far a controller extrapolates |
| search | seeds 4000-4099, drawn from `search_ranges.yaml` | the reported result only, never a choice: ditches crossable only through windows in their steep walls |
| search_val | seeds 4100-4149, drawn from `search_ranges.yaml` | every choice for the search ditches |
| paper | the four packaged environments | the paper's ditches, beside the generated ones |

The seed ranges are disjoint, so a seed names its split. Each generated split draws from its
ranges file (`SPLIT_RANGES`; `ranges.yaml` unless listed there), unless a run names another.
A run's ditches are written, as an environments file in the packaged schema
(`ditch_drake/world/environments.yaml`), beside its results: `<results>.ditches.yaml`. Its
environments are the `sample_ditch` draws of their seeds, so
`ditch-drake replay --environments <that file> --env ditch_2013 --task 1 --seed 0` replays any
rollout.
"""

from pathlib import Path

from pydrake.common.yaml import yaml_dump_typed

from ditch_drake.benchmark.generator import SampledDitch, sample_ditch
from ditch_drake.benchmark.ranges import BenchmarkRanges, load_ranges, packaged_ranges_path
from ditch_drake.common.errors import ConfigError
from ditch_drake.common.files import atomic_write_text
from ditch_drake.systems.episode_monitor import EpisodeConfig
from ditch_drake.world.ditch_splits import (  # noqa: F401 (the benchmark's names for them)
    DITCHES_SUFFIX,
    PAPER_SPLIT,
    SEED_SPLITS,
    SPLITS,
    split_of_environment,
    split_of_seed,
)
from ditch_drake.world.environments import Environment, EnvironmentLibrary, environment_names, load_environments

# The episode time limit (s) of each split whose routes are longer than a crossing's: in a
# search ditch the way in and the way out may lie at opposite ends of a course up to 70 m long
# (the expert's routes on search_val ran up to 130 m at 1 m/s), and a controller that searches
# from its sensors walks the edge both ways first. Other splits: `EpisodeConfig.time_limit_s`.
SPLIT_TIME_LIMITS_S = {"search": 240.0, "search_val": 240.0}

# The packaged ranges file of each generated split that does not draw from `ranges.yaml`.
SPLIT_RANGES = {"stress": "stress_ranges.yaml", "search": "search_ranges.yaml", "search_val": "search_ranges.yaml"}


def check_split(split: str) -> None:
    if split not in SPLITS:
        raise ConfigError(f"unknown split {split!r}: expected one of {list(SPLITS)}")


def split_time_limit_s(split: str) -> float:
    """The episode time limit (s) a benchmark of `split` runs with unless told another
    (`SPLIT_TIME_LIMITS_S`, else the episode's default)."""
    check_split(split)
    return SPLIT_TIME_LIMITS_S.get(split, EpisodeConfig.time_limit_s)


def split_seeds(split: str, geometries: int | None = None) -> list[int]:
    """The first `geometries` seeds of a generated split (all of them for None).

    Raises:
        ConfigError: an unknown split, the paper split (it has no seeds), or a count outside
            1..the split's size.
    """
    check_split(split)
    if split == PAPER_SPLIT:
        raise ConfigError(f"split {split!r} holds the packaged environments {environment_names()}, not seeds")
    seeds = SEED_SPLITS[split]
    if geometries is not None and not 1 <= geometries <= len(seeds):
        raise ConfigError(f"geometries={geometries} is out of range for split {split!r}: expected 1..{len(seeds)}")
    return list(seeds[:geometries])


def split_ranges(split: str, path: str | Path | None = None) -> BenchmarkRanges:
    """The ranges a generated split draws from: the file at `path`, else the split's packaged
    one (`SPLIT_RANGES`, else `ranges.yaml`), validated.

    Raises:
        ConfigError: an unknown split, or a ranges file that is unreadable or out of bounds.
    """
    check_split(split)
    return load_ranges(path or packaged_ranges_path(SPLIT_RANGES.get(split, "ranges.yaml")))


def split_ditches(split: str, geometries: int | None = None,
                  ranges: BenchmarkRanges | None = None) -> list[SampledDitch]:
    """The sampled ditches of the first `geometries` seeds of a generated split, drawn from
    `ranges` (None: the split's, `split_ranges`)."""
    seeds = split_seeds(split, geometries)
    ranges = ranges or split_ranges(split)
    return [sample_ditch(seed, ranges) for seed in seeds]


def ditches_file(results_path: str | Path) -> Path:
    """Where a run's ditches are written: `<results without .jsonl>.ditches.yaml`."""
    path = Path(results_path)
    return path.with_name(path.stem + DITCHES_SUFFIX)


def write_ditches(path: str | Path, ditches: list[SampledDitch]) -> Path:
    """Adds `ditches` to the environments file at `path` (created if missing), atomically.

    Raises:
        ConfigError: the file holds a ditch of the same name that differs (drawn from other
            ranges): results would mix two ditches under one name.
    """
    path = Path(path)
    environments: dict[str, Environment] = dict(load_environments(path, prove_walls=False)) if path.exists() else {}
    changed = False
    for ditch in ditches:
        if ditch.name in environments:
            if repr(environments[ditch.name]) != repr(_as_written(ditch.environment)):
                raise ConfigError(f"{path} holds a different {ditch.name} (drawn from other ranges?): write this "
                                  "run's results and ditches elsewhere (--out)")
            continue
        environments[ditch.name] = ditch.environment
        changed = True
    if changed or not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        header = "# Procedural ditches (ditch_drake/benchmark): written by `ditch-drake benchmark`.\n"
        atomic_write_text(path, header + yaml_dump_typed(EnvironmentLibrary(environments=environments)))
    return path


def _as_written(environment: Environment) -> Environment:
    """The environment as it reads back from YAML (floats and lists as written)."""
    from pydrake.common.yaml import yaml_load_typed

    return yaml_load_typed(schema=Environment, data=yaml_dump_typed(environment))
