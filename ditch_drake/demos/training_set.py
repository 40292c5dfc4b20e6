"""A dataset folder as a training `ArraySet` whose images stay on disk.

`to_array_set(load_dataset(folder), strides)` reads every frame into memory and stacks it four
times (64 KiB a sample). `training_set` makes the same samples from a store
(`ditch_drake.demos.store`) reading only the small fields: the scalars, labels and demonstration
ids are in memory (80 bytes a sample), and the image is a
`ditch_drake.learning.stream.LazyImageStack` over each episode's `image.npy`, which builds a
batch's stacks when training asks for them. Reflected samples (the generalist's mirror and
canonical side) have their scalars and labels reflected here and their images where they are
read. A folder of `.npz` files (the older format, which cannot be read in part) is loaded into
memory as before.

    episodes = dataset_episodes("data/wide", max_demos=40)
    arrays = training_set(episodes)             # or load_training_set(["data/wide"], 40)
    train(arrays, TrainConfig())

Only complete episodes are read: a torn one (`DatasetStore.episodes`) is skipped with a warning
and none of its files is opened. An episode whose arrays disagree with its step count raises
`DatasetError` naming the file, when the set is made, not in the middle of training.
"""

import os
from dataclasses import dataclass

import numpy as np

from ditch_drake.common.errors import DatasetError
from ditch_drake.demos.dataset import Demonstration, to_array_set
from ditch_drake.demos.store import (
    DatasetStore,
    Episode,
    demonstration_metadata,
    first_episodes,
    is_store,
    load_demonstrations,
)
from ditch_drake.learning.data import ArraySet
from ditch_drake.learning.mirror import mirror_left_right
from ditch_drake.learning.stream import LazyImageStack

# The store's fields of `ArraySet`'s in-memory arrays.
_SCALAR_FIELDS = {"imu": "imu_stack", "distance": "distance_stack", "bearing": "bearing_stack", "label": "label"}


@dataclass(frozen=True)
class DatasetEpisode:
    """One episode of a dataset folder: stored (read when needed) or loaded from a `.npz`.

    Attributes:
        metadata: the demonstration's metadata as recorded (environment, task, expert style, ...).
        steps: its control steps.
        store, episode: where it is stored, for a store's episode.
        demonstration: the loaded arrays, for a `.npz` folder's.
    """

    metadata: dict
    steps: int
    store: DatasetStore | None = None
    episode: Episode | None = None
    demonstration: Demonstration | None = None

    @property
    def stored(self) -> bool:
        return self.demonstration is None

    def read(self, fields: list[str]) -> dict[str, np.ndarray]:
        """The episode's arrays of `fields` (memory-mapped for a store's; check `DatasetStore.read`)."""
        if self.demonstration is not None:
            return {name: self.demonstration.arrays[name] for name in fields}
        return self.store.read(self.episode, fields)

    def load(self) -> Demonstration:
        """The whole demonstration in memory."""
        return self.demonstration if self.demonstration is not None else self.store.load(self.episode)


def dataset_episodes(directory: str | os.PathLike, max_demos: int | None = None) -> list[DatasetEpisode]:
    """The complete episodes of a dataset folder (a store, or a folder of `.npz` files, which
    are loaded), the first `max_demos` of them (None: all), in index order.

    Raises:
        ConfigError: `max_demos` < 1.
        DatasetError: no such folder, no episodes, or a bad one.
    """
    if not is_store(directory):
        return [DatasetEpisode(demo.metadata, len(demo), demonstration=demo)
                for demo in load_demonstrations(directory, max_demos)]
    store = DatasetStore.open(directory)
    return [DatasetEpisode(demonstration_metadata(episode.metadata), episode.steps, store, episode)
            for episode in first_episodes(store, max_demos)]


def named_dataset_episodes(directories, max_demos: int | None = None) -> tuple[list[DatasetEpisode], list[str]]:
    """The first `max_demos` episodes of each dataset folder (`dataset_episodes`), in order, and
    their names, `<directory>[<index>]`: how an ensemble's bootstrap names the demonstrations
    it resamples."""
    episodes, names = [], []
    for directory in directories:
        found = dataset_episodes(directory, max_demos)
        episodes += found
        names += [f"{directory}[{index}]" for index in range(len(found))]
    return episodes, names


def _reflect_masks(reflect, counts: np.ndarray) -> list[np.ndarray]:
    """Each entry's reflect flags over its kept steps."""
    reflect = [False] * len(counts) if reflect is None else list(reflect)
    if len(reflect) != len(counts):
        raise DatasetError(f"reflect has {len(reflect)} entries; expected one per episode ({len(counts)})")
    masks = []
    for index, (flags, count) in enumerate(zip(reflect, counts, strict=True)):
        mask = np.broadcast_to(np.asarray(flags, dtype=np.bool_), (count,)) if np.ndim(flags) == 0 else (
            np.asarray(flags, dtype=np.bool_))
        if mask.shape != (count,):
            raise DatasetError(f"reflect[{index}] has shape {mask.shape}; expected ({count},), a flag per kept step")
        masks.append(mask)
    return masks


def training_set(episodes: list[DatasetEpisode], strides: list[int] | None = None, reflect: list | None = None,
                 first_demo_id: int = 0, steps: list | None = None) -> ArraySet:
    """The samples of `episodes` as one training `ArraySet`: `to_array_set`'s, with reflections.

    With every episode in a store, its images stay on disk (a `LazyImageStack`); otherwise the
    demonstrations are loaded and stacked in memory, as `to_array_set` does.

    Args:
        episodes: in order; entry i gets demo_id `first_demo_id + i`. An episode may appear
            more than once (say, once as recorded and once reflected).
        strides: every `strides[i]`-th step of entry i (None: every step); a kept step's stack
            holds the frames of the steps just before it, as the `FrameStacker` gives them.
        reflect: per entry, False, True (every kept step) or a bool array over its kept steps:
            the samples to reflect left to right (`ditch_drake.learning.mirror`). None: none.
        steps: per entry, None (its steps by `strides`) or the indices of the steps to keep, in
            order, for a stored episode (`ditch_drake.demos.interventions.kept_steps`). None:
            every entry by its stride.

    Raises:
        DatasetError: no episodes, strides or reflect flags that do not match the episodes,
            or an episode whose arrays disagree with its step count (naming the file).
    """
    if not episodes:
        raise DatasetError("no demonstrations to train on")
    strides = [1] * len(episodes) if strides is None else list(strides)
    if len(strides) != len(episodes) or min(strides) < 1:
        raise DatasetError(f"strides={strides}: expected one stride >= 1 per demonstration ({len(episodes)})")
    steps = [None] * len(episodes) if steps is None else list(steps)
    if len(steps) != len(episodes) or any(chosen is not None and not episode.stored
                                          for episode, chosen in zip(episodes, steps, strict=True)):
        raise DatasetError(f"steps has {len(steps)} entries; expected one per demonstration ({len(episodes)}), "
                           "and step indices only for a dataset folder's episodes")
    kept = [np.arange(0, episode.steps, stride) if chosen is None else np.asarray(chosen, dtype=np.int64)
            for episode, stride, chosen in zip(episodes, strides, steps, strict=True)]
    counts = np.array([len(steps) for steps in kept])
    masks = _reflect_masks(reflect, counts)
    flags = np.concatenate(masks)
    if not all(episode.stored for episode in episodes):
        arrays = to_array_set([episode.load() for episode in episodes], first_demo_id, strides)
        mirror_left_right({name: getattr(arrays, name) for name in ("image", "imu", "bearing", "label")}, flags)
        return arrays
    frames, source_of = [], {}  # An episode that appears twice is read from one file.
    values = {name: [] for name in _SCALAR_FIELDS}
    for episode, steps in zip(episodes, kept, strict=True):
        path = episode.episode.field_path("image")
        episode.read(["image"])  # Checks its shape and length against the episode's (a header read).
        source_of.setdefault(path, len(frames))
        if source_of[path] == len(frames):
            frames.append(path)
        arrays = episode.read(list(_SCALAR_FIELDS.values()))
        for name, field in _SCALAR_FIELDS.items():
            values[name].append(np.array(arrays[field][steps]))
    scalars = {name: np.concatenate(parts) for name, parts in values.items()}
    mirror_left_right(scalars, flags)
    image = LazyImageStack(frames, episode=np.repeat([source_of[e.episode.field_path("image")] for e in episodes],
                                                      counts),
                           step=np.concatenate(kept), reflect=flags)
    return ArraySet(image=image, **scalars, demo_id=np.repeat(first_demo_id + np.arange(len(episodes)), counts))


def load_training_set(directories: list[str | os.PathLike], max_demos: int | None = None) -> ArraySet:
    """The first `max_demos` demonstrations (None: all) of each folder, in order, as one training
    set (`training_set`: a store's images stay on disk)."""
    return training_set([episode for directory in directories for episode in dataset_episodes(directory, max_demos)])
