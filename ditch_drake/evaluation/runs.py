"""The record of `ditch-drake experiment` runs in a results folder: each stage's wall time, so
that the results page can say how long the protocol took."""

import json
import os
from pathlib import Path

from ditch_drake.common.errors import ConfigError
from ditch_drake.common.files import atomic_write_text

RUNS_FILE = "experiment_runs.json"
"""In the results folder: one entry per `run_experiment` call, its stages' wall times (s)."""


def record_run(results_dir: str | os.PathLike, run: dict) -> Path:
    """Adds or updates `run` (matched by its "started_utc") in the results folder's RUNS_FILE, atomically."""
    path = Path(results_dir) / RUNS_FILE
    runs = read_runs(results_dir)
    runs = [entry for entry in runs if entry.get("started_utc") != run.get("started_utc")] + [run]
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(runs, indent=1) + "\n")
    return path


def read_runs(results_dir: str | os.PathLike) -> list[dict]:
    """The runs recorded in the results folder's RUNS_FILE ([] if none).

    Raises:
        ConfigError: the file is not a JSON list of objects.
    """
    path = Path(results_dir) / RUNS_FILE
    if not path.exists():
        return []
    try:
        runs = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ConfigError(f"{path}: not JSON ({error}); expected a list of experiment runs") from error
    if not isinstance(runs, list) or not all(isinstance(run, dict) for run in runs):
        raise ConfigError(f"{path}: expected a JSON list of experiment runs (objects)")
    return runs
