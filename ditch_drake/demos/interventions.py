"""The intervention flags of a training set's samples: which steps a supervisor took over.

A shared rollout's steps where the fallback drove (`collect --shared`), or a person at
`teleop --shared`, are stored with `intervention` true (`ditch_drake.demos.store`); training
weighs their loss by `TrainConfig.intervention_weight` (Sirius). Episodes of the older `.npz`
format have no such field: none of their steps was taken over.
"""

import numpy as np

from ditch_drake.demos.training_set import DatasetEpisode


def episode_interventions(episodes: list[DatasetEpisode]) -> np.ndarray:
    """(N,) bool over the samples `training_set(episodes)` makes (every step of each entry, in
    order): each step's stored `intervention` flag; all false for a `.npz` episode."""
    parts = []
    for episode in episodes:
        if episode.stored:
            parts.append(np.asarray(episode.read(["intervention"])["intervention"], dtype=np.bool_))
        else:
            parts.append(np.asarray(episode.demonstration.arrays.get("intervention", np.zeros(episode.steps)),
                                    dtype=np.bool_))
    return np.concatenate(parts) if parts else np.zeros(0, np.bool_)
