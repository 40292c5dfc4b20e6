"""Class balancing of the training split: one registry of methods, SMOTE (paper 3.5) among them.

Label 8 (straight ahead) dominates driving data. `TrainConfig.balancing` names how training
makes up for it; `BALANCING` maps each name to a function that, given the training split,
returns a `Balancing`: the rows training draws from (a row may repeat), the synthetic samples
after them, and how the epochs draw and the loss weighs them.

| method | what it does | memory, time |
| --- | --- | --- |
| `smote` | the paper's: new samples interpolated within each minority class, up to `SmoteConfig`'s targets | the new samples' images (spilled to a file when the set streams from disk); minutes |
| `oversample` | rows of the minority classes drawn again at random, to the same targets | an index a sample; milliseconds |
| `weighted_sampler` | each epoch draws as many samples as the split holds, with replacement, a sample's chance inverse to its class's count (torch's `WeightedRandomSampler` recipe), seeded by (seed, epoch) | a weight a sample |
| `class_weights` | cross-entropy weighted n / (classes x count) per class (scikit-learn's "balanced") | 17 weights |
| `ordinal_soft_labels` | cross-entropy against a discretized Gaussian of width `TrainConfig.soft_label_sigma` over the 17 ordered turn rates, centred on the label: a near miss costs less than a far one | a 17 x 17 table |
| `none` | the split as recorded | nothing |

Only the training split is ever balanced; validation stays as recorded and is scored with the
plain cross-entropy whatever the method, so the methods' validation losses compare.

SMOTE here: each sample is a 4 x 128 x 128 image plus 16 scalars (65,552 values), so full
balance is out of reach: raising 16 classes to a majority of ~8 k samples would add ~130 k
samples (8 GiB as uint8, and as many training steps per epoch). The strategy, all in
`SmoteConfig`:

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
  or float16) right away, so the synthetic set costs what the real one does per sample,
  and, given a folder (`smote_samples`' `folder`; `train` passes one when the set's images
  stream from disk), go to a file there instead of memory, so SMOTE's memory is bounded by
  `SmoteConfig` alone, whatever the data's size.
- A class with a single training sample has no neighbour to interpolate with
  (`k_neighbors`): it is oversampled by repeating that sample. A class with no training
  sample stays empty. `k_neighbors` shrinks to the class size - 1 for small classes.

Synthetic samples carry `demo_id = SYNTHETIC_DEMO_ID` (-1). The peak memory of the training
pipeline with SMOTE on a 16 k-sample set is `train_peak_rss_smote_mib` of `ditch-drake bench
--training` (`ditch_drake/perf/bench_training.py`); the in-memory path held 3.7 GiB there
(1.0 GiB of uint8 stacks; 12.8 k training samples got 12.8 k synthetic ones), about 2.5 min
on 2 shared cores. float16 images double the data's share.
"""

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import sklearn
from imblearn.over_sampling import SMOTE

from ditch_drake.learning.config import SmoteConfig, TrainConfig
from ditch_drake.learning.data import (
    SYNTHETIC_DEMO_ID,
    ArraySet,
    InputStats,
    float32_to_images,
    images_to_float32,
)
from ditch_drake.learning.stream import NpyRowWriter
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
    folder: str | os.PathLike | None = None,
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
        folder: write the new samples' images to `synthetic_images.npy` there, as they are
            made, and read them back from it when indexed (`NpyRows`), instead of holding
            them in memory; the same values either way.

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
        for name in _SCALARS
    }
    image_shape, image_dtype = (total, *arrays.image.shape[1:]), arrays.image.dtype
    if folder is None:
        out["image"] = np.empty(image_shape, dtype=image_dtype)
    else:
        out["image"] = NpyRowWriter(Path(folder) / "synthetic_images.npy", image_shape, image_dtype)
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
    if folder is not None:
        out["image"] = out["image"].close()
    return ArraySet(**out)


def balance(train: ArraySet, config: SmoteConfig, seed: int) -> ArraySet:
    """The training split followed by its SMOTE samples (a convenience; it copies `train`).

    `train` must be the training split only (`split_by_demo`), never validation data.
    """
    return ArraySet.concatenate([train, smote_samples(train, config, seed)])


@dataclass
class Balancing:
    """A balanced training split: what `train` draws its batches from and how it weighs them.

    Attributes:
        method: its name in `BALANCING`.
        rows: the training rows of the set, in position order; a row repeated for each extra
            draw of it ("oversample").
        synthetic: new samples after the rows ("smote"), or None.
        sample_weights: (positions,) relative chance of each position in an epoch's draw with
            replacement ("weighted_sampler"), or None: each epoch is a permutation of them all.
        class_weights: (17,) float32 cross-entropy weight of each label ("class_weights"), or None.
        soft_targets: (17, 17) float32, row l the training target of label l
            ("ordinal_soft_labels"), or None: the label itself.
        seconds: the time it took to make.
    """

    method: str
    rows: np.ndarray
    synthetic: ArraySet | None = None
    sample_weights: np.ndarray | None = None
    class_weights: np.ndarray | None = None
    soft_targets: np.ndarray | None = None
    seconds: float = 0.0
    extra_label_counts: np.ndarray = field(default_factory=lambda: np.zeros(NUM_LABELS, np.int64))

    def __len__(self) -> int:
        """The positions an epoch draws from: the rows and the synthetic samples."""
        return len(self.rows) + (0 if self.synthetic is None else len(self.synthetic))

    def epoch_order(self, seed: int, epoch: int) -> np.ndarray:
        """The positions of epoch `epoch`, in order: a permutation, or the weighted draw."""
        rng = np.random.default_rng([seed, 2, epoch])
        if self.sample_weights is None:
            return rng.permutation(len(self))
        return rng.choice(len(self), size=len(self), replace=True, p=self.sample_weights / self.sample_weights.sum())


def _label_counts(arrays: ArraySet, rows: np.ndarray) -> np.ndarray:
    return np.bincount(arrays.label[rows], minlength=NUM_LABELS).astype(np.int64)


def _smote(arrays: ArraySet, rows: np.ndarray, stats: InputStats, config: TrainConfig, folder) -> Balancing:
    synthetic = smote_samples(arrays, config.smote, config.seed, rows, stats, folder)
    return Balancing("smote", rows, synthetic=synthetic, extra_label_counts=synthetic.label_counts())


def oversampled_rows(labels_of_rows: np.ndarray, rows: np.ndarray, config: SmoteConfig, seed: int) -> np.ndarray:
    """Extra rows of the minority classes, drawn with replacement from each class's rows, as many
    per class as SMOTE would make (`synthetic_counts`), grouped by label."""
    todo = synthetic_counts(np.bincount(labels_of_rows, minlength=NUM_LABELS), len(rows), config)
    rng = np.random.default_rng([seed, 4])
    extra = [rng.choice(rows[labels_of_rows == label], int(todo[label]), replace=True) for label in np.flatnonzero(todo)]
    return np.concatenate(extra).astype(np.int64) if extra else np.zeros(0, np.int64)


def _oversample(arrays: ArraySet, rows: np.ndarray, stats: InputStats, config: TrainConfig, folder) -> Balancing:
    extra = oversampled_rows(arrays.label[rows], rows, config.smote, config.seed)
    return Balancing("oversample", np.concatenate([rows, extra]), extra_label_counts=_label_counts(arrays, extra))


def _weighted_sampler(arrays: ArraySet, rows: np.ndarray, stats: InputStats, config: TrainConfig,
                      folder) -> Balancing:
    counts = _label_counts(arrays, rows)
    weights = 1.0 / counts[arrays.label[rows]]
    return Balancing("weighted_sampler", rows, sample_weights=weights)


def balanced_class_weights(label_counts: np.ndarray) -> np.ndarray:
    """(17,) float32 n / (present classes x count) of each present class, 0 for an absent one:
    every class then weighs as much in the loss as an average one."""
    counts = np.asarray(label_counts, dtype=np.float64)
    present = counts > 0
    weights = np.zeros(len(counts), np.float64)
    weights[present] = counts.sum() / (present.sum() * counts[present])
    return weights.astype(np.float32)


def _class_weights(arrays: ArraySet, rows: np.ndarray, stats: InputStats, config: TrainConfig, folder) -> Balancing:
    return Balancing("class_weights", rows, class_weights=balanced_class_weights(_label_counts(arrays, rows)))


def ordinal_soft_targets(sigma: float, num_labels: int = NUM_LABELS) -> np.ndarray:
    """(num_labels, num_labels) float32: row l a discretized Gaussian of std `sigma` (labels)
    over the ordered labels, centred on l, summing to 1 (cut at the ends of the table)."""
    labels = np.arange(num_labels)
    targets = np.exp(-0.5 * ((labels[None, :] - labels[:, None]) / sigma) ** 2)
    return (targets / targets.sum(axis=1, keepdims=True)).astype(np.float32)


def _ordinal_soft_labels(arrays: ArraySet, rows: np.ndarray, stats: InputStats, config: TrainConfig,
                         folder) -> Balancing:
    return Balancing("ordinal_soft_labels", rows, soft_targets=ordinal_soft_targets(config.soft_label_sigma))


def _none(arrays: ArraySet, rows: np.ndarray, stats: InputStats, config: TrainConfig, folder) -> Balancing:
    return Balancing("none", rows)


# The methods of `TrainConfig.balancing`, by the names of `config.BALANCING_METHODS`.
BALANCING: dict[str, Callable[..., Balancing]] = {
    "smote": _smote,
    "oversample": _oversample,
    "weighted_sampler": _weighted_sampler,
    "class_weights": _class_weights,
    "ordinal_soft_labels": _ordinal_soft_labels,
    "none": _none,
}


def balance_training_split(arrays: ArraySet, rows: np.ndarray, stats: InputStats, config: TrainConfig,
                           folder: str | os.PathLike | None = None) -> Balancing:
    """The training rows `rows` of `arrays` balanced by `config.balancing`, timed.

    Args:
        arrays: the set (images in memory or streamed).
        rows: its training split (never validation rows).
        stats: the split's scalar standardization (SMOTE's neighbour search).
        config: the method and its settings (`smote`, `soft_label_sigma`, `seed`).
        folder: where SMOTE writes its new images (None: memory).
    """
    start = time.perf_counter()
    balancing = BALANCING[config.balancing](arrays, np.asarray(rows, dtype=np.int64), stats, config, folder)
    balancing.seconds = time.perf_counter() - start
    return balancing
