"""The intervention flags of a training set's samples: which steps a supervisor took over.

A shared rollout's steps where the fallback drove (`collect --shared`), or a person at
`teleop --shared`, are stored with `intervention` true (`ditch_drake.demos.store`); training
weighs their loss by `TrainConfig.intervention_weight` (Sirius), or learns only them of a
shared episode with `TrainConfig.shared_steps` "interventions" (HG-DAgger, ThriftyDAgger).
Episodes of the older `.npz` format have no such field: none of their steps was taken over.
"""

import numpy as np

from ditch_drake.demos.training_set import DatasetEpisode


def _flags(episode: DatasetEpisode) -> np.ndarray:
    if episode.stored:
        return np.asarray(episode.read(["intervention"])["intervention"], dtype=np.bool_)
    return np.asarray(episode.demonstration.arrays.get("intervention", np.zeros(episode.steps)), dtype=np.bool_)


def episode_interventions(episodes: list[DatasetEpisode], steps: list | None = None) -> np.ndarray:
    """(N,) bool over the samples `training_set(episodes, steps=steps)` makes (the kept steps of
    each entry, in order; None: every step): each step's stored `intervention` flag; all false
    for a `.npz` episode."""
    steps = [None] * len(episodes) if steps is None else steps
    parts = [_flags(episode) if chosen is None else _flags(episode)[chosen]
             for episode, chosen in zip(episodes, steps, strict=True)]
    return np.concatenate(parts) if parts else np.zeros(0, np.bool_)


def is_shared(episode: DatasetEpisode) -> bool:
    """Whether a gated policy drove the episode (`collect --shared`, `teleop --shared`)."""
    return "shared_gate" in episode.metadata


def kept_steps(episodes: list[DatasetEpisode], shared_steps: str = "all") -> list | None:
    """The steps `training_set` keeps of each episode for `TrainConfig.shared_steps`: None for
    "all" (every step of every episode); for "interventions", the indices of the steps the
    supervisor drove in each shared episode (`is_shared`) and None (every step) in the others."""
    if shared_steps == "all":
        return None
    return [np.flatnonzero(_flags(episode)) if is_shared(episode) else None for episode in episodes]
