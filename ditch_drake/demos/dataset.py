"""The demonstration file format: one compressed `.npz` per demonstration.

Arrays, T control steps each (`SCHEMA_VERSION` 1):

| key | shape, dtype | meaning |
| --- | --- | --- |
| `image` | (T, 128, 128) uint8 | newest surface-normal image, round(255 v) for v in [0, 1] |
| `imu_stack` | (T, 8) float32 | [roll, pitch] newest first (rad) |
| `distance_stack` | (T, 4) float32 | distance to goal, newest first (m) |
| `bearing_stack` | (T, 4) float32 | bearing to goal, newest first (rad) |
| `label` | (T,) int16 | executed action label, 0..16 |
| `time_s` | (T,) float64 | simulated time of the step |
| `pose` | (T, 6) float32 | chassis [x, y, z, roll, pitch, yaw] |
| `raw_command` | (T, 2) float32 | command before quantization [v, w] |
| `metadata` | 0-d str | JSON: schema version, environment, task, seed, outcome, control period, action table, expert style |

The metadata is a JSON object; the keys that code reads back are checked for their JSON
type when present (`_METADATA_TYPES`), so a file whose `task` is a string fails on loading
with a message, not later in a summary.

The image stack a policy sees at step t is `image[t], image[t-1], image[t-2],
image[t-3]` (zeros before the first step); `restack_images` rebuilds it. Files are
written atomically (temporary file, flushed to disk, then rename) with the mode a plain
`open()` gives (0644 under the usual umask 022).
"""

import json
import zipfile
import zlib
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ditch_drake import __version__
from ditch_drake.common.errors import ConfigError, DatasetError
from ditch_drake.common.files import atomic_output
from ditch_drake.spec import actions
from ditch_drake.spec.observation_layout import IMAGE_SHAPE, STACK_DEPTH

if TYPE_CHECKING:  # Reading and training need no Drake: a GPU box without pydrake can train.
    from ditch_drake.systems.demo_recorder import DemoLog

SCHEMA_VERSION = 1
FILE_PATTERN = "demo_*.npz"
ARRAY_FIELDS = {
    "image": ((*IMAGE_SHAPE,), np.uint8),
    "imu_stack": ((2 * STACK_DEPTH,), np.float32),
    "distance_stack": ((STACK_DEPTH,), np.float32),
    "bearing_stack": ((STACK_DEPTH,), np.float32),
    "label": ((), np.int16),
    "time_s": ((), np.float64),
    "pose": ((6,), np.float32),
    "raw_command": ((2,), np.float32),
}
# The metadata keys that code reads back, and their JSON types. Absent keys pass (files made
# by hand or by older versions; `dataset_summary` counts them as "?"); bools are not integers.
_METADATA_TYPES = {
    "schema_version": int,
    "ditch_drake_version": str,
    "action_table": list,
    "image_encoding": str,
    "environment": str,
    "task": dict,
    "seed": int,
    "outcome": dict,
    "control_period_s": (int, float),
    "expert_style": dict,
    "driver": str,
    "learner": (str, type(None)),
    "learner_sha256": str,
    "trimmed_steps": int,
}
_NESTED_METADATA_TYPES = {("task", "index"): int, ("task", "name"): str, ("outcome", "status"): str}
_JSON_TYPE_NAMES = {
    dict: "an object",
    list: "an array",
    str: "a string",
    int: "an integer",
    float: "a number",
    bool: "a boolean",
    type(None): "null",
}
_EXPECTED_FILE = (
    f"a .npz of the arrays {list(ARRAY_FIELDS)} and a JSON metadata string (schema_version "
    f"{SCHEMA_VERSION}), as `ditch-drake collect` writes"
)


@dataclass
class Demonstration:
    """One demonstration's arrays (see the module docstring) and metadata."""

    arrays: dict[str, np.ndarray]
    metadata: dict
    path: Path | None = None

    def __len__(self) -> int:
        return len(self.arrays["label"])


def log_to_arrays(log: "DemoLog") -> dict[str, np.ndarray]:
    """A recorder's log as the file's arrays."""
    steps = log.steps
    if not steps:
        raise DatasetError("the demonstration log is empty")
    return {
        "image": np.stack([step.image for step in steps]).astype(np.uint8),
        "imu_stack": np.stack([step.imu_stack for step in steps]).astype(np.float32),
        "distance_stack": np.stack([step.distance_stack for step in steps]).astype(np.float32),
        "bearing_stack": np.stack([step.bearing_stack for step in steps]).astype(np.float32),
        "label": np.array([step.label for step in steps], dtype=np.int16),
        "time_s": np.array([step.time_s for step in steps], dtype=np.float64),
        "pose": np.stack([step.pose for step in steps]).astype(np.float32),
        "raw_command": np.stack([step.raw_command for step in steps]).astype(np.float32),
    }


def standard_metadata(**fields) -> dict:
    """Metadata every file carries, plus the caller's fields."""
    return {
        "schema_version": SCHEMA_VERSION,
        "ditch_drake_version": __version__,
        "action_table": actions.COMMANDS.tolist(),
        "image_encoding": "uint8 = round(255 * normal_z), normal_z in [0, 1]",
        **fields,
    }


def save_demonstration(path: str | Path, demonstration: Demonstration) -> Path:
    """Validates and writes one demonstration atomically; returns the path.

    The file gets the mode a plain `open()` would give (0666 less the umask; see
    `ditch_drake.common.files.atomic_output`).
    """
    path = Path(path)
    validate_demonstration(demonstration.arrays, demonstration.metadata, path)
    with atomic_output(path) as file:
        np.savez_compressed(file, metadata=np.array(json.dumps(demonstration.metadata)), **demonstration.arrays)
    return path


def load_demonstration(path: str | Path) -> Demonstration:
    """Reads and validates one file.

    Nothing in the file is unpickled: an archive holding Python objects, like one that is
    not an archive at all, is refused as not a demonstration file.

    Raises:
        DatasetError: naming the file and what is wrong with it.
    """
    path = Path(path)
    if path.is_dir():
        raise DatasetError(f"demonstration file {path} is a folder; expected {_EXPECTED_FILE}")
    try:
        data = np.load(path, allow_pickle=False)
    except FileNotFoundError as error:
        raise DatasetError(f"demonstration file {path} does not exist") from error
    except PermissionError as error:
        raise DatasetError(f"demonstration file {path} cannot be read: {error.strerror}") from error
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:
        # numpy's own message for bytes that are neither .npy nor .npz suggests unpickling
        # them (allow_pickle), which a file of unknown origin must never get: not passed on.
        reason = "it is empty" if isinstance(error, EOFError) else "it is not a .npz archive"
        raise DatasetError(_not_a_demonstration(path, f"{reason}, {type(error).__name__}")) from error
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise DatasetError(_not_a_demonstration(path, "it is a single .npy array, not a .npz archive"))
    try:
        with data:
            arrays = {key: data[key] for key in data.files if key != "metadata"}
            text = data["metadata"] if "metadata" in data.files else None
    except ValueError as error:  # numpy refuses object arrays without unpickling them.
        raise DatasetError(_not_a_demonstration(path, "it holds pickled Python objects")) from error
    except (OSError, EOFError, zipfile.BadZipFile, zlib.error) as error:
        reason = f"truncated or damaged: {type(error).__name__}: {error}"
        raise DatasetError(_not_a_demonstration(path, reason)) from error
    if text is None:
        raise DatasetError(f"demonstration file {path} has no metadata; expected {_EXPECTED_FILE}")
    if text.shape != () or text.dtype.kind != "U":
        raise DatasetError(
            f"demonstration file {path}: 'metadata' is a {text.dtype} array of shape {text.shape}; "
            "expected a 0-d string of JSON"
        )
    try:
        metadata = json.loads(str(text))
    except json.JSONDecodeError as error:
        raise DatasetError(f"demonstration file {path}: 'metadata' is not JSON ({error})") from error
    validate_demonstration(arrays, metadata, path)
    return Demonstration(arrays, metadata, path)


def _not_a_demonstration(path: Path, reason: str) -> str:
    return (
        f"demonstration file {path} is corrupt or not a demonstration file of this schema ({reason}); "
        f"expected {_EXPECTED_FILE}"
    )


def _json_type(kinds: type | tuple[type, ...]) -> str:
    kinds = kinds if isinstance(kinds, tuple) else (kinds,)
    return " or ".join(_JSON_TYPE_NAMES[kind] for kind in kinds)


def _is_a(value, kinds: type | tuple[type, ...]) -> bool:
    """isinstance, except that a JSON boolean is not an integer or a number."""
    kinds = kinds if isinstance(kinds, tuple) else (kinds,)
    return isinstance(value, kinds) and not (isinstance(value, bool) and bool not in kinds)


def _validate_metadata(metadata, path: Path) -> None:
    """Checks the JSON types of the metadata keys that code reads (`_METADATA_TYPES`)."""
    if not isinstance(metadata, dict):
        raise DatasetError(
            f"{path}: the metadata is {_json_type(type(metadata))} in JSON; expected an object "
            "of keys such as schema_version, environment, task, seed, outcome"
        )
    for key, kinds in _METADATA_TYPES.items():
        if key in metadata and not _is_a(metadata[key], kinds):
            value = metadata[key]
            raise DatasetError(
                f"{path}: metadata key {key!r} is {_json_type(type(value))} ({value!r:.60}); "
                f"expected {_json_type(kinds)}"
            )
    for (outer, key), kinds in _NESTED_METADATA_TYPES.items():
        inner = metadata.get(outer, {})
        if key in inner and not _is_a(inner[key], kinds):
            value = inner[key]
            raise DatasetError(
                f"{path}: metadata key {outer!r}.{key!r} is {_json_type(type(value))} "
                f"({value!r:.60}); expected {_json_type(kinds)}"
            )


def validate_demonstration(arrays: dict, metadata: dict, path: Path) -> None:
    """Checks the metadata's types and version and every array's shape, dtype and values.

    Raises:
        DatasetError: naming `path` and what is wrong.
    """
    _validate_metadata(metadata, path)
    version = metadata.get("schema_version")
    if version != SCHEMA_VERSION:
        raise DatasetError(f"{path}: schema_version {version!r}, expected {SCHEMA_VERSION}")
    missing = sorted(set(ARRAY_FIELDS) - set(arrays))
    if missing:
        raise DatasetError(f"{path}: missing arrays {missing}")
    steps = len(arrays["label"])
    if steps == 0:
        raise DatasetError(f"{path}: the demonstration has no steps")
    for key, (shape, dtype) in ARRAY_FIELDS.items():
        array = arrays[key]
        if array.shape != (steps, *shape) or array.dtype != dtype:
            raise DatasetError(f"{path}: array {key!r} has shape {array.shape} and dtype {array.dtype}; "
                               f"expected {(steps, *shape)} and {np.dtype(dtype)}")
        if array.dtype.kind == "f" and not np.all(np.isfinite(array)):
            raise DatasetError(f"{path}: array {key!r} holds NaN or inf")
    labels = arrays["label"]
    if labels.min() < 0 or labels.max() >= actions.NUM_LABELS:
        raise DatasetError(f"{path}: labels span {labels.min()}..{labels.max()}; expected 0..{actions.NUM_LABELS - 1}")


def restack_images(image: np.ndarray, depth: int = STACK_DEPTH, stride: int = 1) -> np.ndarray:
    """(T, H, W) newest frames -> (ceil(T / stride), depth, H, W) stacks of steps 0, stride,
    2 stride, ...: each the step's frame and the depth - 1 frames before it, newest first, zeros
    before the start. Only the kept steps' stacks are made."""
    kept = np.arange(0, len(image), stride)
    stacks = np.zeros((len(kept), depth, *image.shape[1:]), dtype=image.dtype)
    for age in range(depth):
        source = kept - age
        present = source >= 0
        stacks[present, age] = image[source[present]]
    return stacks


def demonstration_paths(directory: str | Path) -> list[Path]:
    """The demonstration files in a directory, in name order."""
    directory = Path(directory)
    if not directory.is_dir():
        raise DatasetError(f"dataset directory {directory} does not exist")
    return sorted(directory.glob(FILE_PATTERN))


def check_max_demos(max_demos: int | None) -> None:
    """Raises ConfigError for `max_demos` < 1 (a negative one would silently drop the last files)."""
    if max_demos is not None and max_demos < 1:
        raise ConfigError(f"max_demos={max_demos}: expected an integer >= 1, or none for all (--max-demos)")


def load_dataset(directory: str | Path, max_demos: int | None = None) -> list[Demonstration]:
    """All (or the first `max_demos`) demonstrations of a folder of `.npz` files, validated
    (`ditch_drake.demos.store.load_demonstrations` reads a dataset folder too).

    Raises:
        ConfigError: `max_demos` < 1 (a negative one would silently drop the last files).
        DatasetError: no such directory, no demonstration files, or a bad file.
    """
    check_max_demos(max_demos)
    paths = demonstration_paths(directory)
    if not paths:
        raise DatasetError(f"dataset directory {directory} holds no {FILE_PATTERN} files")
    return [load_demonstration(path) for path in paths[:max_demos]]


def dataset_summary(demonstrations: list[Demonstration]) -> dict:
    """Counts per label, per task, per outcome and per driver (the expert, or a DAgger
    round's learner), and the class imbalance."""
    labels = np.concatenate([demo.arrays["label"] for demo in demonstrations])
    per_label = np.bincount(labels, minlength=actions.NUM_LABELS)
    per_task = Counter(demo.metadata.get("task", {}).get("name", "?") for demo in demonstrations)
    per_outcome = Counter(demo.metadata.get("outcome", {}).get("status", "?") for demo in demonstrations)
    per_driver = Counter(demo.metadata.get("learner") or "expert" for demo in demonstrations)
    nonzero = per_label[per_label > 0]
    return {
        "demonstrations": len(demonstrations),
        "steps": len(labels),
        "per_label": per_label.tolist(),
        "per_task": dict(per_task),
        "per_outcome": dict(per_outcome),
        "per_driver": dict(per_driver),
        "straight_fraction": float(per_label[actions.STRAIGHT_LABEL] / max(1, len(labels))),
        "majority_to_minority_ratio": float(nonzero.max() / nonzero.min()) if len(nonzero) else 0.0,
    }


def to_array_set(demonstrations: list[Demonstration], first_demo_id: int = 0, strides: list[int] | None = None):
    """The demonstrations as one training `ArraySet`, images restacked as uint8.

    Demonstration i gets demo_id first_demo_id + i, so a validation split can hold out
    whole demonstrations. `strides[i]` keeps every k-th step of demonstration i (None: every
    step); a kept step's stack still holds the frames of the steps just before it, as the
    `FrameStacker` gives the policy, not those of the kept steps before it.
    """
    from ditch_drake.learning.data import ArraySet

    if not demonstrations:
        raise DatasetError("no demonstrations to train on")
    strides = [1] * len(demonstrations) if strides is None else strides
    if len(strides) != len(demonstrations) or min(strides) < 1:
        raise DatasetError(f"strides={strides}: expected one stride >= 1 per demonstration ({len(demonstrations)})")
    pairs = list(zip(demonstrations, strides, strict=True))
    counts = np.array([len(range(0, len(demo), stride)) for demo, stride in pairs])
    ends = np.cumsum(counts)
    # The stacks are written into one array, so that the samples (64 KiB each) are never held
    # twice, as a list of stacks and their concatenation.
    frames = demonstrations[0].arrays["image"]
    image = np.empty((int(ends[-1]), STACK_DEPTH, *frames.shape[1:]), dtype=frames.dtype)
    for (demo, stride), end, count in zip(pairs, ends, counts, strict=True):
        image[end - count:end] = restack_images(demo.arrays["image"], stride=stride)

    def joined(name: str) -> np.ndarray:
        return np.concatenate([demo.arrays[name][::stride] for demo, stride in pairs])

    return ArraySet(
        image=image,
        imu=joined("imu_stack"),
        distance=joined("distance_stack"),
        bearing=joined("bearing_stack"),
        label=joined("label").astype(np.int64),
        demo_id=np.repeat(first_demo_id + np.arange(len(pairs), dtype=np.int64), counts),
    )


def reflected(demonstration: Demonstration) -> Demonstration:
    """A copy of a recorded rollout with every step reflected left to right
    (`ditch_drake.learning.mirror`; its metadata says so).

    The image, IMU, bearing and label arrays are reflected; the poses and raw commands,
    which training does not read, are kept as recorded.
    """
    from ditch_drake.learning.mirror import mirror_left_right

    names = {"image": "image", "imu": "imu_stack", "bearing": "bearing_stack", "label": "label"}
    batch = {name: demonstration.arrays[key].copy() for name, key in names.items()}
    mirror_left_right(batch)
    arrays = {**demonstration.arrays, **{key: batch[name] for name, key in names.items()}}
    return Demonstration(arrays=arrays, metadata={**demonstration.metadata, "reflected": True}, path=demonstration.path)
