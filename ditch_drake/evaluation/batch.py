"""Batch evaluation: seeded rollouts in parallel worker processes, recorded as they end.

`evaluate(specs, results_path)` runs every `RolloutSpec` not yet in the results file with
the Drake Simulator (no visualization), in a pool of worker processes, and appends each
rollout's `RolloutRecord` the moment it ends. Interrupted (Ctrl-C, a killed job) and run
again, it skips the recorded rollouts: nothing is lost and nothing is recorded twice.

A Python exception inside a rollout is recorded as status "error" with its message. A
worker process that dies (a crash in compiled code, the out-of-memory killer) takes its
rollouts with it: they are retried once in a fresh pool, then recorded as errors. An error
record does not finish its rollout: the next run of the same specs runs it again. A rollout
that cannot import a module stops the run (ConfigError): every other would fail the same way.

Ctrl-C or SIGTERM stops a run within a second or two: the workers are killed (what they
were running is lost and runs again next time), every rollout that had ended is already in
the file, and the report says the run was interrupted (see `ditch_drake.common.parallel`).

Each worker keeps a few built diagrams (`rollout_worker`), and even so its memory grows by
tens of MB per diagram it has built and dropped (about 5 GB after 210 rollouts of the
generalization study with 4 kept), so a pool's worker processes are replaced after about
`ROLLOUTS_PER_WORKER` rollouts each, which bounds them whatever leaks: the pending rollouts
run in chunks of workers x `ROLLOUTS_PER_WORKER`, each chunk in a fresh pool. (Not with the
executor's own `max_tasks_per_child`: on Python 3.11 a pool whose two workers reached that
limit together stopped starting new ones, and the run hung with no process left working.)
"""

import os
import sys
import time
from concurrent.futures import as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field, replace
from pathlib import Path

from tqdm import tqdm

from ditch_drake.common.checks import check_count, check_finite_positive
from ditch_drake.common.config_yaml import config_digest, config_to_yaml, type_path
from ditch_drake.common.errors import ConfigError
from ditch_drake.common.files import exclusive_use, prepare_output
from ditch_drake.common.parallel import (
    WorkerPool,
    check_workers,
    deferred_interrupts,
    interrupt_exit_code,
    terminate_as_interrupt,
    worker_count,
)
from ditch_drake.common.ray_tasks import BACKENDS
from ditch_drake.common.seeds import check_seed
from ditch_drake.diagrams.controllers import (
    UndeclaredInputError,
    check_controller_config,
    config_checkpoint,
    controller_config,
    controller_names,
    with_checkpoint,
)
from ditch_drake.evaluation.results import RecordWriter, RolloutRecord, RolloutSpec, finished_keys, read_records
from ditch_drake.evaluation.rollout_worker import error_record, initialize_worker, run_rollout
from ditch_drake.learning.checkpoint import checkpoint_digest, environment_model
from ditch_drake.learning.inference import check_policy_file
from ditch_drake.systems.episode_monitor import EpisodeConfig
from ditch_drake.world.environments import get_environment

# About how many rollouts a worker process runs before a fresh pool replaces it (see the module docstring).
ROLLOUTS_PER_WORKER = 100
# Pools broken by a dying worker before each remaining rollout runs in a process of its own.
_ATTEMPTS = 2


@dataclass
class EvaluationReport:
    """What `evaluate` did.

    Attributes:
        results_path: the results file.
        requested: distinct rollouts asked for.
        skipped: rollouts already recorded before this run (error records excluded: they run again).
        recorded: records appended by this run.
        successes: successes among them.
        errors: error records among them.
        interrupted: Ctrl-C or SIGTERM ended the run early (what finished is recorded).
        exit_code: the shell's code for that stop (130 Ctrl-C, 143 SIGTERM), else 0.
        wall_s: wall-clock time of the run (s).
        warnings: e.g. a torn last line dropped from the results file.
    """

    results_path: str
    requested: int = 0
    skipped: int = 0
    recorded: int = 0
    successes: int = 0
    errors: int = 0
    interrupted: bool = False
    exit_code: int = 0
    wall_s: float = 0.0
    warnings: list[str] = field(default_factory=list)

    @property
    def rollouts_per_minute(self) -> float:
        return 60.0 * self.recorded / self.wall_s if self.wall_s > 0 else 0.0


def make_specs(controller, checkpoint: str, environment: str, tasks: list[int] | None = None,
               rollouts: int = 10, seed: int = 0, time_limit_s: float = EpisodeConfig.time_limit_s,
               environments_file: str = "") -> list[RolloutSpec]:
    """`rollouts` seeded rollouts (seeds seed, seed + 1, ...) for each task of `environment`.

    Args:
        controller: a registered controller's name (its default config, with `checkpoint`
            for the learned policy), or a controller config (`checkpoint` is then ignored:
            the config names its own).
        environments_file: the YAML file defining `environment` ("" for the packaged one).

    The learned policy's checkpoint is loaded and checked here, once, and its contents'
    digest goes into every spec (and so into the record keys), as does the digest of the
    controller's config.

    Raises:
        ConfigError: an unknown controller, environment or task, a controller config value out
            of range, a checkpoint given to a controller that takes none, a missing checkpoint,
            non-positive counts, a time limit that is not a finite positive number or a
            negative seed, each named.
        CheckpointError: a checkpoint that does not load, with the loader's message.
    """
    config = controller_config(controller, checkpoint) if isinstance(controller, str) else controller
    entry = check_controller_config(config)  # Before any rollout: one message, not an error record each.
    name = controller if isinstance(controller, str) else entry.name  # Several names may share a config type.
    if checkpoint and not hasattr(config, "checkpoint"):
        takers = [known for known in controller_names() if hasattr(controller_config(known), "checkpoint")]
        raise ConfigError(f"checkpoint {checkpoint!r} with controller {name!r}, which takes none; expected a "
                          f"checkpoint only with {takers}")
    check_count(rollouts, "rollouts")
    check_finite_positive(time_limit_s, "time_limit_s")
    if hasattr(config, "checkpoint") and not config.checkpoint:  # The learned policy's default: the environment's.
        config = with_checkpoint(config, environment_model(environment, environments_file))
    checkpoint = config_checkpoint(config)
    digest = check_checkpoint(checkpoint)
    if hasattr(config, "resolved"):  # Values a file sets (the shared gate's budget): the record says what ran.
        config = config.resolved()
    task_count = len(get_environment(environment, environments_file or None).tasks)
    tasks = list(range(task_count)) if tasks is None else list(tasks)
    bad = [task for task in tasks if not 0 <= task < task_count]
    if bad:
        raise ConfigError(f"tasks {bad} of {environment!r} do not exist; expected indices in 0..{task_count - 1}")
    check_seed(seed, rollouts)
    fields = {"controller": name, "controller_type": type_path(type(config)),
              "controller_config": config_to_yaml(config), "controller_sha256": config_digest(config),
              "checkpoint": checkpoint, "checkpoint_sha256": digest,
              "environment": environment, "environments_file": str(environments_file or "")}
    return [RolloutSpec(**fields, task=task, seed=seed + i, time_limit_s=float(time_limit_s),
                        goal_radius_m=float(EpisodeConfig.goal_radius_m))
            for task in tasks for i in range(rollouts)]


def spelled_as_recorded(specs: list[RolloutSpec], records: list[RolloutRecord]) -> list[RolloutSpec]:
    """`specs`, each environments file and checkpoint spelled as `records` (a results file's)
    spell the same file. A key holds the paths as given (a checkpoint's also inside the
    controller's config and its digest), so a run given another spelling of one (absolute where
    the records have it relative, say) would find none of its rollouts done, run them all again
    and append them beside the first ones. A checkpoint is respelled only where the respelled
    config is one the records ran."""
    recorded = sorted({record.environments_file for record in records if record.environments_file})
    spellings = {path: _recorded_spelling(path, recorded) for path in {spec.environments_file for spec in specs}}
    specs = [replace(spec, environments_file=spellings[spec.environments_file]) for spec in specs]
    checkpoints = sorted({record.checkpoint for record in records if record.checkpoint})
    configs = {record.controller_sha256 for record in records}
    respelled = {}  # By checkpoint and config: the fields that respell them ({}: none).
    for spec in specs:
        if spec.checkpoint and (spec.checkpoint, spec.controller_sha256) not in respelled:
            respelled[spec.checkpoint, spec.controller_sha256] = _recorded_checkpoint_fields(spec, checkpoints, configs)
    return [replace(spec, **respelled.get((spec.checkpoint, spec.controller_sha256), {})) for spec in specs]


def _recorded_spelling(path: str, recorded: list[str]) -> str:
    """The spelling among `recorded` of the file `path` names, else `path`."""
    if not path or path in recorded or not os.path.exists(path):
        return path
    return next((known for known in recorded if os.path.exists(known) and os.path.samefile(known, path)), path)


def _recorded_checkpoint_fields(spec: RolloutSpec, checkpoints: list[str], configs: set[str]) -> dict:
    """The spec fields that spell its checkpoint as among `checkpoints` where the config so
    respelled is among `configs` (one the records ran), else {}."""
    from ditch_drake.evaluation.rollout_worker import spec_config

    spelling = _recorded_spelling(spec.checkpoint, checkpoints)
    if spelling == spec.checkpoint:
        return {}
    config = with_checkpoint(spec_config(spec), spelling)
    if config_checkpoint(config) != spelling or config_digest(config) not in configs:
        return {}
    return {"checkpoint": spelling, "controller_config": config_to_yaml(config), "controller_sha256": config_digest(config)}


def check_checkpoint(checkpoint: str) -> str:
    """The checkpoint's digest ("" for none), after loading it once (a .pt checkpoint, an ensemble
    file or a .onnx policy: `check_policy_file`).

    Raises:
        ConfigError: no such checkpoint file.
        CheckpointError: a checkpoint file that does not load.
    """
    if not checkpoint:
        return ""
    try:
        check_policy_file(checkpoint)  # A .pt checkpoint, an ensemble file, or a .onnx policy.
    except FileNotFoundError as error:
        raise ConfigError(str(error)) from error
    return checkpoint_digest(checkpoint)


def evaluate(specs: list[RolloutSpec], results_path: str | os.PathLike, workers: int | None = None,
             progress: bool = True, backend: str = "local", address: str | None = None,
             rollouts_per_worker: int = ROLLOUTS_PER_WORKER) -> EvaluationReport:
    """Runs the specs not yet recorded in `results_path`, appending each record as it ends.

    Args:
        specs: the rollouts; duplicates (same key) run once.
        results_path: the JSON Lines results file (created with its folder if missing).
        workers: worker processes (None: one per core); 0 runs in this process (tests, debugging).
            With Ray: at most this many rollouts at once (default: as many as the cluster takes).
        progress: a progress bar (rollouts done, success so far, ETA) on stderr.
        backend: "local" (a process pool on this machine) or "ray" (a Ray cluster; the
            optional `ray` extra). Records are appended here, by this process, either way.
        address: the Ray cluster's address (None or "local": start a Ray instance here).
        rollouts_per_worker: the local pool's workers are replaced after about this many
            rollouts each (the module docstring); fewer where most rollouts build a diagram
            of their own (`ditch-drake benchmark`: every generated ditch is new).

    Returns:
        What was skipped, recorded, and how long it took; `interrupted` and `exit_code` when
        Ctrl-C (KeyboardInterrupt) or SIGTERM stopped it, which it does not re-raise.

    Raises:
        ResultsError: the results file is of another schema or version.
        ConfigError: an unknown backend, a negative worker count, Ray asked for but not
            installed, a malformed or unreachable Ray address, a results file that cannot be
            written, or one that another run is writing (`common.files.exclusive_use`).
    """
    if backend not in BACKENDS:
        raise ConfigError(f"unknown backend {backend!r}; expected one of {list(BACKENDS)}")
    check_workers(workers)
    prepare_output(results_path, "results file")
    if backend == "ray":
        from ditch_drake.evaluation.ray_backend import check_address

        check_address(address)
    # Two runs on one file would each run (and append) the rollouts the other has not finished yet.
    with exclusive_use(results_path, "results file"):
        return _evaluate_locked(specs, results_path, workers, progress, backend, address, rollouts_per_worker)


def _evaluate_locked(specs: list[RolloutSpec], results_path: str | os.PathLike, workers: int | None,
                     progress: bool, backend: str, address: str | None,
                     rollouts_per_worker: int) -> EvaluationReport:
    """`evaluate`, once this process holds the results file."""
    start = time.perf_counter()
    existing, warnings = read_records(results_path)
    specs = spelled_as_recorded(specs, existing)
    done = finished_keys(existing)
    pending = list({spec.key: spec for spec in specs if spec.key not in done}.values())
    requested = {spec.key for spec in specs}
    report = EvaluationReport(str(results_path), requested=len(requested), skipped=len(requested & done),
                              warnings=warnings)
    local_workers = worker_count(workers)
    bar = tqdm(total=len(pending), desc="rollouts", disable=not progress, file=sys.stderr)

    def keep(writer: RecordWriter, record: RolloutRecord) -> None:
        with deferred_interrupts():
            writer.append(record)
            report.recorded += 1
            report.successes += record.success
            report.errors += record.status == "error"
        bar.update(1)
        bar.set_postfix(success=f"{report.successes}/{report.recorded}", errors=report.errors)
        # Every other rollout of the controller would read it too: the run stops, naming it.
        undeclared = f"{UndeclaredInputError.__name__}: "
        if record.status == "error" and record.error.startswith(undeclared):
            raise ConfigError(record.error.removeprefix(undeclared))
        # A module a rollout cannot import fails every other rollout the same way: the installation's
        # fault, not the rollout's; the run stops rather than fill the file with error records.
        if record.status == "error" and record.error.startswith(("ModuleNotFoundError: ", "ImportError: ")):
            raise ConfigError(f"a rollout could not import what it needs ({record.error}): the package's installation "
                              "is broken; reinstall it (`pip install -e .` in its checkout) and run the same command "
                              "again (the rollouts recorded are kept)")

    try:
        with terminate_as_interrupt(), RecordWriter(results_path) as writer:
            if not pending:
                pass
            elif backend == "ray":
                from ditch_drake.evaluation.ray_backend import run_on_ray

                run_on_ray(pending, address, workers, lambda record: keep(writer, record))
            elif local_workers == 0:
                for spec in pending:
                    keep(writer, run_rollout(spec))
            else:
                _run_in_pools(pending, local_workers, lambda record: keep(writer, record), rollouts_per_worker)
    except KeyboardInterrupt as error:
        report.interrupted = True
        report.exit_code = interrupt_exit_code(error)
    finally:
        bar.close()
    report.wall_s = time.perf_counter() - start
    return report


def _run_in_pools(pending: list[RolloutSpec], workers: int, keep,
                  rollouts_per_worker: int = ROLLOUTS_PER_WORKER) -> None:
    """Runs `pending` in process pools; see the module docstring for a worker that dies.

    A dead worker breaks its whole pool and fails every unfinished future, so which
    rollout killed it is unknown: the unfinished ones run again in a fresh pool, and after
    `_ATTEMPTS` broken pools each remaining rollout runs in a process of its own, where a
    death is its own and is recorded as its error.
    """
    broken_pools = 0
    while pending:
        isolated = broken_pools >= _ATTEMPTS
        chunk = workers * rollouts_per_worker
        batches = [[spec] for spec in pending] if isolated else [
            pending[i:i + chunk] for i in range(0, len(pending), chunk)]
        pending = []
        for batch in batches:
            died = _run_pool(batch, 1 if isolated else workers, keep)
            if died and isolated:
                keep(error_record(died[0], f"the worker process running it died ({broken_pools} pools broke before)"))
            elif died:
                pending += died
        broken_pools += bool(pending)


def _run_pool(specs: list[RolloutSpec], workers: int, keep) -> list[RolloutSpec]:
    """Runs `specs` in one pool, passing each record to `keep`; returns the specs a dead worker took down."""
    died = []
    with WorkerPool(min(workers, len(specs)), initializer=initialize_worker) as pool:
        futures = {pool.submit(run_rollout, spec): spec for spec in specs}
        for future in as_completed(futures):
            try:
                record = future.result()
            except BrokenProcessPool:
                died.append(futures[future])
                continue
            keep(record)
    return died


def load_results(paths: list[str | os.PathLike]) -> list[RolloutRecord]:
    """Every record of the given results files, or of the *.jsonl files in given folders."""
    records = []
    for path in paths:
        path = Path(path)
        files = sorted(path.glob("**/*.jsonl")) if path.is_dir() else [path]
        for file in files:
            records += read_records(file)[0]
    return records
