"""The LeRobotDataset v3.0 layout, written with pyarrow alone (`export_dataset(..., "lerobot", ...)`).

    L/
      meta/info.json                          fps, counts, path templates, the features
      meta/stats.json                         per feature: mean, std, min, max, count, q01..q99
      meta/tasks.parquet                      one row per task string (its index: the task)
      meta/episodes/chunk-000/file-000.parquet    one row per episode: length, where its frames are
      data/chunk-000/file-000.parquet         one row per frame, one row group per episode

The layout is the one LeRobot reads (`LeRobotDataset(repo_id, root=L)`; checked frame by frame
with lerobot 0.6.1, docs/concepts/datasets.md): a data file
holds whole episodes and is closed past `DATA_FILE_MB`, a chunk folder holds `CHUNKS_SIZE`
files, every column of a data file is a feature of `info.json` and the reverse. The image is
an "image" feature, a PNG in the row ({"bytes", "path": None}), not a video: lossless, and
LeRobot decodes it with no video library. `episode_index` counts 0..N-1 in the store's order;
the store's own episode name is the episode row's `source_episode`.

Stats are what LeRobot's `compute_stats` gives, over every frame rather than a sample of the
images: population mean and std, min, max, count, and quantiles q01..q99 read off a histogram
(exact for the image's 256 grey levels; within (max - min) / 5000 for the other features, as
LeRobot's own running histogram). An image's stats are per channel, shape (1, 1, 1), in [0, 1].
"""

import io
import json
from pathlib import Path

import numpy as np

from ditch_drake.common.errors import DatasetError
from ditch_drake.demos.exports import (
    ACTION_NAMES,
    STATE_NAMES,
    driver_of,
    label_commands,
    policy_state,
    task_text,
)
from ditch_drake.demos.exports import control_period_s as common_control_period_s
from ditch_drake.demos.store import FIELDS

CODEBASE_VERSION = "v3.0"
ROBOT_TYPE = "husky"
CHUNKS_SIZE = 1000
DATA_FILE_MB = 100
VIDEO_FILE_MB = 200  # LeRobot's default, recorded in info.json though no video is written.
CHUNK_FILE = "chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
DATA_PATH = "data/" + CHUNK_FILE
EPISODES_PATH = "meta/episodes/" + CHUNK_FILE
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
HISTOGRAM_BINS = 5000
IMAGE_KEY = "observation.image"
IMAGE_SHAPE = (128, 128, 1)

# Each feature: dtype, shape and names as info.json lists them. `label`, `intervention`, `pose`
# and `raw_command` keep the store's other fields; their names start with neither
# "observation" nor "action", so LeRobot's policies do not take them as inputs or targets.
FEATURES = {
    IMAGE_KEY: {"dtype": "image", "shape": list(IMAGE_SHAPE), "names": ["height", "width", "channels"]},
    "observation.state": {"dtype": "float32", "shape": [len(STATE_NAMES)], "names": STATE_NAMES},
    "action": {"dtype": "float32", "shape": [2], "names": ACTION_NAMES},
    "label": {"dtype": "int64", "shape": [1], "names": None},
    "intervention": {"dtype": "bool", "shape": [1], "names": None},
    "pose": {"dtype": "float32", "shape": [6], "names": ["x", "y", "z", "roll", "pitch", "yaw"]},
    "raw_command": {"dtype": "float32", "shape": [2], "names": ACTION_NAMES},
    "timestamp": {"dtype": "float32", "shape": [1], "names": None},
    "frame_index": {"dtype": "int64", "shape": [1], "names": None},
    "episode_index": {"dtype": "int64", "shape": [1], "names": None},
    "index": {"dtype": "int64", "shape": [1], "names": None},
    "task_index": {"dtype": "int64", "shape": [1], "names": None},
}


def _arrow_type(pa, feature: dict):
    if feature["dtype"] == "image":
        return pa.struct([("bytes", pa.binary()), ("path", pa.string())])
    value = pa.from_numpy_dtype(np.dtype(feature["dtype"]))
    return value if feature["shape"] == [1] else pa.list_(value, feature["shape"][0])


def _column(pa, value: np.ndarray, arrow_type):
    if value.ndim == 1:
        return pa.array(value, arrow_type)
    return pa.FixedSizeListArray.from_arrays(pa.array(value.ravel(), arrow_type.value_type), value.shape[1])


def _png(frame: np.ndarray) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(frame), mode="L").save(buffer, format="PNG")
    return buffer.getvalue()


def frame_columns(arrays: dict[str, np.ndarray], episode_index: int, first_index: int, task_index: int) -> dict:
    """One episode's columns but the image, as numpy arrays (T,) or (T, n) of the features' dtypes."""
    steps = len(arrays["label"])
    frame_index = np.arange(steps, dtype=np.int64)
    return {
        "observation.state": policy_state(arrays),
        "action": label_commands(arrays["label"]).astype(np.float32),
        "label": arrays["label"].astype(np.int64),
        "intervention": np.asarray(arrays["intervention"], dtype=np.bool_),
        "pose": np.asarray(arrays["pose"], dtype=np.float32),
        "raw_command": np.asarray(arrays["raw_command"], dtype=np.float32),
        "timestamp": (arrays["time_s"] - arrays["time_s"][0]).astype(np.float32),
        "frame_index": frame_index,
        "episode_index": np.full(steps, episode_index, dtype=np.int64),
        "index": first_index + frame_index,
        "task_index": np.full(steps, task_index, dtype=np.int64),
    }


class _Moments:
    """Count, mean, population variance (Chan's pairwise update), min and max per dimension."""

    def __init__(self):
        self.count, self.mean, self.m2, self.min, self.max = 0, None, None, None, None

    def update(self, values: np.ndarray) -> None:
        values = values.astype(np.float64).reshape(len(values), -1)
        count, mean = len(values), values.mean(axis=0)
        m2, low, high = ((values - mean) ** 2).sum(axis=0), values.min(axis=0), values.max(axis=0)
        if self.count == 0:
            self.count, self.mean, self.m2, self.min, self.max = count, mean, m2, low, high
            return
        total = self.count + count
        delta = mean - self.mean
        self.mean = self.mean + delta * count / total
        self.m2 = self.m2 + m2 + delta**2 * self.count * count / total
        self.count, self.min, self.max = total, np.minimum(self.min, low), np.maximum(self.max, high)

    def edges(self) -> list[np.ndarray]:
        return [np.linspace(low - 1e-10, high + 1e-10, HISTOGRAM_BINS + 1) for low, high in zip(self.min, self.max)]


def _quantile(histogram: np.ndarray, edges: np.ndarray, q: float) -> float:
    """The value below which a fraction q of the histogram's counts lie, linear within a bin."""
    cumulative = np.cumsum(histogram)
    target = q * cumulative[-1]
    bin_index = int(np.searchsorted(cumulative, target))
    if bin_index >= len(histogram):
        return float(edges[-1])
    before = cumulative[bin_index - 1] if bin_index > 0 else 0.0
    inside = histogram[bin_index]
    fraction = (target - before) / inside if inside > 0 else 0.0
    return float(edges[bin_index] + fraction * (edges[bin_index + 1] - edges[bin_index]))


def _feature_stats(moments: _Moments, histograms: list[np.ndarray], edges: list[np.ndarray]) -> dict:
    stats = {"min": moments.min, "max": moments.max, "mean": moments.mean,
             "std": np.sqrt(np.maximum(moments.m2 / moments.count, 0.0))}
    for q in QUANTILES:
        estimate = np.array([_quantile(h, e, q) for h, e in zip(histograms, edges)])
        stats[f"q{round(q * 100):02d}"] = np.clip(estimate, moments.min, moments.max)
    return {**{key: value.tolist() for key, value in stats.items()}, "count": [moments.count]}


def _image_stats(grey_levels: np.ndarray, frames: int) -> dict:
    """Per-channel stats of the image in [0, 1] from the count of each grey level (exact)."""
    values = np.arange(256) / 255.0
    total = grey_levels.sum()
    mean = float((grey_levels * values).sum() / total)
    std = float(np.sqrt(max((grey_levels * (values - mean) ** 2).sum() / total, 0.0)))
    present = np.flatnonzero(grey_levels)
    cumulative = np.cumsum(grey_levels)
    stats = {"min": values[present[0]], "max": values[present[-1]], "mean": mean, "std": std}
    for q in QUANTILES:
        stats[f"q{round(q * 100):02d}"] = values[int(np.searchsorted(cumulative, q * total))]
    return {**{key: [[[float(value)]]] for key, value in stats.items()}, "count": [frames]}


class _DataFiles:
    """The data parquet files: whole episodes each, the next file once one passes `DATA_FILE_MB`."""

    def __init__(self, root: Path, schema):
        self.root, self.schema = root, schema
        self.chunk_index = self.file_index = 0
        self.writer, self.path, self.files = None, None, 0

    def write(self, table) -> tuple[int, int]:
        import pyarrow.parquet as pq

        if self.writer is not None and self.path.stat().st_size >= DATA_FILE_MB * 2**20:
            self.close()
            self.file_index += 1
            if self.file_index == CHUNKS_SIZE:
                self.chunk_index, self.file_index = self.chunk_index + 1, 0
        if self.writer is None:
            self.path = self.root / DATA_PATH.format(chunk_index=self.chunk_index, file_index=self.file_index)
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.writer = pq.ParquetWriter(self.path, self.schema, compression="snappy")
            self.files += 1
        self.writer.write_table(table)  # One row group: the episode.
        return self.chunk_index, self.file_index

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None


def _fps(period_s: float) -> int:
    fps = round(1.0 / period_s)
    if fps < 1 or abs(fps * period_s - 1.0) > 1e-6:
        raise DatasetError(f"control period {period_s} s is {1.0 / period_s:g} frames a second; LeRobot's fps "
                           "is an integer: expected a period of 1/n s")
    return fps


def _episode_row(episode, new_index: int, task: str, chunk_file: tuple[int, int], first: int,
                 arrays: dict) -> dict:
    metadata = episode.metadata
    ditch = metadata.get("ditch") or {}
    return {
        "episode_index": new_index, "tasks": [task], "length": episode.steps,
        "data/chunk_index": chunk_file[0], "data/file_index": chunk_file[1],
        "dataset_from_index": first, "dataset_to_index": first + episode.steps,
        "meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0,
        "source_episode": episode.name, "environment": str(metadata.get("environment", "")),
        "task_name": str((metadata.get("task") or {}).get("name", "")),
        "ditch_split": str(ditch.get("split") or ""), "ditch_seed": ditch.get("seed"),
        "seed": metadata.get("seed"), "driver": driver_of(metadata),
        "outcome": str((metadata.get("outcome") or {}).get("status", "")),
        "intervened_steps": int(np.count_nonzero(arrays["intervention"])),
        "metadata": json.dumps(metadata),
    }


_EPISODE_TYPES = {"episode_index": "int64", "tasks": "list<string>", "length": "int64", "data/chunk_index": "int64",
                  "data/file_index": "int64", "dataset_from_index": "int64", "dataset_to_index": "int64",
                  "meta/episodes/chunk_index": "int64", "meta/episodes/file_index": "int64",
                  "source_episode": "string", "environment": "string", "task_name": "string",
                  "ditch_split": "string", "ditch_seed": "int64", "seed": "int64", "driver": "string",
                  "outcome": "string", "intervened_steps": "int64", "metadata": "string"}


def _write_episodes(pa, pq, rows: list[dict], path: Path) -> None:
    types = {"int64": pa.int64(), "string": pa.string(), "list<string>": pa.list_(pa.string())}
    table = pa.table({name: pa.array([row[name] for row in rows], type=types[kind])
                      for name, kind in _EPISODE_TYPES.items()})
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, path)


def _write_tasks(pa, pq, tasks: dict[str, int], path: Path) -> None:
    """tasks.parquet as pandas writes a frame indexed by "task" (LeRobot reads it with pandas
    and looks a frame's task string up as the index of row `task_index`)."""
    table = pa.table({"task_index": pa.array(list(tasks.values()), pa.int64()),
                      "task": pa.array(list(tasks), pa.string())})
    pandas_metadata = {
        "index_columns": ["task"],
        "column_indexes": [{"name": None, "field_name": None, "pandas_type": "unicode", "numpy_type": "object",
                            "metadata": {"encoding": "UTF-8"}}],
        "columns": [{"name": "task_index", "field_name": "task_index", "pandas_type": "int64",
                     "numpy_type": "int64", "metadata": None},
                    {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object",
                     "metadata": None}],
        "creator": {"library": "pyarrow", "version": pa.__version__},
        "pandas_version": "2.2.0",
    }
    pq.write_table(table.replace_schema_metadata({"pandas": json.dumps(pandas_metadata)}), path)


def write_lerobot(store, episodes: list, root: Path, progress: bool = True) -> dict:
    """Writes `episodes` of `store` as a LeRobotDataset v3.0 folder at `root` (made here)."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    from tqdm import tqdm

    fps = _fps(common_control_period_s(episodes))
    schema = pa.schema([(name, _arrow_type(pa, feature)) for name, feature in FEATURES.items()])
    root.mkdir()
    data_files = _DataFiles(root, schema)
    tasks: dict[str, int] = {}
    rows, moments, grey_levels, frames = [], {}, np.zeros(256, dtype=np.int64), 0
    try:
        for new_index, episode in enumerate(tqdm(episodes, desc=f"export {store.root}", disable=not progress)):
            arrays = store.read(episode)
            task = task_text(episode.metadata)
            columns = frame_columns(arrays, new_index, frames, tasks.setdefault(task, len(tasks)))
            images = arrays["image"]  # (T, 128, 128), as `store.read` checks.
            table = pa.table({IMAGE_KEY: pa.array([{"bytes": _png(frame), "path": None} for frame in images],
                                                  schema.field(IMAGE_KEY).type),
                              **{name: _column(pa, value, schema.field(name).type) for name, value in columns.items()}},
                             schema=schema)
            chunk_file = data_files.write(table)
            for name, value in columns.items():
                moments.setdefault(name, _Moments()).update(value)
            grey_levels += np.bincount(np.asarray(images).ravel(), minlength=256)
            rows.append(_episode_row(episode, new_index, task, chunk_file, frames, arrays))
            frames += episode.steps
    finally:
        data_files.close()
    edges = {name: moment.edges() for name, moment in moments.items()}
    histograms = {name: [np.zeros(HISTOGRAM_BINS) for _ in edges[name]] for name in moments}
    for row, episode in zip(rows, episodes):  # Quantiles: a second pass, over the small fields only.
        arrays = store.read(episode, [field for field in FIELDS if field != "image"])
        columns = frame_columns(arrays, row["episode_index"], row["dataset_from_index"], tasks[row["tasks"][0]])
        for name, value in columns.items():
            value = value.astype(np.float64).reshape(len(value), -1)
            for dimension, (histogram, bins) in enumerate(zip(histograms[name], edges[name])):
                histogram += np.histogram(value[:, dimension], bins=bins)[0]
    stats = {IMAGE_KEY: _image_stats(grey_levels, frames),
             **{name: _feature_stats(moments[name], histograms[name], edges[name]) for name in moments}}
    (root / "meta").mkdir()
    _write_tasks(pa, pq, tasks, root / "meta" / "tasks.parquet")
    _write_episodes(pa, pq, rows, root / EPISODES_PATH.format(chunk_index=0, file_index=0))
    info = {
        "codebase_version": CODEBASE_VERSION, "robot_type": ROBOT_TYPE,
        "total_episodes": len(rows), "total_frames": frames, "total_tasks": len(tasks),
        "chunks_size": CHUNKS_SIZE, "data_files_size_in_mb": DATA_FILE_MB, "video_files_size_in_mb": VIDEO_FILE_MB,
        "fps": fps, "splits": {"train": f"0:{len(rows)}"}, "data_path": DATA_PATH, "video_path": None,
        "features": FEATURES,
    }
    (root / "meta" / "info.json").write_text(json.dumps(info, indent=4) + "\n", encoding="utf-8")
    (root / "meta" / "stats.json").write_text(json.dumps(stats, indent=4) + "\n", encoding="utf-8")
    return {"episodes": len(rows), "frames": frames, "tasks": len(tasks), "fps": fps, "data_files": data_files.files,
            "codebase_version": CODEBASE_VERSION}
