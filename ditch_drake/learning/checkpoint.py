"""Policy checkpoints: the trained weights and everything inference needs, in one file.

A checkpoint is a `torch.save` of a dict of tensors and plain Python values (no pickled
classes or code), read back with `torch.load(weights_only=True)`:

| key | value |
| --- | --- |
| schema | "ditch_drake.policy_checkpoint" |
| schema_version | 1 (`SCHEMA_VERSION`) |
| code_version | `ditch_drake.__version__` of the writer |
| model_config | `ModelConfig.to_dict()` |
| state_dict | the network's weights and BatchNorm statistics (tensors) |
| action_commands | 17 x [v m/s, w rad/s]: `actions.COMMANDS` when trained, label = row |
| input_stats | `InputStats.to_dict()`: mean and std of the scalar inputs (training split) |
| training | summary of the data: per-label counts, demonstrations used, the `TrainConfig` |
| metrics | validation metrics of the kept weights, the per-epoch history, ... |

Files are written atomically (a temporary file in the same folder, flushed to disk, then
`os.replace`), so a reader never sees half a file; a corrupt, truncated or foreign file
raises `CheckpointError` naming the file and what was expected, a missing path or a folder
`CheckpointNotFoundError`. A checkpoint whose training finished no epoch (`metrics` says
`epochs_run` 0 or `best_epoch` -1: untrained weights) is refused unless asked for.
"""

import hashlib
import os
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import numpy as np
import torch

import ditch_drake
from ditch_drake.common.errors import CheckpointError, CheckpointNotFoundError, ConfigError
from ditch_drake.common.files import atomic_output
from ditch_drake.learning.data import InputStats
from ditch_drake.learning.model import FourInputClassifier, ModelConfig
from ditch_drake.spec import actions

SCHEMA = "ditch_drake.policy_checkpoint"
SCHEMA_VERSION = 1
# The trained policies that ship inside the package (`ditch_drake/models/<name>.pt`), made by
# the commands in docs/results/shipped_models.md: per environment, `<env>` is the best measured policy (40
# expert demonstrations plus one DAgger round), `<env>_bc40` the paper's method alone (the 40
# demonstrations, trained on this 2-core CPU in the 15-minute budget). `generalist` was trained
# over the procedural benchmark's train split and chosen on its val split (docs/results/benchmark.md);
# `generalist_k5` is an ensemble of five clones of a rerun of its recipe, the `shared` controller's
# policy (docs/results/shared_control_generalist.md).
SHIPPED_MODELS_DIR = Path(__file__).resolve().parent.parent / "models"
ENVIRONMENT_MODELS = ("crater", "wide", "narrow", "sine")
GENERALIST_MODEL = "generalist"
GENERALIST_ENSEMBLE = "generalist_k5"
SHIPPED_MODELS = (*ENVIRONMENT_MODELS, *(f"{env}_bc40" for env in ENVIRONMENT_MODELS), GENERALIST_MODEL,
                  GENERALIST_ENSEMBLE)


def environment_model(environment: str, environments_file: str = "") -> str:
    """The shipped model of an environment: the learned policy's default checkpoint there.

    A variant of an environment (`Environment.based_on`, e.g. "wide_walled" of "wide") drives
    the model of the environment it is based on.

    Raises:
        ConfigError: no shipped model is named after `environment` or what it is based on.
    """
    from ditch_drake.world.environments import get_environment

    seen = [environment]
    while environment not in ENVIRONMENT_MODELS:
        try:
            based_on = get_environment(environment, environments_file or None).based_on
        except ConfigError:
            based_on = ""
        if not based_on or based_on in seen:
            raise ConfigError(f"environment {seen[0]!r} has no shipped model; name a checkpoint (a .pt file or one "
                              f"of {list(SHIPPED_MODELS)})")
        environment = based_on
        seen.append(environment)
    return environment


# What a checkpoint argument may be, for error messages.
EXPECTED_CHECKPOINT = f"a .pt file written by `ditch-drake train`, or a shipped model name: {list(SHIPPED_MODELS)}"


@dataclass
class PolicyCheckpoint:
    """A trained policy as stored (see the module docstring for the file layout).

    Attributes:
        model_config: the network's shape.
        state_dict: weights and BatchNorm statistics.
        action_commands: (num_labels, 2) [v m/s, w rad/s] of each label.
        input_stats: standardization of the scalar inputs.
        training: data summary (plain values).
        metrics: validation metrics and history (plain values).
        code_version: `ditch_drake.__version__` of the writer.
        path: the file it was loaded from or last saved to, if any.
    """

    model_config: ModelConfig
    state_dict: dict[str, torch.Tensor]
    action_commands: np.ndarray = field(default_factory=lambda: actions.COMMANDS.copy())
    input_stats: InputStats = field(default_factory=InputStats.identity)
    training: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)
    code_version: str = ditch_drake.__version__
    path: Path | None = None

    def summary(self) -> dict[str, str]:
        """What it was trained on and how it validated, as printable columns (`checkpoint-info`,
        the results page's Models table)."""
        training, metrics = self.training, self.metrics
        best = metrics.get("best", {})
        train_config = training.get("train_config", {})
        # Checkpoints from before `TrainConfig.precision` were all trained in fp32.
        bf16 = " bf16" if train_config.get("precision") == "bf16" else ""
        return {
            "demos_train/val": f"{len(training.get('train_demo_ids', []))}/{len(training.get('val_demo_ids', []))}",
            "samples_real/smote/val": f"{training.get('num_train_samples')}/{training.get('num_synthetic_samples')}/"
                                      f"{training.get('num_val_samples')}",
            "epochs": str(metrics.get("epochs_run")),
            "best_epoch": str(metrics.get("best_epoch")),
            f"val_ordinal_pm{metrics.get('ordinal_tolerance', 1)}": f"{best.get('val_ordinal_accuracy', float('nan')):.3f}",
            "val_exact": f"{best.get('val_exact_accuracy', float('nan')):.3f}",
            "training_s": f"{metrics.get('training_seconds', float('nan')):.0f}",
            "device": train_config.get("device", "?") + bf16,
        }

    def build_model(self) -> FourInputClassifier:
        """A fresh network with these weights and input stats, in eval mode, on the CPU."""
        model = FourInputClassifier(self.model_config)
        model.load_state_dict(self.state_dict)
        model.set_input_stats(self.input_stats.to_dict())
        return model.eval()

    def to_payload(self) -> dict:
        """The dict that `torch.save` writes (tensors and plain values only).

        Raises:
            TypeError: `training` or `metrics` holds something other than plain values.
        """
        return {
            "schema": SCHEMA,
            "schema_version": SCHEMA_VERSION,
            "code_version": str(self.code_version),
            "model_config": self.model_config.to_dict(),
            "state_dict": {name: value.detach().cpu().clone() for name, value in self.state_dict.items()},
            "action_commands": np.asarray(self.action_commands, dtype=float).tolist(),
            "input_stats": self.input_stats.to_dict(),
            "training": to_plain(self.training, "training"),
            "metrics": to_plain(self.metrics, "metrics"),
        }


def make_checkpoint(
    model: FourInputClassifier,
    input_stats: InputStats | None = None,
    training: dict | None = None,
    metrics: dict | None = None,
) -> PolicyCheckpoint:
    """A checkpoint of `model`'s current weights (copied) with the current action table.

    `training` and `metrics` are stored as plain values (numpy arrays become lists), as
    they will read back from the file.

    Raises:
        TypeError: `training` or `metrics` holds something a checkpoint cannot.
    """
    return PolicyCheckpoint(
        model_config=ModelConfig.from_dict(model.config.to_dict()),
        state_dict={name: value.detach().cpu().clone() for name, value in model.state_dict().items()},
        input_stats=input_stats or InputStats.identity(),
        training=to_plain(dict(training or {}), "training"),
        metrics=to_plain(dict(metrics or {}), "metrics"),
    )


def to_plain(value, where: str = "value"):
    """`value` with numpy scalars and arrays turned into Python numbers and lists.

    Raises:
        TypeError: a type that `torch.load(weights_only=True)` would refuse, naming where.
    """
    if isinstance(value, (bool, int, float, str)) or value is None:
        return value
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, torch.Tensor):
        return value.detach().cpu()
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (list, tuple)):
        return [to_plain(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, dict):
        out = {}
        for key, v in value.items():
            if not isinstance(key, (str, int)):
                raise TypeError(f"{where} has a key {key!r} of type {type(key).__name__}; expected str or int")
            out[key] = to_plain(v, f"{where}[{key!r}]")
        return out
    raise TypeError(f"{where} is a {type(value).__name__}; a checkpoint holds only tensors and plain values")


def save_payload(payload: dict, path: str | os.PathLike) -> Path:
    """`torch.save(payload)` to `path` atomically: a temporary file in the same folder, then `os.replace`.

    The file is fsynced before the rename and the folder after it, so a crash or a power
    cut leaves either the old file or the whole new one at `path`, never a partial one.
    """
    with atomic_output(path) as file:
        torch.save(payload, file)
    return Path(path)


def load_payload(path: str | os.PathLike, schema: str, version: int) -> dict:
    """The dict saved at `path`, checked to be of `schema` at a version <= `version`.

    Raises:
        CheckpointNotFoundError: no file at `path` (nothing, or a folder).
        CheckpointError: not a torch file of plain values (corrupt, truncated, pickled
            code), not a dict, another schema, or a newer schema version.
    """
    path = Path(path)
    expected = f"a torch.save file of {schema} (schema_version <= {version}, tensors and plain values)"
    if path.is_dir():
        raise CheckpointNotFoundError(f"{path} is a folder, not a file; expected {expected}")
    if not path.is_file():
        raise CheckpointNotFoundError(f"{path}: no such file; expected {expected}")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises RuntimeError, UnpicklingError, EOFError, ... for bad files.
        message = str(error)
        if "Unsupported global" in message:
            reason = "it holds pickled Python objects, which a checkpoint must not"
        elif "zip archive" in message or "PytorchStreamReader" in message or isinstance(error, EOFError):
            reason = "it is truncated or corrupt"
        else:
            reason = "it is corrupt or not a torch.save file"
        raise CheckpointError(
            f"{path} is not a readable checkpoint: {reason} ({type(error).__name__}); expected {expected}"
        ) from error
    if not isinstance(payload, dict) or "schema" not in payload:
        raise CheckpointError(f"{path} holds a {type(payload).__name__} without a 'schema' key; expected {expected}")
    if payload["schema"] != schema:
        raise CheckpointError(f"{path} has schema {payload['schema']!r}; expected {expected}")
    found = payload.get("schema_version")
    if not isinstance(found, int) or isinstance(found, bool) or found < 1:
        raise CheckpointError(f"{path} has schema_version {found!r}; expected an integer in 1..{version}")
    if found > version:
        raise CheckpointError(
            f"{path} has schema_version {found}, written by a newer ditch_drake "
            f"({payload.get('code_version')!r}); this code ({ditch_drake.__version__}) reads up to {version}"
        )
    return payload


def save_checkpoint(checkpoint: PolicyCheckpoint, path: str | os.PathLike) -> Path:
    """Writes `checkpoint` to `path` atomically and records the path on it."""
    checkpoint.path = save_payload(checkpoint.to_payload(), path)
    return checkpoint.path


def _require(payload: dict, key: str, kind: type | tuple[type, ...], path: Path):
    if key not in payload:
        raise CheckpointError(f"{path} lacks {key!r}; expected a {SCHEMA} v{SCHEMA_VERSION} checkpoint")
    if not isinstance(payload[key], kind):
        raise CheckpointError(f"{path}: {key!r} is a {type(payload[key]).__name__}; expected {kind}")
    return payload[key]


def resolve_checkpoint_path(name_or_path: str | os.PathLike) -> Path:
    """The file of a shipped model's name (`SHIPPED_MODELS`), or `name_or_path` as a path.

    Raises:
        CheckpointNotFoundError: neither a shipped model nor an existing file (or a
            folder, said so), naming both options.
    """
    text = str(name_or_path)
    if text in SHIPPED_MODELS:
        path = SHIPPED_MODELS_DIR / f"{text}.pt"
        if not path.is_file():
            raise CheckpointNotFoundError(f"shipped model {text!r} is missing from the package ({path})")
        return path
    path = Path(text)
    if path.is_dir():
        raise CheckpointNotFoundError(f"checkpoint {text!r} is a folder, not a file; expected {EXPECTED_CHECKPOINT}")
    if not path.is_file():
        raise CheckpointNotFoundError(
            f"checkpoint {text!r}: no such file, and not a shipped model; expected {EXPECTED_CHECKPOINT}"
        )
    return path


def checkpoint_digest(checkpoint: str) -> str:
    """First 16 hex digits of the SHA-256 of a checkpoint file, by shipped name or path ("" for
    none): evaluation records and DAgger demonstrations name the file they used by it.

    Cached per file version (path, size, modification time): a checkpoint retrained at the
    same path in the same process gets its new digest.
    """
    if not checkpoint:
        return ""
    path = resolve_checkpoint_path(checkpoint).resolve()
    status = path.stat()
    return _file_digest(path, status.st_size, status.st_mtime_ns)


@cache
def _file_digest(path: Path, size: int, mtime_ns: int) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


def load_checkpoint(
    path: str | os.PathLike, allow_other_action_table: bool = False, allow_untrained: bool = False
) -> PolicyCheckpoint:
    """Reads and checks a checkpoint written by `save_checkpoint`.

    The weights are checked against the stored model config (by building the network),
    so a file that loads here also runs. A checkpoint trained with an action table other
    than the current `actions.COMMANDS` would turn its labels into other commands than
    the demonstrations meant, so it is refused unless `allow_other_action_table`; then the
    checkpoint's own table is what it returns. One whose metrics record that no training
    epoch finished (`epochs_run` 0 or `best_epoch` < 0, as an older `train` wrote when
    interrupted in its first epoch) holds the initial random weights and is refused unless
    `allow_untrained`; metrics without these keys (a checkpoint made outside `train`) say
    nothing either way and pass.

    Raises:
        CheckpointNotFoundError: no file at `path`, or a folder (also a FileNotFoundError).
        CheckpointError: naming the file and what was expected, for a corrupt, truncated
            or foreign file, a newer schema, contents that do not fit together, or
            untrained weights.
    """
    path = Path(path)
    return checkpoint_from_payload(load_payload(path, SCHEMA, SCHEMA_VERSION), path, allow_other_action_table,
                                   allow_untrained)


def checkpoint_from_payload(
    payload: dict, path: str | os.PathLike, allow_other_action_table: bool = False, allow_untrained: bool = False
) -> PolicyCheckpoint:
    """The checks of `load_checkpoint` on a payload already read (of `SCHEMA`, as `load_payload`
    checks): an ensemble file holds its members' payloads (`ditch_drake.learning.ensemble`).
    `path` names it in the messages ("ensemble.pt member 2") and becomes the checkpoint's `path`.

    Raises:
        CheckpointError: as `load_checkpoint`.
    """
    path = Path(path)
    try:
        model_config = ModelConfig.from_dict(_require(payload, "model_config", dict, path))
        model_config.image_feature_size()
    except (TypeError, ValueError) as error:
        raise CheckpointError(f"{path}: bad model_config ({error})") from error
    state_dict = _require(payload, "state_dict", dict, path)
    if not all(isinstance(v, torch.Tensor) for v in state_dict.values()):
        raise CheckpointError(f"{path}: 'state_dict' must map names to tensors")
    try:
        commands = np.asarray(_require(payload, "action_commands", list, path), dtype=float)
    except ValueError as error:
        raise CheckpointError(f"{path}: 'action_commands' is not a numeric table ({error})") from error
    if commands.shape != (model_config.num_labels, 2) or not np.all(np.isfinite(commands)):
        raise CheckpointError(
            f"{path}: 'action_commands' has shape {commands.shape}; expected ({model_config.num_labels}, 2) finite "
            "[v m/s, w rad/s] rows"
        )
    if not allow_other_action_table and (
            commands.shape != actions.COMMANDS.shape or not np.allclose(commands, actions.COMMANDS)):
        raise CheckpointError(
            f"{path} was trained with another action table {commands.tolist()}; expected "
            f"ditch_drake.spec.actions.COMMANDS {actions.COMMANDS.tolist()} (allow_other_action_table=True uses its own)")
    try:
        input_stats = InputStats.from_dict(_require(payload, "input_stats", dict, path))
    except ValueError as error:
        raise CheckpointError(f"{path}: bad input_stats ({error})") from error
    if not all(np.all(np.isfinite(v)) for v in vars(input_stats).values()) or not all(
        np.all(getattr(input_stats, f"{name}_std") > 0) for name in ("imu", "distance", "bearing")
    ):
        raise CheckpointError(f"{path}: input_stats must be finite with positive stds")
    checkpoint = PolicyCheckpoint(
        model_config=model_config,
        state_dict=state_dict,
        action_commands=commands,
        input_stats=input_stats,
        training=_require(payload, "training", dict, path),
        metrics=_require(payload, "metrics", dict, path),
        code_version=str(_require(payload, "code_version", str, path)),
        path=path,
    )
    try:
        model = checkpoint.build_model()
    except (RuntimeError, ValueError) as error:
        reason = " ".join(str(error).split())
        raise CheckpointError(f"{path}: the weights do not fit the stored model_config ({reason})") from error
    if not all(bool(torch.isfinite(v).all()) for v in model.state_dict().values() if v.is_floating_point()):
        raise CheckpointError(f"{path}: the weights hold non-finite values")
    if not allow_untrained and is_untrained(checkpoint.metrics):
        raise CheckpointError(
            f"{path} holds untrained weights: its training finished no epoch (epochs_run "
            f"{checkpoint.metrics.get('epochs_run')!r}, best_epoch {checkpoint.metrics.get('best_epoch')!r}); expected "
            "a checkpoint with at least one finished epoch (allow_untrained=True loads it anyway)"
        )
    return checkpoint


def is_untrained(metrics: dict) -> bool:
    """Whether a checkpoint's metrics record that its training finished no epoch."""
    epochs_run, best_epoch = metrics.get("epochs_run"), metrics.get("best_epoch")
    return (isinstance(epochs_run, int) and epochs_run < 1) or (isinstance(best_epoch, int) and best_epoch < 0)
