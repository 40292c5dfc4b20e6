"""Ensembles of clones: one file for all members, and every member's logits in one forward pass.

An ensemble is K clones of the same network, each trained by `ditch_drake.learning.train` on its
own resample of the demonstrations (`ditch_drake.learning.bootstrap`: drawn with replacement,
whole demonstrations, not samples) with its own seed (`ditch_drake.learning.ensemble_training`). How
much the members disagree on a state is the uncertainty that `ditch_drake.learning.uncertainty`
measures.

The file is a `torch.save` of plain values, read with `weights_only=True` like a single
checkpoint:

| key | value |
| --- | --- |
| schema | "ditch_drake.policy_ensemble" |
| schema_version | 1 (`SCHEMA_VERSION`) |
| code_version | `ditch_drake.__version__` of the writer |
| members | K >= 2 payloads, each what `PolicyCheckpoint.to_payload` writes for one clone |
| bootstrap | `Bootstrap.to_dict()`: the seed, and each member's seed and drawn demonstrations |

The members must agree on everything that fixes what the inputs and outputs mean: the model
config (shapes, `canonical_side`), the weights' names and shapes, the action table, and the
input statistics' keys and lengths. Their input statistics' *values* differ by design: each
member standardizes its inputs with the mean and std of its own resample, as the clone it is
would on its own; `EnsembleNetwork` applies each member's.
"""

import os
import pickle
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

import ditch_drake
from ditch_drake.common.errors import CheckpointError, ConfigError
from ditch_drake.learning.bootstrap import MIN_MEMBERS
from ditch_drake.learning.checkpoint import SCHEMA as MEMBER_SCHEMA
from ditch_drake.learning.checkpoint import SCHEMA_VERSION as MEMBER_SCHEMA_VERSION
from ditch_drake.learning.checkpoint import (
    PolicyCheckpoint,
    checkpoint_from_payload,
    load_payload,
    save_payload,
    to_plain,
)
from ditch_drake.learning.ensemble_network import DEFAULT_PRECISION, EnsembleNetwork
from ditch_drake.learning.model import set_torch_threads

SCHEMA = "ditch_drake.policy_ensemble"
SCHEMA_VERSION = 1


@dataclass
class EnsembleCheckpoint:
    """An ensemble as stored (see the module docstring).

    Attributes:
        members: K >= 2 clones that agree on their shapes and action table.
        bootstrap: the resamples they were trained on (plain values, `Bootstrap.to_dict`), or {}
            for an ensemble assembled from clones trained otherwise.
        code_version: `ditch_drake.__version__` of the writer.
        path: the file it was loaded from or last saved to, if any.
    """

    members: list[PolicyCheckpoint]
    bootstrap: dict = field(default_factory=dict)
    code_version: str = ditch_drake.__version__
    path: Path | None = None

    def __post_init__(self):
        check_members(self.members, str(self.path or "ensemble"))

    @property
    def size(self) -> int:
        """K, the number of members."""
        return len(self.members)

    @property
    def model_config(self):
        """The members' shared `ModelConfig`."""
        return self.members[0].model_config

    @property
    def action_commands(self) -> np.ndarray:
        """(num_labels, 2) [v m/s, w rad/s] per label, the members' shared table."""
        return np.asarray(self.members[0].action_commands, dtype=float)

    def build_network(self, precision: str = DEFAULT_PRECISION) -> EnsembleNetwork:
        """All members as one `EnsembleNetwork` in `precision`, in eval mode, on the CPU.

        Raises:
            ConfigError: a precision that is unknown or does not run natively here
                (`ditch_drake.learning.ensemble_network.check_precision`).
        """
        return EnsembleNetwork([member.build_model() for member in self.members], precision)

    def to_payload(self) -> dict:
        """The dict that `torch.save` writes (tensors and plain values only)."""
        return {
            "schema": SCHEMA,
            "schema_version": SCHEMA_VERSION,
            "code_version": str(self.code_version),
            "members": [member.to_payload() for member in self.members],
            "bootstrap": to_plain(self.bootstrap, "bootstrap"),
        }


def check_members(members: Sequence[PolicyCheckpoint], where: str) -> None:
    """Checks that `members` can run as one ensemble (see the module docstring).

    Raises:
        ConfigError: fewer than two.
        CheckpointError: a member differing from member 0, naming `where`, the member and the key.
    """
    if len(members) < MIN_MEMBERS:
        raise ConfigError(f"{where} has {len(members)} member(s); expected at least {MIN_MEMBERS} (an ensemble's "
                          "uncertainty is its members' disagreement)")
    first = members[0]
    reference = _signature(first)
    for index, member in enumerate(members[1:], start=1):
        for key, value in _signature(member).items():
            if value != reference[key]:
                raise CheckpointError(f"{where}: member {index}'s {key} is {_short(value)}, member 0's "
                                      f"{_short(reference[key])}; expected members of one shape and action table")


def _signature(member: PolicyCheckpoint) -> dict:
    """What members must share, one entry per key an error names."""
    values = {f"model_config.{key}": value for key, value in member.model_config.to_dict().items()}
    values["action_commands"] = np.asarray(member.action_commands, dtype=float).round(12).tolist()
    values.update({f"input_stats.{key} length": len(value) for key, value in member.input_stats.to_dict().items()})
    values["state_dict keys"] = sorted(member.state_dict)
    values.update({f"state_dict.{name} shape": tuple(tensor.shape) for name, tensor in member.state_dict.items()})
    return values


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 120 else text[:117] + "..."


def save_ensemble(ensemble: EnsembleCheckpoint, path: str | os.PathLike) -> Path:
    """Writes `ensemble` to `path` atomically (`save_payload`) and records the path on it."""
    ensemble.path = save_payload(ensemble.to_payload(), path)
    return ensemble.path


def is_ensemble_checkpoint(path: str | os.PathLike) -> bool:
    """Whether the file at `path` says it is an ensemble (its schema), without reading its weights.

    False for anything else, a missing or unreadable file included: the loader of the schema it
    has (or of a single checkpoint) then says what is wrong with it.
    """
    path = Path(path)
    if not path.is_file():
        return False
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except (RuntimeError, OSError, EOFError, ValueError, pickle.UnpicklingError):  # Its own loader names the fault.
        return False
    return isinstance(payload, dict) and payload.get("schema") == SCHEMA


def load_ensemble(path: str | os.PathLike, allow_other_action_table: bool = False) -> EnsembleCheckpoint:
    """Reads and checks an ensemble written by `save_ensemble`.

    Each member passes the checks of `load_checkpoint` (`checkpoint_from_payload`; an untrained
    member is refused), and the members must agree (`check_members`).

    Raises:
        CheckpointNotFoundError: no file at `path`, or a folder.
        CheckpointError: a corrupt, truncated or foreign file, a newer schema, a member that does
            not load (naming the file and the member) or members that differ (naming the key).
        ConfigError: fewer than two members.
    """
    path = Path(path)
    payload = load_payload(path, SCHEMA, SCHEMA_VERSION)
    members = payload.get("members")
    if not isinstance(members, list):
        raise CheckpointError(f"{path}: 'members' is a {type(members).__name__}; expected a list of "
                              f"{MEMBER_SCHEMA} payloads")
    bootstrap = payload.get("bootstrap", {})
    if not isinstance(bootstrap, dict):
        raise CheckpointError(f"{path}: 'bootstrap' is a {type(bootstrap).__name__}; expected a dict")
    checkpoints = []
    for index, member in enumerate(members):
        where = f"{path} member {index}"
        if not isinstance(member, dict) or member.get("schema") != MEMBER_SCHEMA:
            found = member.get("schema") if isinstance(member, dict) else type(member).__name__
            raise CheckpointError(f"{where} is {found!r}; expected a {MEMBER_SCHEMA} payload")
        version = member.get("schema_version")
        if not isinstance(version, int) or isinstance(version, bool) or not 1 <= version <= MEMBER_SCHEMA_VERSION:
            raise CheckpointError(f"{where} has schema_version {version!r}; expected 1..{MEMBER_SCHEMA_VERSION}")
        checkpoint = checkpoint_from_payload(member, where, allow_other_action_table)
        checkpoint.path = path
        checkpoints.append(checkpoint)
    return EnsembleCheckpoint(checkpoints, bootstrap, str(payload.get("code_version", "")), path)


class EnsembleInference:
    """An ensemble's members run together in PyTorch (`EnsembleNetwork`, eval mode, under
    `torch.inference_mode`): what a policy block asks of it.

    Attributes:
        runtime: "torch".
        members: K.
        model_config: the members' shared `ModelConfig`.
        action_commands: (num_labels, 2) [v m/s, w rad/s] per label.
        precision: what the network runs in (`ditch_drake.learning.ensemble_network.PRECISIONS`).
    """

    runtime = "torch"

    def __init__(self, ensemble: EnsembleCheckpoint, num_threads: int | None = 1,
                 precision: str = DEFAULT_PRECISION):
        """Builds the stacked network.

        Args:
            ensemble: a loaded ensemble (`load_ensemble`).
            num_threads: torch's intra-op threads, set here for the whole process
                (`torch.set_num_threads` is process-wide); None leaves torch's setting.
            precision: "float32", or "bfloat16_image" (the image branch in bfloat16, on a
                CPU that runs it natively: `EnsembleNetwork`).

        Raises:
            ValueError: a thread count < 1.
            ConfigError: a precision that is unknown or does not run natively here.
        """
        set_torch_threads(num_threads)
        self.members = ensemble.size
        self.model_config = ensemble.model_config
        self.action_commands = ensemble.action_commands
        self.precision = precision
        self._network = ensemble.build_network(precision)

    def member_logits(self, image: np.ndarray, imu: np.ndarray, distance: np.ndarray,
                      bearing: np.ndarray) -> np.ndarray:
        """(K, batch, num_labels) float32 logits of raw float32 inputs (batch, ...), one pass."""
        inputs = [torch.as_tensor(np.asarray(value, dtype=np.float32)) for value in (image, imu, distance, bearing)]
        with torch.inference_mode():
            return self._network(*inputs).numpy()

    def member_probabilities(self, image: np.ndarray, imu: np.ndarray, distance: np.ndarray,
                             bearing: np.ndarray) -> np.ndarray:
        """(K, batch, num_labels) float64 softmax probabilities of each member."""
        logits = torch.from_numpy(self.member_logits(image, imu, distance, bearing)).double()
        return torch.softmax(logits, dim=-1).numpy()
