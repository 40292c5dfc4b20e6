"""Training the behavioural clone (paper 3.5, 3.6): split, class balancing, layer-specific rates,
early stopping.

`train(arrays, config)` runs the whole protocol on an `ArraySet`, whose images are in memory
or streamed from disk (a `ditch_drake.learning.stream.LazyImageStack`, as
`ditch_drake.demos.training_set` makes of a dataset folder):

1. keep the first `max_demos` demonstrations (the 10/20/40 study);
2. hold out whole demonstrations for validation (`split_indices_by_demo`);
3. fit the scalar inputs' standardization on the training split;
4. balance the classes of the training split only, by `config.balancing`
   (`ditch_drake.learning.balance`; SMOTE by default, the paper's);
5. train with Adam, the image branch and head at `lr`, the scalar branches at
   `lr * scalar_lr_factor`, cross-entropy on the logits (weighted, or against soft targets,
   as the balancing says);
6. after every epoch evaluate on the validation split and keep the weights with the best
   ordinal accuracy (ties: lower validation loss); stop after `patience` epochs without
   improvement.

Batches come through a torch `DataLoader` over `stream.SampleBatches` (`num_workers`
processes, pinned memory on CUDA), in the order of the epoch's shuffle, so they are the same
whether the images are in memory or on disk and however many workers read them; validation
reads through one too, `eval_batch_size` samples at a time. With the images on disk, memory
does not grow with the data: the scalars (80 bytes a sample), the batches in flight, and
SMOTE's own bounded working set, its new images written to a temporary folder (`TMPDIR`)
that is removed when training ends.

Determinism: the model's initialization, every epoch's shuffle and its dropout masks are
drawn from generators seeded by (`seed`, epoch), inside `torch.random.fork_rng` so the
caller's global generator is left alone, with `torch.use_deterministic_algorithms(True)`
and a fixed thread count for the run; the same data and config give the same weights.
Because each epoch is seeded on its own, a run resumed from its `.resume` file after
epoch k continues exactly as the uninterrupted run would have.

Files, when `output_path` is given:

- during training, only the full training state after the last finished epoch, at
  `output_path` + ".resume" (`resume_path`; another schema, which `load_checkpoint`
  refuses). Nothing is written at `output_path` before training ends: a run killed
  outright (SIGKILL, a power cut) leaves the previous file there, or none, and never a
  file that looks like a finished run; `resume=True` continues from the ".resume" file.
- at a clean finish (all epochs, or early stopping): the checkpoint at `output_path`, and
  the ".resume" file is removed (it is about 4 times the checkpoint's size).
- Ctrl-C (KeyboardInterrupt) during the epochs ends training: with at least one finished
  epoch (this run's or the resumed one's), the best weights so far are saved, marked
  `interrupted`, at `output_path` if no file was there, else beside it at
  `interrupted_path(output_path)` (`<stem>.interrupted.pt`), so an interrupted run never
  replaces a checkpoint; with none, no checkpoint is written. The ".resume" file stays.
  `TrainResult.output_path` says where the checkpoint went (None: nowhere).

Every file is written by `save_payload`: a temporary file in the same folder, fsynced, then
`os.replace`, so a reader sees the old file or the whole new one.

Cost: a training step takes about 30 ms per sample on 2 shared CPU cores (the first
convolution, 64 filters at full 128 x 128 resolution, dominates), so an epoch over one
environment's 40 demonstrations (~13 k real + ~13 k SMOTE samples) takes about 12 min.
"""

import copy
import os
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

import ditch_drake
from ditch_drake.common.errors import ConfigError
from ditch_drake.common.files import remove_stale_temporaries
from ditch_drake.common.parallel import interrupt_exit_code
from ditch_drake.common.progress import log_progress
from ditch_drake.learning.balance import Balancing, balance_training_split
from ditch_drake.learning.checkpoint import (
    CheckpointError,
    PolicyCheckpoint,
    load_payload,
    make_checkpoint,
    save_checkpoint,
    save_payload,
    to_plain,
)
from ditch_drake.learning.config import PRECISIONS, ModelConfig, SmoteConfig, TrainConfig  # noqa: F401
from ditch_drake.learning.data import (
    ArraySet,
    InputStats,
    first_demos_indices,
    split_indices_by_demo,
)
from ditch_drake.learning.metrics import confusion_matrix, exact_accuracy, ordinal_accuracy
from ditch_drake.learning.model import FourInputClassifier, parameter_groups
from ditch_drake.learning.stream import TrainingSamples, batch_loader, epoch_batches, to_device
from ditch_drake.spec.actions import NUM_LABELS

RESUME_SCHEMA = "ditch_drake.training_state"
RESUME_SCHEMA_VERSION = 1
RESUME_SUFFIX = ".resume"
# Fields that may change between a run and its resumption; all others must match.
_RESUMABLE_CHANGES = {"epochs", "patience", "num_threads", "device", "precision", "num_workers"}
# A setting's value in a file written before the setting was recorded, where that is no longer
# its default: every training balanced its classes by SMOTE until `balancing` was a setting.
RECORDED_BEFORE = {"balancing": "smote"}
INTERRUPTED_SUFFIX = ".interrupted"

# Deterministic mode fills every new tensor with NaN, a guard against reading memory no operation
# wrote. Training reads none (its weights are the same bit for bit with the fill and without it,
# tests/test_learning.py), and the fill touches every page of the first convolution's output and
# of its gradient at every step.
FILL_UNINITIALIZED_MEMORY = False


@dataclass
class TrainResult:
    """What `train` returns.

    Attributes:
        model: the kept (best) weights, in eval mode, on the CPU.
        checkpoint: the same as a `PolicyCheckpoint` (what was saved to `output_path`).
        history: one dict per finished epoch: epoch, train_loss, train_exact_accuracy,
            train_ordinal_accuracy, val_loss, val_exact_accuracy, val_ordinal_accuracy
            (nan without validation), seconds.
        best_epoch: the epoch whose weights were kept (-1 if none finished).
        stopped_early: patience ran out.
        interrupted: a KeyboardInterrupt ended training.
        output_path: where the checkpoint was saved: the `output_path` asked for,
            `interrupted_path` of it (interrupted, and a file was there), or None (none asked
            for, or interrupted before any epoch finished).
        resume_file: the training state kept for `resume=True` (after an interruption),
            else None.
        exit_code: the shell's code for the stop that interrupted it (130 Ctrl-C, 143
            SIGTERM), else 0.
    """

    model: FourInputClassifier
    checkpoint: PolicyCheckpoint
    history: list[dict]
    best_epoch: int
    stopped_early: bool
    interrupted: bool
    output_path: Path | None = None
    resume_file: Path | None = None
    exit_code: int = 0


@torch.no_grad()
def predict(
    model: FourInputClassifier, arrays: ArraySet, rows: np.ndarray | None = None, batch_size: int = 256,
    num_workers: int = 0,
) -> np.ndarray:
    """(len(rows), num_labels) float32 logits of the rows of `arrays` (all by default), in eval mode,
    read `batch_size` rows at a time through a loader of `num_workers` processes.

    The model's train/eval mode is restored afterwards.
    """
    rows = np.arange(len(arrays)) if rows is None else np.asarray(rows, dtype=np.int64)
    device = next(model.parameters()).device
    was_training = model.training
    model.eval()
    logits = []
    positions = np.arange(len(rows))
    chunks = [positions[start : start + batch_size] for start in range(0, len(rows), batch_size)]
    try:
        for batch in batch_loader(TrainingSamples(arrays, rows), chunks, num_workers, device.type == "cuda"):
            inputs, _ = to_device(batch, device)
            logits.append(model(*inputs).float().cpu().numpy())
    finally:
        model.train(was_training)
    return np.concatenate(logits) if logits else np.zeros((0, model.config.num_labels), np.float32)


def evaluate(
    model: FourInputClassifier,
    arrays: ArraySet,
    rows: np.ndarray | None = None,
    tolerance: int = 1,
    batch_size: int = 256,
    num_workers: int = 0,
) -> dict:
    """Loss, exact and ordinal accuracy and the confusion matrix on the rows of `arrays`.

    Returns:
        {"loss", "exact_accuracy", "ordinal_accuracy" (nan for no rows), "confusion_matrix"
        ((17, 17) int64, row = true label), "predicted" (labels)}.
    """
    rows = np.arange(len(arrays)) if rows is None else np.asarray(rows, dtype=np.int64)
    logits = predict(model, arrays, rows, batch_size, num_workers)
    true = arrays.label[rows]
    predicted = logits.argmax(axis=1) if len(rows) else np.zeros(0, np.int64)
    loss = float("nan")
    if len(rows):
        loss = float(nn.functional.cross_entropy(torch.from_numpy(logits), torch.from_numpy(true)))
    return {
        "loss": loss,
        "exact_accuracy": exact_accuracy(predicted, true),
        "ordinal_accuracy": ordinal_accuracy(predicted, true, tolerance),
        "confusion_matrix": confusion_matrix(predicted, true, model.config.num_labels),
        "predicted": predicted,
    }


def resume_path(output_path: str | os.PathLike) -> Path:
    """Where `train` keeps the full training state for `output_path`."""
    output_path = Path(output_path)
    return output_path.with_name(output_path.name + RESUME_SUFFIX)


def interrupted_path(output_path: str | os.PathLike) -> Path:
    """Where an interrupted `train` saves its best weights when a file is already at
    `output_path`: `<stem>.interrupted<suffix>` beside it (`policy.pt` -> `policy.interrupted.pt`)."""
    output_path = Path(output_path)
    return output_path.with_name(f"{output_path.stem}{INTERRUPTED_SUFFIX}{output_path.suffix or '.pt'}")


def _torch_seed(seed: int, stream: int, epoch: int = 0) -> int:
    """A torch seed of its own for (seed, stream, epoch): stream 0 initializes, 1 drops out."""
    return int(np.random.default_rng([seed, stream, epoch]).integers(2**62))


def _is_better(candidate: tuple[float, float], best: tuple[float, float] | None) -> bool:
    """(ordinal accuracy, loss): higher accuracy wins, then lower loss; nan never wins."""
    if best is None:
        return True
    accuracy, loss = candidate
    if np.isnan(accuracy):
        return False
    if np.isnan(best[0]) or accuracy > best[0]:
        return True
    return accuracy == best[0] and loss < best[1]


def _config_dict(config: TrainConfig) -> dict:
    values = asdict(config)
    if values["intervention_weight"] == 1.0:  # Uniform: recorded as before the field existed.
        del values["intervention_weight"]
    if values["shared_steps"] == "all":  # Every step: recorded as before the field existed.
        del values["shared_steps"]
    return to_plain(values, "train_config")


def loader_workers(config: TrainConfig) -> int:
    """`config.num_workers`, or for None: 0 on every device.

    Measured on an H200 (`python -m ditch_drake.perf.bench_training_device`, docs/concepts/learning.md):
    reading in the training process streams 5,600 samples/s, and 2 or 4 workers, forked from the
    preloaded server, were no faster (5,300 and 4,700) while the first epoch paid their start.
    """
    return 0 if config.num_workers is None else config.num_workers


def train(
    arrays: ArraySet,
    config: TrainConfig | None = None,
    progress: bool = True,
    output_path: str | os.PathLike | None = None,
    resume: bool = False,
    intervention: np.ndarray | None = None,
) -> TrainResult:
    """Trains the paper's classifier on `arrays` (see the module docstring for the protocol).

    Args:
        arrays: all samples (validated); only the first `config.max_demos`
            demonstrations are used.
        config: settings; default `TrainConfig()`.
        progress: show a tqdm bar per epoch and print one line per epoch (to stderr).
        output_path: where to save the checkpoint when training ends (see the module
            docstring for what an interruption saves where), with the ".resume" training
            state beside it during training; None saves nothing.
        resume: continue from `resume_path(output_path)` if it exists (the data and every
            config field but epochs, patience, num_threads, device and precision must be
            the same).
        intervention: (N,) bool over the rows of `arrays`, the steps a supervisor took over
            (the store's `intervention` field; `ditch_drake.demos.interventions`), whose loss
            `config.intervention_weight` weighs; None: none. Unused at weight 1.

    Returns:
        The kept model, its checkpoint, the per-epoch history and where it was saved.

    Raises:
        ConfigError: an unusable data set for the config (too few demonstrations to
            split, more asked for than there are, no training samples), or `resume`
            without `output_path` (a ValueError, as before).
        CheckpointError: `output_path` is a folder, or a resume file of another run or config.
    """
    config = config or TrainConfig()
    if resume and output_path is None:
        raise ConfigError("resume=True needs output_path (the .resume file sits beside it)")
    output_path = None if output_path is None else Path(output_path)
    if output_path is not None and output_path.is_dir():  # Found now, not after hours of training.
        raise CheckpointError(f"{output_path} is a folder; expected the path of a .pt file to write (--out)")
    if output_path is not None:
        remove_stale_temporaries(output_path.parent)
    try:
        rows = first_demos_indices(arrays, config.max_demos)
        train_rows, val_rows = split_indices_by_demo(arrays.demo_id, config.val_fraction, config.seed, rows)
    except ValueError as error:  # Fewer demonstrations than max_demos, or too few to split.
        raise ConfigError(str(error)) from error
    if len(train_rows) < 2:
        raise ConfigError(f"{len(train_rows)} training sample(s) after the validation split; expected at least 2")
    if intervention is not None and np.shape(intervention) != (len(arrays),):
        raise ConfigError(f"intervention has shape {np.shape(intervention)}; expected ({len(arrays)},), a flag per "
                          "sample")
    stats = InputStats.fit(arrays, train_rows)
    # SMOTE's new images go to disk when the set's own images are there: in memory they would
    # grow with the data (64 KiB a sample).
    spill = None if isinstance(arrays.image, np.ndarray) or config.balancing != "smote" else (
        tempfile.TemporaryDirectory(prefix="ditch_drake_smote_"))
    try:
        balancing = balance_training_split(arrays, train_rows, stats, config, spill and spill.name)
        added = int(balancing.extra_label_counts.sum())
        log_progress(
            progress,
            f"{len(train_rows)} training samples ({len(np.unique(arrays.demo_id[train_rows]))} demonstrations), "
            f"{len(val_rows)} validation ({len(np.unique(arrays.demo_id[val_rows]))}); {config.balancing} added "
            f"{added} in {balancing.seconds:.1f} s",
        )
        summary = {
            "label_counts": np.bincount(arrays.label[train_rows], minlength=NUM_LABELS),
            # The samples balancing added: SMOTE's new ones, or the rows oversampling draws again.
            "synthetic_label_counts": balancing.extra_label_counts,
            "val_label_counts": np.bincount(arrays.label[val_rows], minlength=NUM_LABELS),
            "train_demo_ids": np.unique(arrays.demo_id[train_rows]),
            "val_demo_ids": np.unique(arrays.demo_id[val_rows]),
            "num_train_samples": len(train_rows),
            "num_synthetic_samples": added,
            "num_val_samples": len(val_rows),
            "train_config": _config_dict(config),
            "balancing": config.balancing,
            "balancing_seconds": balancing.seconds,
            # Kept for the readers of older checkpoints' key: SMOTE's time, 0 for another method.
            "smote_seconds": balancing.seconds if config.balancing == "smote" else 0.0,
        }
        sample_weights = None
        if config.intervention_weight != 1.0:  # At 1, nothing changes: not even the summary's keys.
            flags = np.zeros(len(arrays), np.bool_) if intervention is None else np.asarray(intervention, np.bool_)
            sample_weights = position_weights(flags, balancing, config.intervention_weight)
            summary["intervention_train_samples"] = int(flags[train_rows].sum())
            log_progress(progress, f"{summary['intervention_train_samples']} intervention samples weigh "
                                   f"{config.intervention_weight:g} in the loss")

        previous_threads = torch.get_num_threads()
        previous_deterministic = torch.are_deterministic_algorithms_enabled()
        previous_warn_only = torch.is_deterministic_algorithms_warn_only_enabled()
        previous_fill = torch.utils.deterministic.fill_uninitialized_memory
        try:
            if config.num_threads is not None:
                torch.set_num_threads(config.num_threads)
            torch.use_deterministic_algorithms(True, warn_only=True)
            torch.utils.deterministic.fill_uninitialized_memory = FILL_UNINITIALIZED_MEMORY
            with torch.random.fork_rng(devices=[]):
                return _run(arrays, config, progress, output_path, resume, val_rows, stats, balancing, summary,
                            sample_weights)
        finally:
            torch.set_num_threads(previous_threads)
            torch.use_deterministic_algorithms(previous_deterministic, warn_only=previous_warn_only)
            torch.utils.deterministic.fill_uninitialized_memory = previous_fill
    finally:
        if spill is not None:
            spill.cleanup()


def available_device() -> str:
    """"cuda" when torch sees a GPU, else "cpu": what `ditch-drake train` and experiments use by default."""
    return "cuda" if torch.cuda.is_available() else "cpu"


def available_precision(device: str) -> str:
    """"bf16" on a CPU whose instructions run bfloat16 natively (AVX512-BF16 or AMX), else
    "fp32": what `ditch-drake train` and experiments use by default. CUDA trains in fp32."""
    if torch.device(device).type != "cpu":
        return "fp32"
    probes = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")  # Private torch API: absent means no.
    return "bf16" if any(getattr(torch.cpu, probe, lambda: False)() for probe in probes) else "fp32"


def position_weights(intervention: np.ndarray, balancing: Balancing, weight: float) -> np.ndarray:
    """(positions,) float32: the loss weight of each position an epoch draws from, `weight` where
    the row is an intervention and 1 elsewhere; a synthetic (SMOTE) sample, interpolated within
    its class from rows of either kind, weighs 1."""
    weights = np.where(intervention[balancing.rows], np.float32(weight), np.float32(1.0)).astype(np.float32)
    extra = len(balancing) - len(balancing.rows)
    return np.concatenate([weights, np.ones(extra, np.float32)])


def intervention_weighted_loss(logits: torch.Tensor, labels: torch.Tensor, sample_weights: torch.Tensor,
                               class_weights: torch.Tensor | None = None,
                               soft_targets: torch.Tensor | None = None) -> torch.Tensor:
    """The batch's cross-entropy with per-sample weights: sum(w_i c_i l_i) / sum(w_i c_i), where
    l_i is sample i's cross-entropy (against `soft_targets[label]` when given), w_i its
    `sample_weights` entry and c_i its class's `class_weights` entry (1 without)."""
    targets = labels if soft_targets is None else soft_targets[labels]
    losses = nn.functional.cross_entropy(logits, targets, weight=class_weights, reduction="none")
    weights = sample_weights if class_weights is None else sample_weights * class_weights[labels]
    return (sample_weights * losses).sum() / weights.sum()


def _loss_function(balancing: Balancing, device: str):
    """The training loss of a balancing: cross-entropy, class-weighted or against soft targets."""
    if balancing.soft_targets is not None:
        targets = torch.from_numpy(balancing.soft_targets).to(device)
        return lambda logits, labels: nn.functional.cross_entropy(logits, targets[labels])
    weights = None if balancing.class_weights is None else torch.from_numpy(balancing.class_weights).to(device)
    return nn.CrossEntropyLoss(weight=weights)


def _weighted_loss_function(balancing: Balancing, device: str, sample_weights: np.ndarray):
    """The training loss of a balancing with `sample_weights[position]` per sample
    (`intervention_weighted_loss`): called with the batch's logits, labels and positions."""
    weights = torch.from_numpy(sample_weights).to(device)
    class_weights = None if balancing.class_weights is None else torch.from_numpy(balancing.class_weights).to(device)
    soft_targets = None if balancing.soft_targets is None else torch.from_numpy(balancing.soft_targets).to(device)

    def loss(logits, labels, positions):
        return intervention_weighted_loss(logits, labels, weights[torch.from_numpy(positions).to(device)],
                                          class_weights, soft_targets)

    return loss


def _run(arrays, config, progress, output_path, resume, val_rows, stats, balancing, summary,
         sample_weights=None) -> TrainResult:
    torch.manual_seed(_torch_seed(config.seed, 0))
    model = FourInputClassifier(config.model)
    model.set_input_stats(stats.to_dict())
    model.to(config.device)
    optimizer = torch.optim.Adam(parameter_groups(model, config.lr, config.scalar_lr_factor))
    loss_function = _loss_function(balancing, config.device)
    if sample_weights is not None:
        loss_function = _weighted_loss_function(balancing, config.device, sample_weights)
    samples = TrainingSamples(arrays, balancing.rows, balancing.synthetic)
    workers = loader_workers(config)
    pin = torch.device(config.device).type == "cuda"
    run = {"history": [], "best_state": None, "best_key": None, "best_epoch": -1, "bad_epochs": 0, "confusion": None}
    start_epoch = 0
    state_file = None if output_path is None else resume_path(output_path)
    if resume and state_file.exists():
        start_epoch = _restore(state_file, config, summary, model, optimizer, run)
        log_progress(progress, f"resuming from {state_file} after epoch {start_epoch - 1}")

    has_val = len(val_rows) > 0
    stopped_early = interrupted = False
    exit_code = 0
    try:
        for epoch in range(start_epoch, config.epochs):
            if has_val and run["bad_epochs"] >= config.patience:
                stopped_early = True
                break
            start = time.perf_counter()
            torch.manual_seed(_torch_seed(config.seed, 1, epoch))
            batches = epoch_batches(balancing.epoch_order(config.seed, epoch), config.batch_size,
                                    config.max_batches_per_epoch)
            model.train()
            loss_sum, predicted, true = 0.0, [], []
            bar = tqdm(batch_loader(samples, batches, workers, pin), total=len(batches), desc=f"epoch {epoch}",
                       disable=not progress, leave=False, file=sys.stderr)
            for positions, batch in zip(batches, bar, strict=True):
                inputs, labels = to_device(batch, config.device)
                with torch.autocast(torch.device(config.device).type, torch.bfloat16, config.precision == "bf16"):
                    logits = model(*inputs)
                    loss = loss_function(logits, labels) if sample_weights is None else (
                        loss_function(logits, labels, positions))
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
                loss_value = loss.item()
                loss_sum += loss_value * len(labels)
                predicted.append(logits.argmax(dim=1).cpu().numpy())
                true.append(labels.cpu().numpy())
                bar.set_postfix(loss=f"{loss_value:.3f}")
            predicted, true = np.concatenate(predicted), np.concatenate(true)
            val = evaluate(model, arrays, val_rows, config.ordinal_tolerance, config.eval_batch_size, workers)
            record = {
                "epoch": epoch,
                "train_loss": loss_sum / len(true),
                "train_exact_accuracy": exact_accuracy(predicted, true),
                "train_ordinal_accuracy": ordinal_accuracy(predicted, true, config.ordinal_tolerance),
                "val_loss": val["loss"],
                "val_exact_accuracy": val["exact_accuracy"],
                "val_ordinal_accuracy": val["ordinal_accuracy"],
                "seconds": time.perf_counter() - start,
            }
            run["history"].append(record)
            key = (record["val_ordinal_accuracy"], record["val_loss"])
            improved = not has_val or _is_better(key, run["best_key"])
            if improved:
                run.update(best_key=key, best_epoch=epoch, bad_epochs=0, confusion=val["confusion_matrix"])
                run["best_state"] = copy.deepcopy(model.state_dict())
            else:
                run["bad_epochs"] += 1
            log_progress(progress, _epoch_line(record, improved))
            if output_path is not None:
                # Only the resume file, never a checkpoint at output_path mid-run: a run killed
                # between epochs must not leave a file there that reads as a finished one.
                _save_state(state_file, config, summary, epoch, model, optimizer, run)
            if has_val and run["bad_epochs"] >= config.patience and epoch + 1 < config.epochs:
                stopped_early = True
                break
    except KeyboardInterrupt as error:
        interrupted, exit_code = True, interrupt_exit_code(error)
        if run["best_state"] is None:
            log_progress(progress, "interrupted before the first epoch finished: no checkpoint is saved")
        else:
            log_progress(progress, f"interrupted; keeping the weights of epoch {run['best_epoch']}")
    trained = run["best_state"] is not None
    if not trained:  # Interrupted in the first epoch: the initial weights, returned but never saved.
        run["best_state"] = copy.deepcopy(model.state_dict())
    checkpoint = _checkpoint(config, stats, summary, run, stopped_early, interrupted)
    saved_to = kept_state = None
    if output_path is not None and trained:
        saved_to = interrupted_path(output_path) if interrupted and output_path.exists() else output_path
        save_checkpoint(checkpoint, saved_to)
        log_progress(progress, f"saved {saved_to} (weights of epoch {run['best_epoch']})")
    if state_file is not None:
        if interrupted:
            kept_state = state_file if state_file.exists() else None
        else:  # Finished: the training state is of no more use.
            state_file.unlink(missing_ok=True)
    return TrainResult(
        model=checkpoint.build_model(),
        checkpoint=checkpoint,
        history=run["history"],
        best_epoch=run["best_epoch"],
        stopped_early=stopped_early,
        interrupted=interrupted,
        output_path=saved_to,
        resume_file=kept_state,
        exit_code=exit_code,
    )


def _checkpoint(
    config: TrainConfig, stats: InputStats, summary: dict, run: dict, stopped_early: bool, interrupted: bool
) -> PolicyCheckpoint:
    best = next((r for r in run["history"] if r["epoch"] == run["best_epoch"]), {})
    metrics = {
        "best_epoch": run["best_epoch"],
        "best": dict(best),
        "ordinal_tolerance": config.ordinal_tolerance,
        "val_confusion_matrix": run["confusion"],
        "epochs_run": len(run["history"]),
        "stopped_early": stopped_early,
        "interrupted": interrupted,
        "history": run["history"],
        # Balancing plus every finished epoch (training and validation); loading the data is not in it.
        "training_seconds": summary["balancing_seconds"] + sum(record["seconds"] for record in run["history"]),
    }
    model = FourInputClassifier(config.model)
    model.load_state_dict(run["best_state"])
    return make_checkpoint(model, stats, summary, metrics)


def _save_state(state_file: Path, config, summary, epoch, model, optimizer, run) -> None:
    save_payload(
        {
            "schema": RESUME_SCHEMA,
            "schema_version": RESUME_SCHEMA_VERSION,
            "code_version": ditch_drake.__version__,
            "train_config": _config_dict(config),
            "train_demo_ids": to_plain(summary["train_demo_ids"]),
            "epoch": epoch,
            "model_state": model.state_dict(),
            "optimizer_state": optimizer.state_dict(),
            "best_state": run["best_state"],
            "best_key": None if run["best_key"] is None else list(run["best_key"]),
            "best_epoch": run["best_epoch"],
            "bad_epochs": run["bad_epochs"],
            "confusion": to_plain(run["confusion"]),
            "history": to_plain(run["history"], "history"),
        },
        state_file,
    )


def _restore(state_file: Path, config, summary, model, optimizer, run) -> int:
    """Loads a resume file into `model`, `optimizer` and `run`; returns the next epoch."""
    state = load_payload(state_file, RESUME_SCHEMA, RESUME_SCHEMA_VERSION)
    mine, theirs = _config_dict(config), state.get("train_config", {})
    # A field added since the file was written had its default value then (`RECORDED_BEFORE`
    # where the default has changed since).
    theirs = {**_config_dict(TrainConfig()), **RECORDED_BEFORE, **theirs}
    differ = sorted(k for k in set(mine) | set(theirs) if k not in _RESUMABLE_CHANGES and mine.get(k) != theirs.get(k))
    if differ or state.get("train_demo_ids") != to_plain(summary["train_demo_ids"]):
        raise CheckpointError(
            f"{state_file} is from another run: config fields {differ} differ, or the training demonstrations do"
        )
    try:
        model.load_state_dict(state["model_state"])
        optimizer.load_state_dict(state["optimizer_state"])
        run.update(
            history=list(state["history"]),
            best_state=state["best_state"],
            best_key=None if state["best_key"] is None else tuple(state["best_key"]),
            best_epoch=int(state["best_epoch"]),
            bad_epochs=int(state["bad_epochs"]),
            confusion=state["confusion"],
        )
        return int(state["epoch"]) + 1
    except (KeyError, RuntimeError, ValueError, TypeError) as error:
        raise CheckpointError(f"{state_file}: incomplete training state ({type(error).__name__}: {error})") from error


def _epoch_line(record: dict, improved: bool) -> str:
    return (
        f"epoch {record['epoch']:3d}  train loss {record['train_loss']:.4f} "
        f"acc {record['train_exact_accuracy']:.3f} ord {record['train_ordinal_accuracy']:.3f}  "
        f"val loss {record['val_loss']:.4f} acc {record['val_exact_accuracy']:.3f} "
        f"ord {record['val_ordinal_accuracy']:.3f}  {record['seconds']:.1f} s{'  *' if improved else ''}"
    )
