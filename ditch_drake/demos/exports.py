"""Exports of a dataset folder to other learning libraries' layouts: `ditch-drake dataset export`.

One registry entry a format ("module:function" of its writer, imported when used, and the
libraries it needs), so a format is added in one place. Every writer streams the store episode
by episode (no more than one episode's arrays in memory) into a hidden temporary sibling of
the target, renamed into place at the end: an interrupted export leaves nothing at the target,
and an existing target is never overwritten. The layouts and their units are on
docs/concepts/datasets.md.

The mapping shared by the formats lives here: the policy's low-dimensional inputs as one
`state` vector and the recorded label as its [v, w] command.
"""

import importlib
import os
import secrets
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ditch_drake.common.errors import ConfigError, DatasetError
from ditch_drake.spec import actions
from ditch_drake.spec.observation_layout import STACK_DEPTH


@dataclass(frozen=True)
class ExportFormat:
    """A layout `export_dataset` writes."""

    writer: str  # "module:function", called as function(store, episodes, temporary_out, progress) -> dict
    modules: tuple[str, ...]  # the libraries it needs (the `export` extra)
    makes: str  # "a folder" or "a file", for messages


EXPORT_FORMATS = {
    "lerobot": ExportFormat("ditch_drake.demos.lerobot_export:write_lerobot", ("pyarrow",), "a folder"),
    "robomimic": ExportFormat("ditch_drake.demos.robomimic_export:write_robomimic", ("h5py",), "a file"),
}
INSTALL_HINT = "pip install -e '.[export]'"

# The store's fields that make the policy's low-dimensional input, in `state` order (the layout
# of `ditch_drake.learning`'s inputs beside the image: see docs/concepts/observation.md).
STATE_FIELDS = ("imu_stack", "distance_stack", "bearing_stack")
_AGES = ["t"] + [f"t-{age}" for age in range(1, STACK_DEPTH)]
STATE_NAMES = ([f"{angle}_{age}" for age in _AGES for angle in ("roll", "pitch")]
               + [f"distance_{age}" for age in _AGES] + [f"bearing_{age}" for age in _AGES])
STATE_UNITS = "rad (roll, pitch), m (distance), rad (bearing, positive left); newest first"
ACTION_NAMES = ["v", "w"]
ACTION_UNITS = "m/s, rad/s"


def policy_state(arrays: dict[str, np.ndarray]) -> np.ndarray:
    """(T, 16) float32: imu_stack (8), distance_stack (4), bearing_stack (4), side by side."""
    return np.concatenate([np.asarray(arrays[name], dtype=np.float32) for name in STATE_FIELDS], axis=1)


def label_commands(labels: np.ndarray) -> np.ndarray:
    """(T, 2) float64: the [v m/s, w rad/s] of each label, from the action table."""
    return actions.COMMANDS[np.asarray(labels, dtype=np.int64)]


def task_text(metadata: dict) -> str:
    """A task in words, one for each environment and task: LeRobot's `task` string."""
    environment = metadata.get("environment", "?")
    task = metadata.get("task") or {}
    start, goal = task.get("start"), task.get("goal")
    if start and goal:
        return (f"cross the ditch {environment} from ({start[0]:g}, {start[1]:g}) to ({goal[0]:g}, {goal[1]:g})")
    return f"cross the ditch {environment}: {task.get('name', '?')}"


def driver_of(metadata: dict) -> str:
    """Who drove: the expert, a person, or a learner that the expert labelled (DAgger)."""
    return metadata.get("driver") or "expert"


def control_period_s(episodes: list) -> float:
    """The episodes' common control period (s).

    Raises:
        DatasetError: an episode without one, or episodes of different periods (an export
            has one frame rate).
    """
    periods = {}
    for episode in episodes:
        period = episode.metadata.get("control_period_s")
        if not isinstance(period, (int, float)) or isinstance(period, bool) or not period > 0:
            raise DatasetError(f"{episode.path}/episode.json: control_period_s is {period!r}; expected the "
                               "control period in s, as `collect` records it")
        periods.setdefault(float(period), episode.name)
    if len(periods) > 1:
        raise DatasetError(f"episodes of different control periods ({periods}); an export has one frame rate: "
                           "export them from separate dataset folders")
    return next(iter(periods))


def require_modules(names: tuple[str, ...], format: str):
    """Imports the libraries a format needs.

    Raises:
        ConfigError: one is missing, naming the extra that installs it.
    """
    missing = []
    for name in names:
        try:
            importlib.import_module(name)
        except ImportError:
            missing.append(name)
    if missing:
        raise ConfigError(f"the {format} export needs {', '.join(missing)}: {INSTALL_HINT}")


def _load_writer(reference: str):
    module, _, attribute = reference.partition(":")
    return getattr(importlib.import_module(module), attribute)


def temporary_sibling(out: Path) -> Path:
    """A hidden name beside `out` for the export in progress (readers skip dotfiles)."""
    return out.with_name(f".{out.name}.{os.getpid()}.{secrets.token_hex(6)}.tmp")


def _move_into_place(temporary: Path, out: Path) -> None:
    """Renames the finished export to `out`, never replacing what appeared there meanwhile."""
    try:
        if temporary.is_dir():
            os.rename(temporary, out)  # Fails if `out` became a file or a non-empty folder.
        else:
            os.link(temporary, out)  # Fails, rather than replacing, if `out` appeared.
            os.unlink(temporary)
    except OSError as error:
        if out.exists():
            raise ConfigError(f"export target {out} appeared while exporting; nothing was overwritten") from error
        raise


def export_dataset(path: str | os.PathLike, format: str, out: str | os.PathLike, progress: bool = True) -> dict:
    """Writes the dataset folder at `path` in `format`'s layout at `out` (which must not exist).

    Args:
        path: a dataset folder (`DatasetStore`).
        format: a key of `EXPORT_FORMATS` ("lerobot": a LeRobotDataset v3 folder; "robomimic":
            one HDF5 file).
        out: what to write; its parent folders are made.
        progress: a progress bar over the episodes.

    Returns:
        The writer's summary: {"format", "source", "out", "episodes", "frames", ...}.

    Raises:
        ConfigError: an unknown format, `out` exists, or the format's library is missing.
        DatasetError: `path` is not a dataset folder, holds no episode, or a bad episode.
    """
    from ditch_drake.demos.store import DatasetStore

    if format not in EXPORT_FORMATS:
        raise ConfigError(f"export format {format!r} is unknown; expected one of {sorted(EXPORT_FORMATS)}")
    spec = EXPORT_FORMATS[format]
    out = Path(out)
    if out.exists() or out.is_symlink():
        raise ConfigError(f"export target {out} exists; expected a new path ({spec.makes}): nothing is overwritten")
    store = DatasetStore.open(path)
    episodes = store.episodes()
    if not episodes:
        raise DatasetError(f"{path} holds no complete episode; nothing to export")
    require_modules(spec.modules, format)
    writer = _load_writer(spec.writer)
    out.parent.mkdir(parents=True, exist_ok=True)
    temporary = temporary_sibling(out)
    try:
        summary = writer(store, episodes, temporary, progress)
        _move_into_place(temporary, out)
    finally:
        if temporary.is_dir():
            shutil.rmtree(temporary, ignore_errors=True)
        elif temporary.exists():
            temporary.unlink()
    return {"format": format, "source": str(path), "out": str(out), **summary}
