"""How a policy's network runs: its inference runtimes, one registry.

A runtime turns a checkpoint into an inference object: its model config, its action table
and one method, `logits(image, imu, distance, bearing)`, from a batch of raw float32 inputs
(the layouts of `ditch_drake.learning.onnx_policy`) to the (batch, num_labels) logits.
Everything around it (the softmax, the left-right mirror of a canonical-side model, the
argmax, the command) is the `LearnedPolicy` block's, the same for every runtime.

An ensemble file (`ditch_drake.learning.ensemble`, `is_ensemble_checkpoint`) gives an
`EnsembleInference` instead: `members` K and `member_logits(...)`, every member's
(K, batch, num_labels) logits in one forward pass. It runs on torch only for now; the policy
block averages the members' probabilities and measures their uncertainty.

| runtime | a .pt checkpoint (or a shipped name) | a .onnx file | an ensemble file |
| --- | --- | --- | --- |
| torch | the network in PyTorch | refused: it runs only on onnxruntime | all members in one `EnsembleNetwork` |
| onnxruntime | exported in memory (`export_onnx`), run by ONNX Runtime | run by ONNX Runtime, with the action table and model config of its metadata | refused (`ConfigError`) |

onnxruntime needs the onnx extra (`pip install -e '.[onnx]'`); asked for without it, it
is refused with a `ConfigError` that says so.
"""

import importlib.util
import os
from collections.abc import Callable
from pathlib import Path
from typing import Protocol

import numpy as np
import torch

from ditch_drake.common.errors import CheckpointError, ConfigError
from ditch_drake.learning.checkpoint import PolicyCheckpoint, load_checkpoint, resolve_checkpoint_path
from ditch_drake.learning.config import ModelConfig
from ditch_drake.learning.ensemble import EnsembleInference, is_ensemble_checkpoint, load_ensemble
from ditch_drake.learning.ensemble_network import DEFAULT_PRECISION
from ditch_drake.learning.ensemble_network import check_precision as check_network_precision
from ditch_drake.learning.model import set_torch_threads
from ditch_drake.learning.onnx_policy import (
    INPUT_NAMES,
    INSTALL_HINT,
    OUTPUT_NAME,
    export_onnx,
    file_sha256,
    is_onnx_path,
    onnxruntime_session,
    read_onnx_policy,
)


class PolicyInference(Protocol):
    """A policy's network in one runtime (the module docstring)."""

    runtime: str
    model_config: ModelConfig
    action_commands: np.ndarray

    def logits(self, image: np.ndarray, imu: np.ndarray, distance: np.ndarray, bearing: np.ndarray) -> np.ndarray:
        """(batch, num_labels) float32 logits of raw float32 inputs (batch, ...)."""


class EnsemblePolicyInference(Protocol):
    """K clones' networks run together (`ditch_drake.learning.ensemble.EnsembleInference`)."""

    runtime: str
    members: int
    model_config: ModelConfig
    action_commands: np.ndarray

    def member_logits(self, image: np.ndarray, imu: np.ndarray, distance: np.ndarray,
                      bearing: np.ndarray) -> np.ndarray:
        """(members, batch, num_labels) float32 logits of raw float32 inputs (batch, ...)."""


class TorchInference:
    """A checkpoint's network in PyTorch, in eval mode, under `torch.inference_mode`."""

    runtime = "torch"

    def __init__(self, checkpoint: PolicyCheckpoint, num_threads: int | None = 1):
        """Builds the network.

        Args:
            checkpoint: the trained policy.
            num_threads: torch's intra-op threads, set here for the whole process
                (`torch.set_num_threads` is process-wide); None leaves torch's setting.

        Raises:
            ValueError: a thread count < 1.
        """
        set_torch_threads(num_threads)
        self.model_config = checkpoint.model_config
        self.action_commands = np.asarray(checkpoint.action_commands, dtype=float)
        self._model = checkpoint.build_model()

    def logits(self, image: np.ndarray, imu: np.ndarray, distance: np.ndarray, bearing: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return self._model(*(torch.as_tensor(x) for x in (image, imu, distance, bearing))).numpy()


class OnnxRuntimeInference:
    """An ONNX model of the network in an `onnxruntime.InferenceSession` on the CPU."""

    runtime = "onnxruntime"

    def __init__(self, model: bytes, model_config: ModelConfig, action_commands: np.ndarray, num_threads: int = 1,
                 where: str = "the ONNX policy"):
        """Opens the session (`onnx_policy.onnxruntime_session`, `num_threads` intra-op threads).

        Raises:
            ConfigError: onnxruntime is not installed.
            CheckpointError: onnxruntime cannot load `model`, naming `where`.
        """
        self.model_config = model_config
        self.action_commands = np.asarray(action_commands, dtype=float)
        self._session = onnxruntime_session(model, num_threads, where)
        self._outputs = [OUTPUT_NAME]

    def logits(self, image: np.ndarray, imu: np.ndarray, distance: np.ndarray, bearing: np.ndarray) -> np.ndarray:
        feed = dict(zip(INPUT_NAMES, (image, imu, distance, bearing), strict=True))
        return self._session.run(self._outputs, feed)[0]


def _torch_runtime(path: Path, num_threads: int | None) -> TorchInference | EnsembleInference:
    if is_onnx_path(path):
        raise CheckpointError(f"{path} is an ONNX model, which runs only on runtime 'onnxruntime'; expected a .pt "
                              "checkpoint for runtime 'torch', or runtime 'onnxruntime'")
    if is_ensemble_checkpoint(path):
        return EnsembleInference(load_ensemble(path), num_threads)
    return TorchInference(load_checkpoint(path), num_threads)


def _onnxruntime_runtime(path: Path, num_threads: int | None) -> OnnxRuntimeInference:
    if is_ensemble_checkpoint(path):
        raise _ensemble_runtime_error(str(path), "onnxruntime")
    threads = 1 if num_threads is None else num_threads
    if is_onnx_path(path):
        policy = read_onnx_policy(path)
        return OnnxRuntimeInference(policy.model, policy.model_config, policy.action_commands, threads, str(path))
    checkpoint = load_checkpoint(path)
    model = export_onnx(checkpoint, str(path), file_sha256(path))
    return OnnxRuntimeInference(model, checkpoint.model_config, checkpoint.action_commands, threads,
                                f"the export of {path}")


# The runtimes a policy's network runs on (`LearnedPolicyConfig.runtime`): name -> (checkpoint
# file, threads) -> inference object, and the packages each needs beyond the package's own.
RUNTIMES: dict[str, Callable[[Path, int | None], PolicyInference | EnsemblePolicyInference]] = {
    "torch": _torch_runtime,
    "onnxruntime": _onnxruntime_runtime,
}
RUNTIME_PACKAGES = {"torch": (), "onnxruntime": ("onnxruntime", "onnx")}
# The runtimes that run an ensemble file's members (in one pass).
ENSEMBLE_RUNTIMES = ("torch",)


def _ensemble_runtime_error(checkpoint: str, runtime: str) -> ConfigError:
    return ConfigError(f"learned checkpoint {checkpoint!r} is an ensemble with runtime={runtime!r}; expected runtime "
                       f"among {list(ENSEMBLE_RUNTIMES)}, the ones that run an ensemble's members")


def is_ensemble(checkpoint: str | os.PathLike) -> bool:
    """Whether `checkpoint` (a shipped name or a path) is an ensemble file; False for a name or
    path that resolves to no file (its loader says what is wrong)."""
    if not str(checkpoint) or is_onnx_path(checkpoint):
        return False
    try:
        path = resolve_checkpoint_path(checkpoint)
    except FileNotFoundError:
        return False
    return is_ensemble_checkpoint(path)


def check_runtime(runtime: str, checkpoint: str = "") -> None:
    """That `runtime` is a registered runtime whose packages are installed and that runs `checkpoint`.

    Cheap (nothing is imported or loaded; for a runtime other than torch, an ensemble file's
    header is read), for configs checked before any rollout.

    Raises:
        ConfigError: an unknown runtime, naming the choices; a missing package, naming the
            extra that installs it; a .onnx checkpoint with a runtime other than onnxruntime;
            an ensemble file with a runtime that does not run ensembles (`ENSEMBLE_RUNTIMES`).
    """
    if runtime not in RUNTIMES:
        raise ConfigError(f"learned runtime={runtime!r}: expected one of {list(RUNTIMES)}")
    missing = [name for name in RUNTIME_PACKAGES[runtime] if importlib.util.find_spec(name) is None]
    if missing:
        raise ConfigError(f"learned runtime={runtime!r} needs {missing}, not installed; expected the onnx extra: "
                          f"{INSTALL_HINT}")
    if checkpoint and is_onnx_path(checkpoint) and runtime != "onnxruntime":
        raise ConfigError(f"learned checkpoint {checkpoint!r} is an ONNX model with runtime={runtime!r}; expected "
                          "runtime 'onnxruntime', the one that runs it")
    if checkpoint and runtime not in ENSEMBLE_RUNTIMES and is_ensemble(checkpoint):
        raise _ensemble_runtime_error(checkpoint, runtime)


def check_precision(precision: str, checkpoint: str = "") -> None:
    """That `precision` (`ditch_drake.learning.ensemble_network.PRECISIONS`) is known and runs
    natively on this CPU, and that a precision other than float32 is asked of an ensemble file
    (`EnsembleNetwork` is the network that has one). Cheap: an ensemble's header is read.

    Raises:
        ConfigError: an unknown precision, bfloat16 on a CPU without it, or a precision other
            than float32 with a single clone, naming the value and what was expected.
    """
    check_network_precision(precision)
    if precision != DEFAULT_PRECISION and not is_ensemble(checkpoint):
        name = checkpoint or "the environment's shipped model"
        raise ConfigError(f"learned precision={precision!r} with checkpoint {name!r}, a single clone: the precision "
                          f"applies to an ensemble's network; expected an ensemble file or precision "
                          f"{DEFAULT_PRECISION!r}")


def load_policy(checkpoint: str | os.PathLike, runtime: str = "torch", num_threads: int | None = 1,
                precision: str = DEFAULT_PRECISION) -> PolicyInference | EnsemblePolicyInference:
    """The inference object of `checkpoint` (a shipped name, a .pt or a .onnx file, or an ensemble
    file: then an `EnsembleInference`) on `runtime`.

    Args:
        checkpoint: what `--checkpoint` takes.
        runtime: a name of `RUNTIMES`.
        num_threads: intra-op threads (torch: process-wide, None leaves its setting; onnxruntime:
            the session's, None is 1).
        precision: an ensemble network's (`check_precision`); float32 for anything else.

    Raises:
        ConfigError: an unknown or uninstalled runtime, a .onnx checkpoint on torch, or an
            ensemble on a runtime other than torch, naming the runtime; a precision that
            `check_precision` refuses.
        CheckpointNotFoundError: no such checkpoint.
        CheckpointError: a file that does not load or check, naming it.
    """
    check_runtime(runtime, str(checkpoint))
    check_precision(precision, str(checkpoint))
    path = resolve_checkpoint_path(checkpoint)
    if precision != DEFAULT_PRECISION:
        return EnsembleInference(load_ensemble(path), num_threads, precision)
    return RUNTIMES[runtime](path, num_threads)


def check_policy_file(checkpoint: str | os.PathLike) -> None:
    """Loads a .pt checkpoint (`load_checkpoint`) or an ensemble file (`load_ensemble`), or reads
    a .onnx policy (`read_onnx_policy`), raising what they raise: a batch checks its checkpoint
    once before any rollout."""
    path = resolve_checkpoint_path(checkpoint)
    if is_onnx_path(path):
        read_onnx_policy(path)
    elif is_ensemble_checkpoint(path):
        load_ensemble(path)
    else:
        load_checkpoint(path)
