"""The training set, its split by demonstration and the input standardization.

The on-disk demonstration format and its loader live elsewhere; they hand `train` an
`ArraySet`: one row per control step, the four stacked inputs exactly as the FrameStacker
outputs them (`ditch_drake.spec.observation_layout`), the recorded action label and the
demonstration the step came from.

Images are kept compact: uint8 (0..255 standing for [0, 1]) or float16 ([0, 1]). 16 k
samples of 4 x 128 x 128 take 1 GiB as uint8 (2 GiB as float16, 4 GiB as float32), so the
training code converts them to float32 one batch at a time (`images_to_tensor`). Or they stay
on disk: the image may be a `ditch_drake.learning.stream.LazyImageStack`, which builds the
stacks of the rows it is indexed by from each episode's frames (what
`ditch_drake.demos.training_set` makes of a dataset folder); the scalars are always in memory.
"""

from dataclasses import dataclass

import numpy as np
import torch

from ditch_drake.spec.actions import NUM_LABELS
from ditch_drake.spec.observation_layout import (
    BEARING_STACK_SIZE,
    DISTANCE_STACK_SIZE,
    IMAGE_STACK_SHAPE,
    IMU_STACK_SIZE,
)

SYNTHETIC_DEMO_ID = -1
"""`ArraySet.demo_id` of samples made by SMOTE rather than recorded."""

IMAGE_DTYPES = (np.dtype(np.uint8), np.dtype(np.float16))
_SCALAR_FIELDS = {"imu": IMU_STACK_SIZE, "distance": DISTANCE_STACK_SIZE, "bearing": BEARING_STACK_SIZE}
_CHECK_CHUNK = 1024  # samples per chunk when scanning float16 images (bounded temporaries)


@dataclass
class ArraySet:
    """N training samples as parallel numpy arrays (validated on construction).

    Attributes:
        image: (N, 4, 128, 128) uint8 (0..255 for [0, 1]) or float16 in [0, 1]; channel 0
            newest, rows and columns as `FrameStacker.image_stack` reshaped to
            `IMAGE_STACK_SHAPE`. A numpy array, or an object of that `shape` and `dtype` whose
            indexing by an integer array returns those rows as one (`stream.LazyImageStack`,
            `stream.NpyRows`: images read from disk when a batch needs them).
        imu: (N, 8) float32, [roll_t, pitch_t, roll_t-1, ...] (rad).
        distance: (N, 4) float32, distance to the goal, newest first (m).
        bearing: (N, 4) float32, bearing to the goal, newest first (rad).
        label: (N,) int64 action labels in 0..16 (`ditch_drake.spec.actions`).
        demo_id: (N,) int64, the demonstration each sample came from (>= 0);
            `SYNTHETIC_DEMO_ID` (-1) for samples made by SMOTE.

    Scalar arrays and labels of another numeric dtype are converted (cheap); images of
    another dtype are refused rather than silently copied (see `images_to_uint8`).

    Raises:
        ValueError: naming the field, its shape or dtype and what was expected, for a
            wrong shape or dtype, a label outside 0..16, a demo id below -1, a value that
            is not finite, or a float16 image value outside [0, 1].
    """

    image: np.ndarray
    imu: np.ndarray
    distance: np.ndarray
    bearing: np.ndarray
    label: np.ndarray
    demo_id: np.ndarray

    def __post_init__(self):
        self.label = _as_integer_vector("label", self.label)
        n = self.label.shape[0]
        self.demo_id = _as_integer_vector("demo_id", self.demo_id)
        if self.demo_id.shape != (n,):
            raise ValueError(f"ArraySet.demo_id has shape {self.demo_id.shape}; expected ({n},) like label")
        for name, size in _SCALAR_FIELDS.items():
            value = np.asarray(getattr(self, name))
            if value.shape != (n, size):
                raise ValueError(f"ArraySet.{name} has shape {value.shape}; expected ({n}, {size}) (N from label)")
            if not np.issubdtype(value.dtype, np.number):
                raise ValueError(f"ArraySet.{name} has dtype {value.dtype}; expected float32")
            value = value.astype(np.float32, copy=False)
            if not np.all(np.isfinite(value)):
                rows = np.flatnonzero(~np.all(np.isfinite(value), axis=1))
                raise ValueError(
                    f"ArraySet.{name} (shape {value.shape}) has non-finite values in rows {rows[:10].tolist()}"
                )
            setattr(self, name, value)
        if self.image.shape != (n, *IMAGE_STACK_SHAPE):
            raise ValueError(
                f"ArraySet.image has shape {self.image.shape}; expected ({n}, {', '.join(map(str, IMAGE_STACK_SHAPE))})"
            )
        if self.image.dtype not in IMAGE_DTYPES:
            raise ValueError(
                f"ArraySet.image (shape {self.image.shape}) has dtype {self.image.dtype}; expected uint8 (0..255 "
                "for [0, 1]) or float16 in [0, 1]; convert float images with images_to_uint8"
            )
        if self.image.dtype == np.float16:
            for start in range(0, n, _CHECK_CHUNK):
                chunk = self.image[start : start + _CHECK_CHUNK]
                bad = ~((chunk >= 0) & (chunk <= 1))  # NaN fails both comparisons.
                if bad.any():
                    row = start + int(np.flatnonzero(bad.reshape(len(chunk), -1).any(axis=1))[0])
                    raise ValueError(
                        f"ArraySet.image (shape {self.image.shape}, float16) has a value outside [0, 1] or not "
                        f"finite in sample {row}"
                    )
        if n and (self.label.min() < 0 or self.label.max() >= NUM_LABELS):
            bad = np.unique(self.label[(self.label < 0) | (self.label >= NUM_LABELS)])
            raise ValueError(
                f"ArraySet.label (shape {self.label.shape}) has labels {bad[:10].tolist()} outside 0..{NUM_LABELS - 1}"
            )
        if n and self.demo_id.min() < SYNTHETIC_DEMO_ID:
            raise ValueError(f"ArraySet.demo_id (shape {self.demo_id.shape}) has ids below {SYNTHETIC_DEMO_ID}")

    def __len__(self) -> int:
        return int(self.label.shape[0])

    def take(self, indices: np.ndarray) -> "ArraySet":
        """The samples at `indices` (copies)."""
        indices = np.asarray(indices, dtype=np.int64)
        return ArraySet(
            image=self.image[indices],
            imu=self.imu[indices],
            distance=self.distance[indices],
            bearing=self.bearing[indices],
            label=self.label[indices],
            demo_id=self.demo_id[indices],
        )

    def demos(self) -> np.ndarray:
        """Sorted ids of the recorded demonstrations present (synthetic samples left out)."""
        ids = np.unique(self.demo_id)
        return ids[ids != SYNTHETIC_DEMO_ID]

    def label_counts(self) -> np.ndarray:
        """(17,) int64: samples per label."""
        return np.bincount(self.label, minlength=NUM_LABELS).astype(np.int64)

    @staticmethod
    def concatenate(parts: "list[ArraySet]") -> "ArraySet":
        """One set of the samples of `parts`, in order (the images must share a dtype).

        Raises:
            ValueError: no parts, or images of different dtypes.
        """
        if not parts:
            raise ValueError("ArraySet.concatenate needs at least one part")
        dtypes = {p.image.dtype for p in parts}
        if len(dtypes) > 1:
            raise ValueError(f"ArraySet.concatenate: image dtypes differ ({sorted(map(str, dtypes))})")
        return ArraySet(
            **{name: np.concatenate([getattr(p, name) for p in parts]) for name in ArraySet.__dataclass_fields__}
        )


def _as_integer_vector(name: str, value) -> np.ndarray:
    value = np.asarray(value)
    if value.ndim != 1:
        raise ValueError(f"ArraySet.{name} has shape {value.shape}; expected (N,)")
    is_integral = np.issubdtype(value.dtype, np.integer) or (
        np.issubdtype(value.dtype, np.floating) and np.all(value == np.round(value))
    )
    if value.size and not is_integral:
        raise ValueError(f"ArraySet.{name} (shape {value.shape}) has dtype {value.dtype}; expected integers")
    return value.astype(np.int64, copy=False)


def images_to_uint8(images: np.ndarray) -> np.ndarray:
    """Float images in [0, 1] -> uint8 0..255 (rounded, clipped), for `ArraySet.image`."""
    return np.clip(np.rint(np.asarray(images, dtype=np.float32) * 255.0), 0, 255).astype(np.uint8)


def images_to_tensor(images: np.ndarray) -> torch.Tensor:
    """A batch of `ArraySet.image` rows as a float32 tensor in [0, 1] (the network's input)."""
    tensor = torch.from_numpy(np.ascontiguousarray(images))
    if tensor.dtype == torch.uint8:
        return tensor.to(torch.float32).div_(255.0)
    return tensor.to(torch.float32)


def images_to_float32(images: np.ndarray) -> np.ndarray:
    """`ArraySet.image` rows as float32 in [0, 1] (numpy)."""
    if images.dtype == np.uint8:
        return images.astype(np.float32) * np.float32(1.0 / 255.0)
    return images.astype(np.float32)


def float32_to_images(values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """float32 images in [0, 1] -> `ArraySet.image` rows of `dtype` (uint8 or float16), clipped."""
    if np.dtype(dtype) == np.uint8:
        return images_to_uint8(values)
    return np.clip(values, 0.0, 1.0).astype(np.float16)


@dataclass
class InputStats:
    """Per-component mean and std of the scalar inputs, from the training split only.

    The network standardizes its scalar inputs with these (`FourInputClassifier.set_input_stats`);
    the checkpoint stores them (`to_dict`) so inference applies the same numbers.
    """

    imu_mean: np.ndarray
    imu_std: np.ndarray
    distance_mean: np.ndarray
    distance_std: np.ndarray
    bearing_mean: np.ndarray
    bearing_std: np.ndarray

    MIN_STD = 1e-6
    """A component whose std is below this (constant in training) gets std 1."""

    @classmethod
    def fit(cls, arrays: ArraySet, indices: np.ndarray | None = None) -> "InputStats":
        """The stats of `arrays` (or of its rows `indices`).

        Raises:
            ValueError: no samples.
        """
        values = {}
        for name in _SCALAR_FIELDS:
            data = getattr(arrays, name)
            data = data if indices is None else data[indices]
            if len(data) == 0:
                raise ValueError("InputStats.fit needs at least one sample")
            std = data.std(axis=0, dtype=np.float64)
            values[f"{name}_mean"] = data.mean(axis=0, dtype=np.float64).astype(np.float32)
            values[f"{name}_std"] = np.where(std < cls.MIN_STD, 1.0, std).astype(np.float32)
        return cls(**values)

    @classmethod
    def identity(cls) -> "InputStats":
        """Mean 0, std 1 (no standardization)."""
        values = {}
        for name, size in _SCALAR_FIELDS.items():
            values[f"{name}_mean"] = np.zeros(size, np.float32)
            values[f"{name}_std"] = np.ones(size, np.float32)
        return cls(**values)

    def standardize(self, name: str, values: np.ndarray) -> np.ndarray:
        """(values - mean) / std of input `name` ("imu", "distance" or "bearing"), float32."""
        return ((values - getattr(self, f"{name}_mean")) / getattr(self, f"{name}_std")).astype(np.float32)

    def unstandardize(self, name: str, values: np.ndarray) -> np.ndarray:
        """The inverse of `standardize`."""
        return (values * getattr(self, f"{name}_std") + getattr(self, f"{name}_mean")).astype(np.float32)

    def to_dict(self) -> dict[str, list[float]]:
        """Plain lists, for a checkpoint and `FourInputClassifier.set_input_stats`."""
        return {key: [float(x) for x in value] for key, value in vars(self).items()}

    @classmethod
    def from_dict(cls, values: dict) -> "InputStats":
        """The stats of `to_dict`'s output.

        Raises:
            ValueError: a missing key or a wrong length.
        """
        arrays = {}
        for name, size in _SCALAR_FIELDS.items():
            for kind in ("mean", "std"):
                key = f"{name}_{kind}"
                if key not in values:
                    raise ValueError(f"input stats lack {key!r}")
                arrays[key] = np.asarray(values[key], dtype=np.float32)
                if arrays[key].shape != (size,):
                    raise ValueError(f"input stats {key!r} has shape {arrays[key].shape}, expected ({size},)")
        return cls(**arrays)


def first_demos_indices(arrays: ArraySet, max_demos: int | None) -> np.ndarray:
    """Rows of the `max_demos` demonstrations with the smallest ids (all rows for None).

    The 10/20/40-demonstration study trains on the first N demonstrations, so a smaller
    set is always a subset of a larger one.

    Raises:
        ValueError: `max_demos` < 1, or more demonstrations asked for than there are.
    """
    if max_demos is None:
        return np.arange(len(arrays))
    demos = arrays.demos()
    if max_demos < 1 or max_demos > len(demos):
        raise ValueError(f"max_demos={max_demos} must be in 1..{len(demos)} (the demonstrations in the set)")
    return np.flatnonzero(np.isin(arrays.demo_id, demos[:max_demos]))


def split_indices_by_demo(
    demo_id: np.ndarray, val_fraction: float, seed: int, indices: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Train and validation rows, holding out whole demonstrations.

    Args:
        demo_id: (N,) the demonstration of each row.
        val_fraction: share of the demonstrations held out: round(val_fraction * demos),
            at least 1 and at most demos - 1 when positive; 0 holds out none.
        seed: chooses which demonstrations (numpy `default_rng`).
        indices: split only these rows (default all).

    Returns:
        (train_rows, val_rows), each sorted.

    Raises:
        ValueError: `val_fraction` outside [0, 1), fewer than two demonstrations to split,
            or synthetic (SMOTE) rows, which must be made after the split.
    """
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"val_fraction={val_fraction} must be in [0, 1)")
    rows = np.arange(len(demo_id)) if indices is None else np.sort(np.asarray(indices, dtype=np.int64))
    ids = np.asarray(demo_id)[rows]
    if np.any(ids == SYNTHETIC_DEMO_ID):
        raise ValueError("split_by_demo got synthetic (SMOTE) samples: split first, then oversample the training split")
    demos = np.unique(ids)
    if val_fraction == 0.0:
        return rows, rows[:0]
    if len(demos) < 2:
        raise ValueError(f"cannot hold out whole demonstrations for validation: only {len(demos)} demonstration(s)")
    n_val = int(np.clip(round(val_fraction * len(demos)), 1, len(demos) - 1))
    val_demos = np.random.default_rng(seed).choice(demos, size=n_val, replace=False)
    is_val = np.isin(ids, val_demos)
    return rows[~is_val], rows[is_val]


def split_by_demo(arrays: ArraySet, val_fraction: float, seed: int) -> tuple[ArraySet, ArraySet]:
    """Train and validation sets with no demonstration in both (see `split_indices_by_demo`)."""
    train_rows, val_rows = split_indices_by_demo(arrays.demo_id, val_fraction, seed)
    return arrays.take(train_rows), arrays.take(val_rows)
