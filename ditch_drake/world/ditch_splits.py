"""Which split a ditch belongs to, from its name: the seed ranges of the generated splits.

The seed ranges are disjoint, so a seed names its split; a generated ditch is named
`ditch_<seed>`, and the packaged environments are the paper's split. The benchmark draws the
ditches (`ditch_drake.benchmark.splits`); demonstrations record the split of theirs.
"""

from ditch_drake.world.environments import environment_names

SEED_SPLITS = {"train": range(200), "val": range(1000, 1050), "test": range(2000, 2100),
               "stress": range(3000, 3100), "search": range(4000, 4100), "search_val": range(4100, 4150)}
PAPER_SPLIT = "paper"
SPLITS = (*SEED_SPLITS, PAPER_SPLIT)
# The generated splits a choice may see (a checkpoint, a recipe, a gate's thresholds); the
# others are held out for reporting.
CHOICE_SPLITS = ("train", "val", "search_val")
# How the file of a run's generated ditches is named: `<results stem>.ditches.yaml`.
DITCHES_SUFFIX = ".ditches.yaml"


def is_ditches_file(path) -> bool:
    """Whether `path` (str or Path) names a file of generated ditches (`DITCHES_SUFFIX`)."""
    return str(path).endswith(DITCHES_SUFFIX)


def split_of_seed(seed: int) -> str:
    """The split a generated ditch's seed belongs to ("" for none)."""
    return next((split for split, seeds in SEED_SPLITS.items() if seed in seeds), "")


def seed_of_environment(name: str) -> int | None:
    """The seed of a generated ditch's name (`ditch_<seed>`), else None."""
    prefix, _, number = name.partition("_")
    return int(number) if prefix == "ditch" and number.isdigit() else None


def split_of_environment(name: str) -> str:
    """The split of an environment name: a packaged one is "paper", `ditch_<seed>` its seed's."""
    if name in environment_names(variants=True):
        return PAPER_SPLIT
    seed = seed_of_environment(name)
    return split_of_seed(seed) if seed is not None else ""
