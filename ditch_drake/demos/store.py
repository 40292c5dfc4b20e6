"""The dataset store: a folder of episodes, one memory-mappable `.npy` file per field.

    D/
      dataset.json                  format, schema version, the fields with their units
      episodes/
        episode_000000/
          image.npy                 (T, 128, 128) uint8
          imu_stack.npy ... intervention.npy
          episode.json              the episode's metadata, written last
        .episode_000001.<pid>.<token>.tmp/    an episode still being written (or torn)

An episode is the unit of writing: its files go into a hidden temporary folder, each synced,
`episode.json` last, and the folder is renamed into place, so a reader sees a whole episode or
none. A worker killed mid-write leaves the temporary folder, which readers skip with a warning
and writers of the same store remove once its process is gone (`remove_stale_episodes`). The
index of the episodes is their `episode.json` files, read in name order: there is no separate
index file to fall out of step with the folders.

Why `.npy` per field and episode, not zarr or HDF5: numpy maps a `.npy` file into memory with no
library beyond numpy (`np.load(mmap_mode="r")`), so training reads the frames it needs and no
more; an uncompressed file is what makes the mapping possible (zarr's chunks are compressed and
decoded whole), and a folder per episode makes appending atomic without locks, even from many
processes at once. The cost is disk: 16 KiB per step for the image, about 20 times the
compressed `.npz` of the older format, since the normal images compress well (Wide's 40
demonstrations: 243 MiB against 12 MiB; `ditch-drake dataset convert` turns those into a store).

Fields, T control steps each (`FIELDS`; units in `dataset.json`):

| field | shape, dtype | meaning |
| --- | --- | --- |
| `image` | (T, 128, 128) uint8 | newest surface-normal image, round(255 n_z) for n_z in [0, 1] |
| `imu_stack` | (T, 8) float32 | [roll, pitch] newest first (rad) |
| `distance_stack` | (T, 4) float32 | distance to the goal, newest first (m) |
| `bearing_stack` | (T, 4) float32 | bearing to the goal, newest first (rad, positive left) |
| `label` | (T,) int16 | the action label recorded, 0..16 (the expert's, a person's, or a DAgger labeller's) |
| `time_s` | (T,) float64 | simulated time of the step (s) |
| `pose` | (T, 6) float32 | chassis [x, y, z (m), roll, pitch, yaw (rad)] in the world |
| `raw_command` | (T, 2) float32 | the labelling driver's command before quantization [v (m/s), w (rad/s)] |
| `intervention` | (T,) bool | the step's command came from a supervisor taking over, not the driving policy |

`episode.json` holds the demonstration's metadata (environment, task, seed, outcome, expert
style, driver, ...) and the store's own keys: `steps`, and `ditch` ({"name", "seed", "split"}:
the generated ditch's seed and split, or the paper's split for a packaged environment).
"""

import json
import os
import re
import secrets
import shutil
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ditch_drake import __version__
from ditch_drake.common.errors import DatasetError
from ditch_drake.common.files import atomic_write_text, fsync_folder, process_exists
from ditch_drake.demos.dataset import (
    ARRAY_FIELDS,
    Demonstration,
    check_max_demos,
    load_dataset,
    validate_demonstration,
)
from ditch_drake.world.ditch_splits import seed_of_environment, split_of_environment

STORE_FORMAT = "ditch_drake.dataset"
STORE_SCHEMA_VERSION = 1
STORE_FILE = "dataset.json"
EPISODES_DIR = "episodes"
EPISODE_FILE = "episode.json"
EPISODE_PREFIX = "episode_"

FIELDS: dict[str, tuple[tuple[int, ...], np.dtype]] = {
    **{name: (shape, np.dtype(dtype)) for name, (shape, dtype) in ARRAY_FIELDS.items()},
    "intervention": ((), np.dtype(np.bool_)),
}
FIELD_UNITS = {
    "image": "normal z in [0, 1] as uint8 0..255",
    "imu_stack": "rad",
    "distance_stack": "m",
    "bearing_stack": "rad",
    "label": "action label 0..16",
    "time_s": "s",
    "pose": "m, m, m, rad, rad, rad",
    "raw_command": "m/s, rad/s",
    "intervention": "bool",
}
_EPISODE_NAME = re.compile(rf"^{EPISODE_PREFIX}(\d{{6,}})$")
_TEMPORARY_EPISODE = re.compile(rf"^\.({EPISODE_PREFIX}\d{{6,}})\.(\d+)\.[0-9a-f]{{12}}\.tmp$")
_EXPECTED_STORE = (f"a dataset folder holding {STORE_FILE} (format {STORE_FORMAT!r}, schema_version "
                   f"{STORE_SCHEMA_VERSION}) and {EPISODES_DIR}/, as `ditch-drake collect` or "
                   "`ditch-drake dataset convert` writes")


def episode_name(index: int) -> str:
    """The folder name of episode `index` (`episode_000042`)."""
    if index < 0:
        raise DatasetError(f"episode index {index}: expected an integer >= 0")
    return f"{EPISODE_PREFIX}{index:06d}"


def episode_index(name: str) -> int:
    """The index in an episode's folder name."""
    match = _EPISODE_NAME.match(name)
    if match is None:
        raise DatasetError(f"{name!r} is not an episode folder name; expected {EPISODE_PREFIX}NNNNNN")
    return int(match.group(1))


def is_store(path: str | os.PathLike) -> bool:
    """Whether `path` is a dataset folder (it holds `dataset.json`)."""
    return (Path(path) / STORE_FILE).is_file()


@dataclass(frozen=True)
class Episode:
    """One complete episode of a store: its row of the index."""

    name: str
    path: Path
    steps: int
    metadata: dict

    @property
    def index(self) -> int:
        return episode_index(self.name)

    def field_path(self, field: str) -> Path:
        return self.path / f"{field}.npy"


def _store_header() -> dict:
    return {
        "format": STORE_FORMAT,
        "schema_version": STORE_SCHEMA_VERSION,
        "created_by": f"ditch_drake {__version__}",
        "fields": {name: {"shape": ["T", *shape], "dtype": dtype.name, "unit": FIELD_UNITS[name]}
                   for name, (shape, dtype) in FIELDS.items()},
    }


def _write_synced(path: Path, write) -> None:
    with open(path, "wb") as file:
        write(file)
        file.flush()
        os.fsync(file.fileno())


class DatasetStore:
    """A dataset folder (see the module docstring): append episodes, list them, read their fields.

    Open one with `DatasetStore.open(path)` (it must exist) or `DatasetStore.create(path)`
    (made if missing, opened if it is already a store).
    """

    def __init__(self, root: Path):
        self.root = Path(root)

    @classmethod
    def open(cls, path: str | os.PathLike) -> "DatasetStore":
        """The store at `path`, after checking its format and schema version.

        Raises:
            DatasetError: no such folder, no `dataset.json`, or one of another format or version.
        """
        root = Path(path)
        if not root.exists():
            raise DatasetError(f"dataset folder {root} does not exist; expected {_EXPECTED_STORE}")
        if not root.is_dir():
            raise DatasetError(f"dataset path {root} is a file; expected {_EXPECTED_STORE}")
        header_path = root / STORE_FILE
        if not header_path.is_file():
            raise DatasetError(f"{root} has no {STORE_FILE}; expected {_EXPECTED_STORE}")
        try:
            header = json.loads(header_path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
            raise DatasetError(f"{header_path}: {error}; expected {_EXPECTED_STORE}") from error
        if not isinstance(header, dict) or header.get("format") != STORE_FORMAT:
            found = header.get("format") if isinstance(header, dict) else type(header).__name__
            raise DatasetError(f"{header_path}: format {found!r}; expected {STORE_FORMAT!r}")
        if header.get("schema_version") != STORE_SCHEMA_VERSION:
            raise DatasetError(f"{header_path}: schema_version {header.get('schema_version')!r} is unknown; expected "
                               f"{STORE_SCHEMA_VERSION} (this ditch_drake {__version__} reads only that)")
        return cls(root)

    @classmethod
    def create(cls, path: str | os.PathLike) -> "DatasetStore":
        """A new store at `path` (the folder may exist, empty or not, if it holds no store
        yet), or the store already there.

        Raises:
            DatasetError: `path` is a file, or holds a `dataset.json` of another format or version.
        """
        root = Path(path)
        if root.exists() and not root.is_dir():
            raise DatasetError(f"dataset path {root} is a file; expected a folder for {_EXPECTED_STORE}")
        if is_store(root):
            return cls.open(root)
        try:
            (root / EPISODES_DIR).mkdir(parents=True, exist_ok=True)
            atomic_write_text(root / STORE_FILE, json.dumps(_store_header(), indent=2) + "\n")
        except OSError as error:  # A part of the path is a file, no permission, a full disk.
            raise DatasetError(f"dataset folder {root} cannot be made: {error.strerror or error}") from error
        return cls(root)

    @property
    def episodes_dir(self) -> Path:
        return self.root / EPISODES_DIR

    def episode_path(self, index: int) -> Path:
        return self.episodes_dir / episode_name(index)

    def has_episode(self, index: int) -> bool:
        """Whether a complete episode `index` is stored (its folder and `episode.json`)."""
        return (self.episode_path(index) / EPISODE_FILE).is_file()

    def temporary_episodes(self) -> list[Path]:
        """Episodes being written, or left torn by a killed writer."""
        if not self.episodes_dir.is_dir():
            return []
        return sorted(path for path in self.episodes_dir.iterdir() if _TEMPORARY_EPISODE.match(path.name))

    def remove_stale_episodes(self) -> list[Path]:
        """Deletes the temporary folders of writers whose process is gone; returns them."""
        removed = []
        for path in self.temporary_episodes():
            pid = int(_TEMPORARY_EPISODE.match(path.name).group(2))
            if pid != os.getpid() and not process_exists(pid):
                shutil.rmtree(path, ignore_errors=True)
                removed.append(path)
        return removed

    def episodes(self, warn: bool = True) -> list[Episode]:
        """The complete episodes, in index order.

        A torn episode (a temporary folder, or an episode folder without its `episode.json`)
        is skipped, with a warning when `warn`.

        Raises:
            DatasetError: an `episode.json` that is not a JSON object with an integer `steps`.
        """
        if not self.episodes_dir.is_dir():
            raise DatasetError(f"{self.root} has no {EPISODES_DIR}/ folder; expected {_EXPECTED_STORE}")
        found, torn = [], [path.name for path in self.temporary_episodes()]
        for path in sorted(self.episodes_dir.iterdir()):
            if not _EPISODE_NAME.match(path.name):
                continue
            metadata_path = path / EPISODE_FILE
            if not metadata_path.is_file():
                torn.append(path.name)
                continue
            found.append(_read_episode(path, metadata_path))
        if torn and warn:
            warnings.warn(f"{self.root}: skipped {len(torn)} torn episode(s) (written by a process that was killed, "
                          f"or still being written): {torn[:5]}", stacklevel=2)
        return sorted(found, key=lambda episode: episode.index)

    def append(self, demonstration: Demonstration, index: int | None = None,
               intervention: np.ndarray | None = None) -> Episode:
        """Writes one episode atomically (see the module docstring); returns it.

        Args:
            demonstration: its arrays and metadata (validated first).
            index: the episode's index (`collect` uses the demonstration's slot); None takes
                the next after the highest stored.
            intervention: (T,) bool, the steps a supervisor took over; None: none did (an
                `intervention` array among the demonstration's arrays is used if present).

        Raises:
            DatasetError: an invalid demonstration, or episode `index` already stored (an
                episode is never overwritten).
        """
        arrays = dict(demonstration.arrays)
        if intervention is not None:
            arrays["intervention"] = np.asarray(intervention)
        arrays.setdefault("intervention", np.zeros(len(demonstration), dtype=np.bool_))
        if index is None:
            stored = self.episodes(warn=False)
            index = stored[-1].index + 1 if stored else 0
        final = self.episode_path(index)
        validate_demonstration({k: v for k, v in arrays.items() if k != "intervention"}, demonstration.metadata, final)
        _check_field(arrays["intervention"], "intervention", len(demonstration), final)
        if final.exists():
            raise DatasetError(f"{final} exists; an episode is never overwritten (expected a new index)")
        self.episodes_dir.mkdir(parents=True, exist_ok=True)
        temporary = self.episodes_dir / f".{final.name}.{os.getpid()}.{secrets.token_hex(6)}.tmp"
        temporary.mkdir()
        try:
            for name in FIELDS:
                value = np.ascontiguousarray(arrays[name], dtype=FIELDS[name][1])
                _write_synced(temporary / f"{name}.npy", lambda file, value=value: np.save(file, value))
            metadata = episode_metadata(demonstration.metadata, len(demonstration))
            text = json.dumps(metadata, indent=1).encode("utf-8")
            _write_synced(temporary / EPISODE_FILE, lambda file: file.write(text))
            fsync_folder(temporary)
            try:
                os.rename(temporary, final)  # Fails, rather than merging, if another writer took the index.
            except OSError as error:
                raise DatasetError(f"{final} was written by another process meanwhile ({error})") from error
            fsync_folder(self.episodes_dir)
        finally:
            if temporary.exists():
                shutil.rmtree(temporary, ignore_errors=True)
        return _read_episode(final, final / EPISODE_FILE)

    def read(self, episode: Episode, fields: list[str] | None = None, mmap: bool = True) -> dict[str, np.ndarray]:
        """The episode's arrays (all fields, or `fields`), memory-mapped read-only with `mmap`.

        Every array's shape and dtype are checked against `FIELDS` and the episode's `steps`
        (a header read, even when mapped); the small fields' values are checked too.

        Raises:
            DatasetError: a missing or unreadable file, or an array of another shape, dtype or
                length than the episode's, naming the file.
        """
        arrays = {}
        for name in fields or list(FIELDS):
            if name not in FIELDS:
                raise DatasetError(f"unknown field {name!r}; expected one of {list(FIELDS)}")
            path = episode.field_path(name)
            try:
                value = np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
            except FileNotFoundError as error:
                raise DatasetError(f"{path} is missing; expected the episode's {name} array") from error
            except (OSError, ValueError, EOFError) as error:
                raise DatasetError(f"{path}: not a readable .npy array ({type(error).__name__}: {error})") from error
            _check_field(value, name, episode.steps, path)
            arrays[name] = value
        return arrays

    def load(self, episode: Episode) -> Demonstration:
        """The episode as an in-memory `Demonstration` (every array copied, validated); its
        `intervention` array is among the arrays."""
        arrays = {name: np.array(value) for name, value in self.read(episode, mmap=False).items()}
        demonstration = Demonstration(arrays, demonstration_metadata(episode.metadata), episode.path)
        validate_demonstration({k: v for k, v in arrays.items() if k != "intervention"}, demonstration.metadata,
                               episode.path)
        return demonstration


def load_demonstrations(folder: str | os.PathLike, max_demos: int | None = None) -> list[Demonstration]:
    """All (or the first `max_demos`) demonstrations of a dataset folder, or of an older folder
    of `.npz` files (`load_dataset`), validated, in memory.

    Raises:
        ConfigError: `max_demos` < 1.
        DatasetError: no such folder, no complete episodes, or a bad file.
    """
    if not is_store(folder):
        return load_dataset(folder, max_demos)
    store = DatasetStore.open(folder)
    return [store.load(episode) for episode in first_episodes(store, max_demos)]


def first_episodes(store: DatasetStore, max_demos: int | None = None) -> list[Episode]:
    """The first `max_demos` complete episodes of `store` (None: all), in index order.

    Raises:
        ConfigError: `max_demos` < 1.
        DatasetError: the store holds no complete episode.
    """
    check_max_demos(max_demos)
    episodes = store.episodes()
    if not episodes:
        raise DatasetError(f"dataset folder {store.root} holds no complete episodes")
    return episodes[:max_demos]


def episode_metadata(metadata: dict, steps: int) -> dict:
    """A demonstration's metadata as an `episode.json`: the store's keys added."""
    environment = metadata.get("environment", "")
    ditch = {"name": environment, "seed": seed_of_environment(environment) if isinstance(environment, str) else None,
             "split": split_of_environment(environment) if isinstance(environment, str) else ""}
    return {**metadata, "steps": steps, "ditch": ditch}


def demonstration_metadata(metadata: dict) -> dict:
    """An `episode.json`'s metadata without the store's keys: the demonstration's as recorded."""
    return {key: value for key, value in metadata.items() if key not in ("steps", "ditch")}


def _read_episode(path: Path, metadata_path: Path) -> Episode:
    try:
        metadata = json.loads(metadata_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DatasetError(f"{metadata_path}: {error}; expected the episode's JSON metadata") from error
    steps = metadata.get("steps") if isinstance(metadata, dict) else None
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
        raise DatasetError(f"{metadata_path}: 'steps' is {steps!r}; expected the episode's step count, an integer >= 1")
    return Episode(path.name, path, steps, metadata)


def _check_field(value: np.ndarray, name: str, steps: int, path: Path) -> None:
    shape, dtype = FIELDS[name]
    if value.shape != (steps, *shape) or value.dtype != dtype:
        raise DatasetError(f"{path}: array {name!r} has shape {value.shape} and dtype {value.dtype}; expected "
                           f"{(steps, *shape)} and {dtype} (the episode's {steps} steps)")


def convert_npz_folder(source: str | os.PathLike, destination: str | os.PathLike, progress: bool = True) -> dict:
    """Copies a folder of `demo_NNN.npz` files into the store at `destination`, episode NNN
    for file NNN, losslessly (every array as stored, the metadata as recorded; no step was
    taken over, so `intervention` is all false).

    An episode already stored is left alone, so an interrupted conversion run again finishes
    the rest. A file that fails to load stops the conversion, naming it (what was converted
    is kept).

    Returns:
        {"source", "destination", "converted", "kept", "steps"}.

    Raises:
        DatasetError: `source` is not a folder of `.npz` demonstrations, a bad file, or
            `destination` is a file or another format's folder.
    """
    from tqdm import tqdm

    from ditch_drake.demos.dataset import demonstration_paths, load_demonstration

    paths = demonstration_paths(source)
    if not paths:
        raise DatasetError(f"{source} holds no demo_NNN.npz files; expected a folder that `collect` wrote "
                           "before the dataset store")
    if is_store(source):
        raise DatasetError(f"{source} is already a dataset folder; expected a folder of demo_NNN.npz files")
    store = DatasetStore.create(destination)
    store.remove_stale_episodes()
    converted = kept = steps = 0
    for path in tqdm(paths, desc=f"convert {source}", disable=not progress):
        number = path.stem.removeprefix("demo_")
        if not number.isdigit():
            raise DatasetError(f"{path}: expected a name demo_NNN.npz, NNN the demonstration's slot")
        if store.has_episode(int(number)):
            kept += 1
            continue
        demonstration = load_demonstration(path)
        store.append(demonstration, int(number))
        converted += 1
        steps += len(demonstration)
    return {"source": str(source), "destination": str(destination), "converted": converted, "kept": kept,
            "steps": steps}


def store_summary(store: DatasetStore) -> dict:
    """`dataset_summary`'s counts for a store, from its index and its label and intervention
    arrays only (the images are not read), plus per split and per environment counts, the
    intervened steps and the size on disk."""
    from collections import Counter

    from ditch_drake.spec import actions

    episodes = store.episodes()
    per_label = np.zeros(actions.NUM_LABELS, dtype=np.int64)
    intervened = 0
    for episode in episodes:
        arrays = store.read(episode, ["label", "intervention"])
        per_label += np.bincount(arrays["label"], minlength=actions.NUM_LABELS)
        intervened += int(np.count_nonzero(arrays["intervention"]))
    steps = int(per_label.sum())
    nonzero = per_label[per_label > 0]

    def count(key) -> dict:
        return dict(Counter(key(episode.metadata) for episode in episodes))

    return {
        "format": STORE_FORMAT,
        "schema_version": STORE_SCHEMA_VERSION,
        "episodes": len(episodes),
        "demonstrations": len(episodes),
        "steps": steps,
        "intervened_steps": intervened,
        "disk_mib": sum(path.stat().st_size for path in store.episodes_dir.rglob("*") if path.is_file()) / 2**20,
        "per_label": per_label.tolist(),
        "per_task": count(lambda m: (m.get("task") or {}).get("name", "?")),
        "per_outcome": count(lambda m: (m.get("outcome") or {}).get("status", "?")),
        "per_driver": count(lambda m: m.get("learner") or m.get("driver") or "expert"),
        "per_split": count(lambda m: (m.get("ditch") or {}).get("split") or "?"),
        "per_environment": count(lambda m: m.get("environment", "?")),
        "straight_fraction": float(per_label[actions.STRAIGHT_LABEL] / max(1, steps)),
        "majority_to_minority_ratio": float(nonzero.max() / nonzero.min()) if len(nonzero) else 0.0,
    }
