"""Class balancing of the training split with SMOTE (paper 3.5), within a memory budget.

Label 8 (straight ahead) dominates driving data. The paper adds SMOTE samples of the
minority classes to the training set. Here each sample is a 4 x 128 x 128 image plus 16
scalars (65,552 values), so full balance is out of reach: raising 16 classes to a majority
of ~8 k samples would add ~130 k samples (8 GiB as uint8, and as many training steps per
epoch). The strategy, all in `SmoteConfig`:

- Targets short of full balance: every present minority class is raised to
  `target_fraction` (default 0.5) of the majority class's count, and the synthetic
  samples are capped at `max_synthetic_fraction` (default 1.0) times the real training
  samples, scaling every class's deficit down by the same factor when the cap binds.
- imbalanced-learn's `SMOTE` runs one class at a time (a `sampling_strategy` dict naming
  that class, plus one sample of another class because imbalanced-learn refuses a single
  class), in chunks of at most `chunk_size` new samples, on float32 features: the image in
  [0, 1] flattened, followed by the scalar inputs standardized with the training split's
  `InputStats`. imbalanced-learn copies its input about four times and builds float64
  temporaries of the new samples, so both the class's samples (`max_base_samples`, a
  random subset when a class has more) and the chunk are bounded; neighbours are searched
  within that subset. New samples go back to the image dtype of the set (uint8 rounded,
  or float16) right away, so the synthetic set costs what the real one does per sample.
- A class with a single training sample has no neighbour to interpolate with
  (`k_neighbors`): it is oversampled by repeating that sample. A class with no training
  sample stays empty. `k_neighbors` shrinks to the class size - 1 for small classes.
- Only the training split is ever passed here; validation stays as recorded.

Synthetic samples carry `demo_id = SYNTHETIC_DEMO_ID` (-1). The peak memory of the whole
training pipeline on a 16 k-sample set (uint8 images, 1.0 GiB; 12.8 k training samples get
12.8 k synthetic ones) is measured by `ditch_drake/perf/bench_training.py::measure_training_memory_mib`:
3.7 GiB peak RSS, SMOTE included (about 2.5 min on 2 shared cores). float16 images double
the data's share.
"""


import numpy as np
import sklearn
from imblearn.over_sampling import SMOTE

from ditch_drake.learning.config import SmoteConfig
from ditch_drake.learning.data import (
    SYNTHETIC_DEMO_ID,
    ArraySet,
    InputStats,
    float32_to_images,
    images_to_float32,
)
from ditch_drake.spec.actions import NUM_LABELS

_SCALARS = ("imu", "distance", "bearing")
# scikit-learn's Cython neighbour search costs ~0.5 s per call on 65 k float32 features
# however few the samples, and beats its NumPy path only for larger classes (measured:
# 6 samples 0.51 s vs 0.01 s; 2,000 samples 11 s vs 23 s).
_CYTHON_NEIGHBOURS_FROM = 256


def synthetic_counts(label_counts: np.ndarray, real_samples: int, config: SmoteConfig) -> np.ndarray:
    """How many synthetic samples each label gets.

    Args:
        label_counts: (17,) training samples per label.
        real_samples: the training split's size (the budget's base).
        config: the targets and the budget.

    Returns:
        (17,) int64, zero for the majority class, for absent classes and when SMOTE is off.
    """
    counts = np.asarray(label_counts, dtype=np.int64)
    if config.target_fraction == 0.0 or counts.max(initial=0) == 0:
        return np.zeros_like(counts)
    target = int(np.ceil(config.target_fraction * counts.max()))
    deficit = np.where(counts > 0, np.maximum(target - counts, 0), 0)
    budget = int(config.max_synthetic_fraction * real_samples)
    if deficit.sum() > budget:
        deficit = np.floor(deficit * (budget / deficit.sum())).astype(np.int64)
    return deficit


def _features(arrays: ArraySet, rows: np.ndarray, stats: InputStats) -> np.ndarray:
    """float32 (len(rows), 65,552): image in [0, 1] flattened, then standardized scalars."""
    image = images_to_float32(arrays.image[rows]).reshape(len(rows), -1)
    parts = [image] + [stats.standardize(name, getattr(arrays, name)[rows]) for name in _SCALARS]
    return np.concatenate(parts, axis=1)


def _write_features(features: np.ndarray, out: dict[str, np.ndarray], start: int, stats: InputStats) -> None:
    """Writes float32 features back as samples into rows start.. of the output arrays."""
    n = len(features)
    image = out["image"]
    image_size = int(np.prod(image.shape[1:]))
    image[start : start + n] = float32_to_images(features[:, :image_size], image.dtype).reshape(n, *image.shape[1:])
    column = image_size
    for name in _SCALARS:
        size = out[name].shape[1]
        out[name][start : start + n] = stats.unstandardize(name, features[:, column : column + size])
        column += size


def smote_samples(
    arrays: ArraySet,
    config: SmoteConfig,
    seed: int,
    indices: np.ndarray | None = None,
    stats: InputStats | None = None,
) -> ArraySet:
    """The synthetic samples that balance a training split (not the split itself).

    Args:
        arrays: the set holding the training split.
        config: targets, budget and memory bounds.
        seed: makes the result reproducible.
        indices: the training split's rows of `arrays` (default: all rows). Never pass
            validation rows.
        stats: standardization of the scalars for the neighbour search; default: fitted
            on the training rows.

    Returns:
        The synthetic samples (possibly none), grouped by label, with the image dtype of
        `arrays` and `demo_id` -1.
    """
    rows = np.arange(len(arrays)) if indices is None else np.asarray(indices, dtype=np.int64)
    labels = arrays.label[rows]
    todo = synthetic_counts(np.bincount(labels, minlength=NUM_LABELS), len(rows), config)
    rng = np.random.default_rng(seed)
    stats = stats if stats is not None else InputStats.fit(arrays, rows)
    total = int(todo.sum())
    out = {
        name: np.empty((total, *getattr(arrays, name).shape[1:]), dtype=getattr(arrays, name).dtype)
        for name in ("image", *_SCALARS)
    }
    out["label"] = np.repeat(np.arange(NUM_LABELS), todo).astype(np.int64)
    out["demo_id"] = np.full(total, SYNTHETIC_DEMO_ID, np.int64)
    start = 0
    for label in np.flatnonzero(todo):
        label, needed = int(label), int(todo[label])
        class_rows = rows[labels == label]
        if len(class_rows) == 1:  # No neighbour to interpolate with: repeat the sample.
            for name in ("image", *_SCALARS):
                out[name][start : start + needed] = getattr(arrays, name)[class_rows[0]]
            start += needed
            continue
        if len(class_rows) > config.max_base_samples:
            class_rows = np.sort(rng.choice(class_rows, config.max_base_samples, replace=False))
        donor = rows[labels != label][:1]  # imbalanced-learn needs two classes; the donor is left out again.
        base = _features(arrays, np.concatenate([class_rows, donor]), stats)
        y = np.concatenate([np.full(len(class_rows), label), arrays.label[donor]])
        k = min(config.k_neighbors, len(class_rows) - 1)
        for chunk_start in range(0, needed, config.chunk_size):
            chunk = min(needed - chunk_start, config.chunk_size)
            smote = SMOTE(
                sampling_strategy={label: len(class_rows) + chunk},
                k_neighbors=k,
                random_state=int(rng.integers(2**31 - 1)),
            )
            with sklearn.config_context(enable_cython_pairwise_dist=len(class_rows) >= _CYTHON_NEIGHBOURS_FROM):
                resampled, _ = smote.fit_resample(base, y)
            _write_features(resampled[len(base) :], out, start, stats)
            del resampled
            start += chunk
        del base
    return ArraySet(**out)


def balance(train: ArraySet, config: SmoteConfig, seed: int) -> ArraySet:
    """The training split followed by its SMOTE samples (a convenience; it copies `train`).

    `train` must be the training split only (`split_by_demo`), never validation data.
    """
    return ArraySet.concatenate([train, smote_samples(train, config, seed)])
