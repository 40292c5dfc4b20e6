"""The stages the training pipelines share (the paper's protocol, the generalist's recipe), each
written once: collect with resume and interruption, train-or-resume a checkpoint, the device and
precision of training, and passing on a stop.

Each stage does only what an earlier run left undone, so a pipeline run again resumes; a stage
that was stopped (Ctrl-C or SIGTERM) keeps what it finished, reports it, and the pipeline stops
with the same signal (`pass_on_stop`).
"""

import os
from collections.abc import Callable
from pathlib import Path

from ditch_drake.common.errors import ConfigError
from ditch_drake.common.parallel import Terminated
from ditch_drake.common.progress import log_progress


def training_device(requested: str) -> str:
    """The torch device a training run asks for: `auto` (CUDA when torch sees a GPU, else the
    CPU), `cpu` or `cuda`.

    Raises:
        ConfigError: `cuda` asked for where torch sees no CUDA device.
    """
    import torch

    from ditch_drake.learning.train import available_device

    if requested == "auto":
        return available_device()
    if requested == "cuda" and not torch.cuda.is_available():
        raise ConfigError("--device cuda: torch sees no CUDA device; use --device cpu or auto")
    return requested


def training_precision(device: str, requested: str = "auto") -> str:
    """The precision a training run on `device` asks for: `auto` (`available_precision`: bf16 on
    a CPU that runs it natively, else fp32), `fp32` or `bf16`."""
    from ditch_drake.learning.train import available_precision

    return available_precision(device) if requested == "auto" else requested


def pass_on_stop(exit_code: int) -> None:
    """Raises the stop a stage caught and reported, by its exit code: `Terminated` for SIGTERM's
    (143), else KeyboardInterrupt (Ctrl-C's 130), so the command exits with the same code."""
    raise Terminated() if exit_code == Terminated.exit_code else KeyboardInterrupt()


def collect_demonstrations(config, name: str, progress: bool) -> dict:
    """Collects the demonstrations `config` (a `CollectConfig`) asks for that its folder does not
    hold yet (`collect` writes each as it ends, so a rerun does only the rest), says how many were
    kept and recorded, and passes on a stop.

    Returns:
        `collect`'s report.
    """
    from ditch_drake.demos.collect import collect

    report = collect(config, progress)
    unfilled = report["unfilled_slots"]
    log_progress(progress, f"collect {name}: {report['kept_before']} kept, {report['recorded']} recorded"
                 + (f", unfilled {unfilled}" if unfilled else ""))
    if report["interrupted"]:
        pass_on_stop(report["exit_code"])
    return report


def train_or_resume(out: str | os.PathLike, name: str, samples: Callable[[], object], config,
                    progress: bool, interventions: Callable[[], object] | None = None) -> None:
    """Trains `config` (a `TrainConfig`) on `samples()` (an `ArraySet`, loaded only when training
    runs) into the checkpoint `out`, unless an earlier run finished it. `interventions()`: the
    samples' intervention flags, which `config.intervention_weight` weighs (None: none).

    A finished checkpoint at `out` is kept; one from an interrupted run, or one that does not
    load, is trained again; a `.resume` file beside `out` (`train`'s state after its last
    finished epoch) is resumed from. A stop during training keeps what `train` keeps (see its
    docstring) and is passed on.
    """
    from ditch_drake.learning.checkpoint import CheckpointError, load_checkpoint
    from ditch_drake.learning.train import resume_path, train

    out = Path(out)
    if out.exists() and not resume_path(out).exists():
        try:
            if not load_checkpoint(out).metrics.get("interrupted", False):
                log_progress(progress, f"train {name}: {out} exists, kept")
                return
            log_progress(progress, f"train {name}: {out} is from an interrupted run; training again")
        except CheckpointError as error:
            log_progress(progress, f"train {name}: {error}; training again")
    out.parent.mkdir(parents=True, exist_ok=True)
    result = train(samples(), config, progress=progress, output_path=out, resume=True,
                   intervention=interventions() if interventions is not None else None)
    if result.interrupted:
        pass_on_stop(result.exit_code)


def train_ensemble_or_resume(out: str | os.PathLike, name: str, directories: list[str | os.PathLike],
                             max_demos: int | None, config, members: int, progress: bool) -> None:
    """Trains an ensemble of `members` clones on the first `max_demos` demonstrations of each of
    `directories` into `out`, as `ditch-drake train --ensemble` does (`train_ensemble`, each
    member on a bootstrap resample, its demonstrations named `<directory>[<index>]`), unless
    an earlier run finished it (`ensemble_or_resume`)."""
    from ditch_drake.demos.training_set import named_dataset_episodes, training_set

    def demonstrations():
        episodes, names = named_dataset_episodes(directories, max_demos)
        return (lambda indices: training_set([episodes[i] for i in indices])), names

    ensemble_or_resume(out, name, demonstrations, config, members, progress)


def ensemble_or_resume(out: str | os.PathLike, name: str, demonstrations: Callable[[], tuple], config, members: int,
                       progress: bool) -> None:
    """Trains an ensemble of `members` clones into `out` by `train_ensemble` on what
    `demonstrations()` gives (read only when training runs): the samples of the demonstrations at
    given indices, and their names. A file at `out` that loads as an ensemble is kept; one that
    does not is trained again. The members an interrupted run finished are kept and the one it
    was training resumes (`train_ensemble`); a stop is passed on.
    """
    from ditch_drake.common.errors import CheckpointError
    from ditch_drake.learning.ensemble import load_ensemble
    from ditch_drake.learning.ensemble_training import train_ensemble

    out = Path(out)
    if out.exists():
        try:
            load_ensemble(out)
            log_progress(progress, f"train {name}: {out} exists, kept")
            return
        except (CheckpointError, ConfigError) as error:
            log_progress(progress, f"train {name}: {error}; training again")
    samples_of, names = demonstrations()
    out.parent.mkdir(parents=True, exist_ok=True)
    result = train_ensemble(samples_of, names, out, config, members, progress)
    if result.interrupted:
        pass_on_stop(result.exit_code)


def record_signals_or_resume(out: str | os.PathLike, checkpoint: str, runs: list[tuple[str, int]], rollouts: int,
                             seed: int, time_limit_s: float, environments_file: str, progress: bool,
                             risk: bool = False, workers: int | None = 0) -> None:
    """Records the signals file `out` of `checkpoint`'s ungated rollouts as `ditch-drake
    gate-signals` does (`record_gate_signals` on each (environment, task) of `runs`, seeds
    seed .. seed + rollouts - 1; `risk`: the tip-risk signals too, as `--risk`; `workers`
    processes, None one per core), with its AUC report beside it (`<out>.auc.json`), unless an
    earlier run finished it.

    Each episode is kept in `<out>.parts/` as it finishes and one kept before is not run
    again; the file is written when all have finished, then the folder is removed. A stop keeps
    the finished episodes and is passed on.

    Raises:
        ConfigError: the parts folder holds a recording with another checkpoint or time
            limit, or another process is recording it.
    """
    import torch

    from ditch_drake.common.files import exclusive_use
    from ditch_drake.common.parallel import worker_count
    from ditch_drake.evaluation.batch import check_checkpoint
    from ditch_drake.evaluation.gate_signals import EpisodeParts, parts_folder, write_signals_file

    out = Path(out)
    folder = parts_folder(out)

    def finished() -> bool:  # With a recording in progress the file may be from a stop while it was written.
        return out.exists() and not EpisodeParts.begun(folder)

    if finished():
        log_progress(progress, f"calibrate {checkpoint}: {out} exists, kept")
        return
    digest = check_checkpoint(checkpoint)
    out.parent.mkdir(parents=True, exist_ok=True)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # One forward pass of one sample: as each evaluation worker runs it.
    try:
        with exclusive_use(out, "signals file"):
            if finished():  # Another run finished it meanwhile.
                return
            try:
                recorded, _ = write_signals_file(out, checkpoint, digest, runs, rollouts, seed, time_limit_s,
                                                 environments_file, progress=progress, risk=risk,
                                                 workers=worker_count(workers))
            except KeyboardInterrupt:
                log_progress(progress, f"calibrate {checkpoint}: interrupted; the finished episodes are kept in "
                                       f"{folder}")
                raise
            log_progress(progress, f"calibrate {checkpoint}: {len(recorded.episodes['episode_seed'])} episodes, "
                                   f"signals in {out}")
    finally:
        torch.set_num_threads(threads)
