"""Training an ensemble (`ditch-drake train --ensemble K`): K clones, each by `train` on its own
bootstrap resample of the demonstrations, assembled into one ensemble file.

Files, for the output `OUT` (e.g. `ensemble.pt`):

- `OUT.members/bootstrap.json`: the resamples and the training settings, written first; a rerun
  with other settings or other demonstrations is refused rather than mixing two ensembles.
- `OUT.members/member_<k>.pt`: member k's checkpoint when its training finished (written by
  `train`, atomically), with its `.resume` file beside it while it trains.
- `OUT`: the ensemble (`ditch_drake.learning.ensemble`), written when every member has finished;
  then the members' folder is removed.

Interrupted (Ctrl-C, SIGTERM), the members that finished stay in the folder and the member in
training keeps its `.resume` file; the same command again skips the finished members and
continues the interrupted one from its last finished epoch.
"""

import dataclasses
import json
import os
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ditch_drake.common.errors import CheckpointError, ConfigError
from ditch_drake.common.files import atomic_output
from ditch_drake.common.progress import log_progress
from ditch_drake.learning.bootstrap import Bootstrap, bootstrap_demonstrations
from ditch_drake.learning.checkpoint import load_checkpoint
from ditch_drake.learning.config import TrainConfig
from ditch_drake.learning.data import ArraySet
from ditch_drake.learning.ensemble import EnsembleCheckpoint, save_ensemble
from ditch_drake.learning.train import _RESUMABLE_CHANGES, _config_dict, train

MEMBERS_SUFFIX = ".members"
MANIFEST = "bootstrap.json"


@dataclass
class EnsembleTrainResult:
    """What `train_ensemble` returns.

    Attributes:
        output_path: the ensemble file, or None when interrupted before every member finished.
        members_folder: where the members are kept until the ensemble is assembled.
        trained: the members trained (or continued) by this call.
        skipped: the members that had finished before it.
        best: per finished member, the validation record of its kept epoch ({} for a skipped one).
        interrupted: a Ctrl-C or SIGTERM ended it.
        exit_code: the shell's code of that stop (130, 143), else 0.
    """

    output_path: Path | None
    members_folder: Path
    trained: list[int] = field(default_factory=list)
    skipped: list[int] = field(default_factory=list)
    best: dict[int, dict] = field(default_factory=dict)
    interrupted: bool = False
    exit_code: int = 0


def members_folder(output_path: str | os.PathLike) -> Path:
    """Where the members of the ensemble for `output_path` wait to be assembled: `OUT.members`."""
    output_path = Path(output_path)
    return output_path.with_name(output_path.name + MEMBERS_SUFFIX)


def member_path(folder: Path, member: int) -> Path:
    """Member `member`'s checkpoint in the members' folder."""
    return folder / f"member_{member}.pt"


def _manifest(bootstrap: Bootstrap, config: TrainConfig) -> dict:
    settings = {key: value for key, value in _config_dict(config).items()
                if key not in _RESUMABLE_CHANGES and key != "seed"}
    # As it reads back from the file, to compare like with like.
    return json.loads(json.dumps({"bootstrap": bootstrap.to_dict(), "train_config": settings}))


def _check_manifest(folder: Path, manifest: dict) -> None:
    """Writes the manifest of a new folder, or checks the one there.

    Raises:
        ConfigError: the folder holds the members of another ensemble, naming what differs.
    """
    path = folder / MANIFEST
    if not path.exists():
        folder.mkdir(parents=True, exist_ok=True)
        with atomic_output(path) as file:
            file.write(json.dumps(manifest, indent=1).encode())
        return
    try:
        found = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise ConfigError(f"{path} is unreadable ({error}); expected the manifest of an ensemble in training "
                          "(remove the folder to start afresh)") from error
    differ = [key for key in ("seed", "demonstrations", "draws") if found.get("bootstrap", {}).get(key)
              != manifest["bootstrap"][key]]
    theirs, mine = found.get("train_config", {}), manifest["train_config"]
    differ += [f"train_config.{key}" for key in sorted(set(theirs) | set(mine)) if theirs.get(key) != mine.get(key)]
    if differ:
        raise ConfigError(f"{folder} holds the members of another ensemble ({', '.join(differ)} differ); expected "
                          "the same demonstrations, seed, member count and settings, or remove the folder")


def _finished(path: Path) -> bool:
    """Whether a member's training finished: its checkpoint is there and not an interrupted one."""
    if not path.exists():
        return False
    checkpoint = load_checkpoint(path, allow_untrained=True)
    return not checkpoint.metrics.get("interrupted", False)


def train_ensemble(
    samples_of: Callable[[np.ndarray], ArraySet],
    demonstrations: Sequence[str] | int,
    output_path: str | os.PathLike,
    config: TrainConfig | None = None,
    members: int = 5,
    progress: bool = True,
    interventions_of: Callable[[np.ndarray], np.ndarray] | None = None,
) -> EnsembleTrainResult:
    """Trains `members` clones on bootstrap resamples of the demonstrations and writes one ensemble.

    Member k draws its resample with `bootstrap_demonstrations(demonstrations, members, config.seed)`
    and trains with `train` under `config` with seed `config.seed + k`. The copies of a
    demonstration drawn more than once share its id, so `train`'s validation split holds out all
    of them or none.

    Args:
        samples_of: the training samples of the demonstrations at the given indices, in that order,
            an index that repeats giving its samples again, entry i with demo_id i
            (`ditch_drake.demos.training_set.training_set` of those episodes).
        demonstrations: their names (recorded in the file), or how many there are.
        output_path: the ensemble file to write (see the module docstring for the files beside it).
        config: the training settings of every member (default `TrainConfig()`).
        members: K >= 2.
        progress: print which member trains, and `train`'s own progress.
        interventions_of: the intervention flag of each of `samples_of`'s samples for the same
            indices (`train`'s `intervention`, which `config.intervention_weight` weighs); None: none.

    Raises:
        ConfigError: K < 2, or a members' folder of another ensemble.
        CheckpointError: `output_path` is a folder; a member's file that does not load.
    """
    config = config or TrainConfig()
    output_path = Path(output_path)
    if output_path.is_dir():
        raise CheckpointError(f"{output_path} is a folder; expected the path of a .pt file to write (--out)")
    bootstrap = bootstrap_demonstrations(demonstrations, members, config.seed)
    folder = members_folder(output_path)
    _check_manifest(folder, _manifest(bootstrap, config))
    result = EnsembleTrainResult(None, folder)
    for draw in bootstrap.draws:
        path = member_path(folder, draw.member)
        if _finished(path):
            log_progress(progress, f"ensemble member {draw.member + 1} of {members}: finished before, {path}")
            result.skipped.append(draw.member)
            continue
        log_progress(progress, f"ensemble member {draw.member + 1} of {members}: seed {draw.seed}, "
                               f"{len(draw.distinct())} distinct of {bootstrap.count} demonstrations")
        arrays = samples_of(draw.indices)
        arrays = dataclasses.replace(arrays, demo_id=draw.indices[arrays.demo_id])
        weighted = {} if interventions_of is None else {"intervention": interventions_of(draw.indices)}
        trained = train(arrays, dataclasses.replace(config, seed=draw.seed), progress, path, resume=True, **weighted)
        result.trained.append(draw.member)
        if trained.interrupted:
            result.interrupted, result.exit_code = True, trained.exit_code
            finished = len(result.skipped) + len(result.trained) - 1
            log_progress(progress, f"interrupted in member {draw.member + 1}: {finished} finished member(s) kept in "
                                   f"{folder}; the same command continues")
            return result
        result.best[draw.member] = dict(trained.checkpoint.metrics.get("best", {}))
    checkpoints = [load_checkpoint(member_path(folder, draw.member)) for draw in bootstrap.draws]
    result.output_path = save_ensemble(EnsembleCheckpoint(checkpoints, bootstrap.to_dict()), output_path)
    log_progress(progress, f"saved the ensemble of {members} members to {output_path}")
    shutil.rmtree(folder)
    return result
