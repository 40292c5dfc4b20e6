"""The paper's experiments as data: collect, train, evaluate and report, each stage resumable.

An experiment YAML (`experiments/paper.yaml`) names the studies of the paper (section 5,
docs/design.md, "The experiments"): scalability (10/20/40 demonstrations, evaluated in the training
environment), generalization (each 40-demonstration model in the other environments),
baseline (the DWA in every environment), amalgam (one model trained on several
environments, evaluated in another), must_cross (issue 20: the classical controllers and
the learned models, like for like, in walled environments where every route crosses the
ditch) and shared_control (an ensemble of clones gated by its uncertainty, with a fallback
where it is unsure, beside the ensemble alone and random handover at the same budget; and
optionally one round of learning from the handovers, `AggregationRound`).
`run_experiment` turns it into work:

1. collect: `collect` the missing demonstrations of every environment a model trains on;
2. train: every distinct model (environments, number of demonstrations, ensemble members),
   skipping a finished checkpoint and resuming an interrupted one (a single clone from its
   `.resume` file, an ensemble from its finished members); a clone retrained after the
   aggregation round first runs the round where it is unfinished (its clone's signals file,
   then its gated episodes, each resumable);
3. evaluate: the signals files the shared-control gates are calibrated on, where missing
   (`<results_dir>/gate/<model>.npz`, resumable as `ditch-drake gate-signals`), then every
   study's rollouts, appended to `<results_dir>/<study>.jsonl` (finished rollouts are skipped);
   then the shared-control study's part on a benchmark split, if it has one (`SplitGating`:
   its signals file on a split a choice may be made on, its rollouts on another);
4. report: `ditch_drake.evaluation.report.write_report` over the results.

`only` restricts every stage to the models and evaluations that involve the named
environments (a walled environment involves the open one it is based on: `--only wide`
keeps `wide_walled`'s evaluations), so the protocol can also be completed in parts. Each
stage's wall time is returned, printed, and recorded in `<results_dir>/experiment_runs.json`,
which the report shows.
"""

import datetime
import functools
import json
import math
import os
import platform
import time
import typing
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

from ditch_drake.common.config_yaml import load_typed_yaml
from ditch_drake.common.errors import ConfigError
from ditch_drake.common.outputs import figures_beside
from ditch_drake.common.parallel import check_workers
from ditch_drake.common.progress import log_progress
from ditch_drake.evaluation.results import RolloutSpec
from ditch_drake.evaluation.runs import record_run
from ditch_drake.learning.config import BALANCING_METHODS, SHARED_STEPS
from ditch_drake.pipelines.stages import (
    collect_demonstrations,
    pass_on_stop,
    record_signals_or_resume,
    train_ensemble_or_resume,
    train_or_resume,
    training_device,
    training_precision,
)
from ditch_drake.world.environments import environment_names, get_environment, load_environments


@dataclass
class TrainingSettings:
    """`ditch-drake train` settings shared by every model of the experiment (see `TrainConfig`).

    `precision`: "auto" (`available_precision`: bf16 on a CPU that runs it natively), "fp32"
    or "bf16". `balancing`: one of `BALANCING_METHODS` (`ditch_drake.learning.balance`).
    """

    epochs: int = 8
    patience: int = 4
    batches_per_epoch: int = 96
    synthetic_fraction: float = 0.5
    precision: str = "auto"
    balancing: str = "smote"


@dataclass
class ScalabilityStudy:
    """Models trained on the first N demonstrations, evaluated in their own environment."""

    environments: list[str] = field(default_factory=list)
    demos: list[int] = field(default_factory=lambda: [10, 20, 40])


@dataclass
class GeneralizationStudy:
    """Each environment's model (`demos` demonstrations) evaluated in the other environments."""

    environments: list[str] = field(default_factory=list)
    demos: int = 40


@dataclass
class BaselineStudy:
    """A classical controller in each environment.

    Attributes:
        environments: where it runs.
        controller: its config with all its parameters, written with its YAML tag (e.g.
            `!DwaBaselineConfig {planner: {costmap: {lethal_slope_deg: 60}}}`); None: the DWA baseline's defaults.
    """

    environments: list[str] = field(default_factory=list)
    controller: typing.Any = None


@dataclass
class AmalgamStudy:
    """One model trained on several environments together, evaluated elsewhere."""

    train: list[str] = field(default_factory=list)
    evaluate: list[str] = field(default_factory=list)
    demos: int = 40


@dataclass
class MustCrossStudy:
    """Like for like where the ditch cannot be bypassed (issue 20): results in `must_cross.jsonl`.

    In each walled environment (fenced so that every route crosses the ditch; its
    `Environment.based_on` names the open environment it is made from) run each of
    `controllers`, the shipped learned model of its base environment (`shipped_models`), and
    the paper-method model of its base environment (`<models_dir>/<base>_<demos>.pt`, the
    experiment's own, trained on the base's first `demos` demonstrations: the same file the
    generalization study trains, trained by the train stage when missing). Each of
    `open_controllers` also runs in each of `open_environments` (`learned`: that environment's
    shipped model), on the same seeds, so the open field stands beside the walled one.

    Attributes:
        environments: the walled environments (each must name the environment it is based on).
        controllers: registered controller names run in every walled environment.
        shipped_models: run the learned controller with no checkpoint (its environment's
            base's shipped model) in every walled environment.
        demos: the paper-method models' demonstrations per model (0: no such models).
        open_environments: open environments where `open_controllers` run.
        open_controllers: registered controller names run in every open environment.
    """

    environments: list[str] = field(default_factory=list)
    controllers: list[str] = field(default_factory=lambda: ["dwa", "dwa_paper"])
    shipped_models: bool = True
    demos: int = 40
    open_environments: list[str] = field(default_factory=list)
    open_controllers: list[str] = field(default_factory=lambda: ["dwa_paper"])


PAPER_ENVIRONMENTS = ["crater", "wide", "narrow", "sine"]
# The fallbacks a batch evaluation can run (`teleop` needs a person at a Meshcat).
STUDY_FALLBACKS = ("expert", "mppi")


@dataclass
class AggregationRound:
    """One round of learning from the gate's handovers (ThriftyDAgger-style), on each
    environment's single paper-method clone (`<models_dir>/<env>_<demos>.pt`, the
    generalization study's file): the clone, gated by `signal` at `budget` with `fallback`
    taking over, drives `rollouts` episodes on training seeds (as `ditch-drake collect --shared`,
    into `<demos_dir>/handovers/<env>_<demos>`, each step flagged where the fallback drove),
    and a clone is retrained on the first `demos` demonstrations and those episodes for each
    weight of `intervention_weights` (`<env>_<demos>_round_w<W>.pt`, as `ditch-drake train
    --intervention-weight W`: 1 is uniform aggregation, above 1 Sirius-style weighting). With
    "expert" among `labels` the same episodes are recorded again with the expert's label at
    every step (`collect --shared-labels expert`, into `..._expert`) and a clone retrained on
    them for each weight too (`<env>_<demos>_round_expert_w<W>.pt`). The study then evaluates
    the clone and each retrained one ungated, on its test seeds.

    The gate's budget is calibrated on the clone's own validation rollouts (the study's
    calibration seeds; `<results_dir>/gate/<env>_<demos>_risk.npz` with the tip-risk signals
    for a risk signal, as `ditch-drake gate-signals --risk`).

    Attributes:
        signal: what the gate reads on one clone: a risk signal ("tip_risk_ahead",
            "tip_risk_now", deg) or "mean_softmax_entropy" (nats); a disagreement signal needs
            an ensemble.
        budget: the share of control steps the fallback may drive, in (0, 1).
        fallback: who takes over, and labels the steps it drove: "expert" or "mppi".
        rollouts: gated episodes per environment.
        seed: the first episode's seed (training seeds: apart from the calibration's and the
            test seeds).
        intervention_weights: one retrained clone per weight, each > 0 (dimensionless; 1 uniform).
        labels: the labels the round's steps are retrained on, some of `SHARED_LABELS`:
            "executed" (what the robot did: the clone's where it drove, the fallback's where it
            took over) and "expert" (the expert fallback's answer at every step).
        shared_steps: which of the round's steps each retrained clone learns from, some of
            `SHARED_STEPS` (as `train --shared-steps`): "all" (Sirius) and "interventions" (only
            the steps the fallback drove: HG-DAgger, ThriftyDAgger; named `..._interventions_w<W>`).
    """

    signal: str = "tip_risk_ahead"
    budget: float = 0.1
    fallback: str = "expert"
    rollouts: int = 20
    seed: int = 20000
    intervention_weights: list[float] = field(default_factory=lambda: [1.0, 3.0])
    labels: list[str] = field(default_factory=lambda: ["executed"])
    shared_steps: list[str] = field(default_factory=lambda: ["all"])


@dataclass
class SplitGating:
    """The shared-control study of one policy on a benchmark split (the generalist ensemble on
    the test split), beside the paper's ditches: its signals file recorded on another split's
    ditches (`<results_dir>/gate/<policy>_<calibration_split>.npz`, as `ditch-drake gate-signals
    --split`), then on `split`'s ditches the policy alone and, for each budget and fallback, the
    gate on the study's signal and random handover at the same budget (as `ditch-drake
    benchmark --split`): results in `<results_dir>/shared_control_<split>.jsonl`, its ditches
    beside it. Episodes last the experiment's `time_limit_s`, as the benchmark's do on these
    splits (120 s).

    Attributes:
        checkpoint: the gated policy, a shipped name or a .pt file (an ensemble for a
            disagreement signal).
        calibration_split: whose ditches set the thresholds: one a choice may be made on
            (`CHOICE_SPLITS`: train, val, search_val).
        calibration_geometries: that split's first N ditches (None: all).
        split: where it is measured (e.g. "test", held out).
        geometries: that split's first N ditches (None: all).
        seed: the rollout seed of every ditch and task, one rollout each, for both splits.
        budgets: shares of control steps the fallback may drive, each in (0, 1).
        fallbacks: who takes over, each "expert" or "mppi".
        signal: what its gates read ("": the study's `signal`): an uncertainty signal, or a
            risk signal ("tip_risk_ahead", "tip_risk_now"; its signals file then recorded with
            `--risk`, `<policy>_<calibration_split>_risk.npz`).
    """

    checkpoint: str = "generalist_k5"
    calibration_split: str = "val"
    calibration_geometries: int | None = None
    split: str = "test"
    geometries: int | None = None
    seed: int = 0
    budgets: list[float] = field(default_factory=lambda: [0.02])
    fallbacks: list[str] = field(default_factory=lambda: ["expert", "mppi"])
    signal: str = ""

    def gate_signal(self, study: "SharedControlStudy") -> str:
        """The signal its gates read."""
        return self.signal or study.signal


@dataclass
class SharedControlStudy:
    """An ensemble gated by its uncertainty, with a fallback where it is unsure, against the
    ensemble alone and against random handover at the same budget: results in
    `shared_control.jsonl` (docs/concepts/controllers.md, "Shared control").

    Per environment: the ensemble of `ensemble` paper-method clones, each on a bootstrap
    resample of the environment's first `demos` demonstrations (`<models_dir>/<env>_<demos>_k<K>.pt`,
    as `ditch-drake train --ensemble K`; with K = 1 the single clone `<env>_<demos>.pt`); the
    signals file of its own ungated validation rollouts (`<results_dir>/gate/<model>.npz`, as
    `ditch-drake gate-signals`), which the gates' budgets are calibrated on; and the rollouts,
    on seeds `seed`, .. (the experiment's `rollouts` per task): the ensemble alone, and for each
    budget and fallback the gate on `signal` and the gate on a seeded random draw (signal
    "random") at the same budget.

    Attributes:
        environments: where the ensembles are trained and evaluated, each in its own.
        demos: demonstrations per model (the first ones of the environment's folder).
        ensemble: K, clones per ensemble (>= 2 for a disagreement signal).
        signal: the signal the gate reads (`ditch_drake.learning.uncertainty`): an uncertainty
            signal (rad/s for "angular_rate_spread", nats for the entropies), or a risk signal
            ("tip_risk_ahead", "tip_risk_now"; deg), whose signals files are then recorded with
            the tip-risk signals (`--risk`, `<model>_risk.npz`).
        budgets: shares of control steps the fallback may drive, each in (0, 1) (dimensionless).
        fallbacks: who takes over, each "expert" or "mppi".
        calibration_rollouts: seeded ungated rollouts per task recorded for the signals file.
        calibration_seed: the first seed of those rollouts (validation seeds).
        seed: the first seed of the study's rollouts (test seeds: they must not overlap the
            calibration's).
        random_lower_threshold: the random gate's lower threshold on its draw in [0, 1)
            (dimensionless); its upper one is set by the budget.
        calm_steps: control steps (0.1 s each) the signal must stay below the lower threshold
            before a gate hands back, for both gates (and the aggregation round's).
        progress_limit_s: None, or a watchdog beside both gates (the signal's and random
            handover, so the control keeps it too) and the split part's: the fallback also
            takes over after this many seconds without progress toward the goal (s;
            `SharedControlConfig.progress_limit_s`).
        regress_limit_m: None, or a second watchdog, the same way: once the robot has fallen
            back this far from the goal since it last came nearer (m;
            `SharedControlConfig.regress_limit_m`).
        aggregation: None, or one round of learning from the handovers (`AggregationRound`).
        split: None, or the same gates around one policy on a benchmark split (`SplitGating`),
            run with the study unless `--only` names environments.
    """

    environments: list[str] = field(default_factory=lambda: list(PAPER_ENVIRONMENTS))
    demos: int = 40
    ensemble: int = 5
    signal: str = "angular_rate_spread"
    budgets: list[float] = field(default_factory=lambda: [0.01, 0.02, 0.05, 0.1, 0.2])
    fallbacks: list[str] = field(default_factory=lambda: ["expert", "mppi"])
    calibration_rollouts: int = 10
    calibration_seed: int = 0
    seed: int = 300
    random_lower_threshold: float = 0.8
    calm_steps: int = 5
    progress_limit_s: float | None = None
    regress_limit_m: float | None = None
    aggregation: AggregationRound | None = None
    split: SplitGating | None = None


@dataclass
class Studies:
    scalability: ScalabilityStudy | None = None
    generalization: GeneralizationStudy | None = None
    baseline: BaselineStudy | None = None
    amalgam: AmalgamStudy | None = None
    must_cross: MustCrossStudy | None = None
    shared_control: SharedControlStudy | None = None


@dataclass
class ExperimentConfig:
    """An experiment file.

    Attributes:
        name: names the report.
        environments_file: a YAML file of environments (packaged schema) that the studies may name
            besides the packaged ones ("": the packaged ones only).
        seed: the seed of collection, training and the first rollout.
        demos_dir: demonstrations, one folder per environment.
        models_dir: trained checkpoints.
        results_dir: results files, one per study.
        report: the report's Markdown file (empty: `report.md` in `results_dir`); its figures go
            to `figures_dir`.
        figures_dir: PNG figures (empty: `report_img` beside the report).
        tasks: task indices evaluated in every environment (empty: all).
        rollouts: seeded rollouts per task.
        time_limit_s: the episode timeout (s).
        workers: worker processes (None: one per core; 0: in this process).
        training: training settings.
        studies: what to run.
    """

    name: str = "experiment"
    environments_file: str = ""
    seed: int = 0
    demos_dir: str = "data/demos"
    models_dir: str = "models"
    results_dir: str = "results"
    report: str = ""
    figures_dir: str = ""
    tasks: list[int] = field(default_factory=list)
    rollouts: int = 10
    time_limit_s: float = 120.0
    workers: int | None = None
    training: TrainingSettings = field(default_factory=TrainingSettings)
    studies: Studies = field(default_factory=Studies)


@dataclass(frozen=True)
class ModelSpec:
    """A model to train: its environments and the first `demos` demonstrations of each, and
    `ensemble` clones (K > 1: an ensemble, `ditch_drake.learning.ensemble_training`).
    `intervention_weight`: None, or a single clone retrained after the shared-control study's
    aggregation round with this weight on the fallback's steps (`AggregationRound`), on the
    round's steps labelled as `round_labels` says, those of them `round_steps` keeps."""

    environments: tuple[str, ...]
    demos: int
    ensemble: int = 1
    intervention_weight: float | None = None
    round_labels: str = "executed"
    round_steps: str = "all"

    @property
    def name(self) -> str:
        name = f"{'+'.join(self.environments)}_{self.demos}"
        if self.intervention_weight is not None:
            labels = "" if self.round_labels == "executed" else f"_{self.round_labels}"
            steps = "" if self.round_steps == "all" else f"_{self.round_steps}"
            return f"{name}_round{labels}{steps}_w{self.intervention_weight:g}"
        return f"{name}_k{self.ensemble}" if self.ensemble > 1 else name

    @property
    def before_the_round(self) -> "ModelSpec":
        """The clone the aggregation round gates (itself if this is not a retrained one)."""
        return replace(self, intervention_weight=None, round_labels="executed", round_steps="all")


def load_experiment(path: str | os.PathLike) -> ExperimentConfig:
    """Reads and checks an experiment file.

    Raises:
        ConfigError: unreadable or malformed YAML, an unknown key (a typo), or an unknown
            environment, naming the file and the value.
    """
    from ditch_drake.diagrams.controllers import controller_config_types

    path = Path(path)
    # The baseline may be any registered controller: its config is one of theirs, by YAML tag.
    options = typing.Union[controller_config_types()]  # noqa: UP007  (built from the registry at run time)
    BaselineStudy.__dataclass_fields__["controller"].type = typing.Optional[options]  # noqa: UP045
    config = load_typed_yaml(path, ExperimentConfig, "experiment file")
    known = set(environment_names(variants=True))
    if config.environments_file:
        known |= set(load_environments(config.environments_file))
    named = list(_study_environments(config))
    unknown = sorted({env for _, env in named if env not in known})
    if unknown:
        keys = sorted({key for key, env in named if env not in known})
        raise ConfigError(f"experiment file {path} names unknown environments {unknown} ({', '.join(keys)}); "
                          f"expected some of {sorted(known)}")
    if config.rollouts < 1 or not 0 < config.time_limit_s < math.inf:
        raise ConfigError(f"experiment file {path}: rollouts={config.rollouts} must be >= 1 and "
                          f"time_limit_s={config.time_limit_s} finite and positive")
    check_workers(config.workers, f"experiment file {path}: workers")
    _check_must_cross(config, path)
    _check_shared_control(config, path)
    if config.training.precision not in ("auto", "fp32", "bf16"):
        raise ConfigError(f"experiment file {path}: training.precision={config.training.precision!r} must be "
                          "'auto', 'fp32' or 'bf16'")
    if config.training.balancing not in BALANCING_METHODS:
        raise ConfigError(f"experiment file {path}: training.balancing={config.training.balancing!r}: expected one "
                          f"of {list(BALANCING_METHODS)}")
    return config


def _check_must_cross(config: ExperimentConfig, path: Path) -> None:
    """Refuses a must_cross study naming an unknown controller, an open environment among the
    walled ones, a walled environment without a shipped model when `shipped_models` asks for
    them, or a negative number of demonstrations (environment names are checked before), so
    that the evaluate stage cannot fail on it after hours of training."""
    from ditch_drake.diagrams.controllers import controller_names
    from ditch_drake.learning.checkpoint import environment_model

    study = config.studies.must_cross
    if study is None:
        return
    unknown = sorted({name for name in study.controllers + study.open_controllers if name not in controller_names()})
    if unknown:
        raise ConfigError(f"experiment file {path}: studies.must_cross names unknown controllers {unknown}; "
                          f"expected some of {controller_names()}")
    open_ = [env for env in study.environments if base_environment(config, env) == env]
    if open_:
        raise ConfigError(f"experiment file {path}: studies.must_cross.environments {open_} are not walled variants "
                          "(their environments name no `based_on`); put open environments under open_environments")
    if study.demos < 0:
        raise ConfigError(f"experiment file {path}: studies.must_cross.demos={study.demos} must be >= 0")
    for env in study.environments if study.shipped_models else []:
        try:
            environment_model(env, config.environments_file)
        except ConfigError as error:
            raise ConfigError(f"experiment file {path}: studies.must_cross.shipped_models: {error}") from error


def _is_integer(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_share(value) -> bool:
    """A share of control steps strictly between 0 and 1, as a budget is."""
    return not isinstance(value, bool) and isinstance(value, (int, float)) and 0.0 < value < 1.0


def _check_shared_control(config: ExperimentConfig, path: Path) -> None:
    """Refuses a shared_control study whose evaluations could not run (environment names are
    checked before), naming the key: a signal that is neither an uncertainty nor a risk
    signal, a disagreement signal with K < 2, a watchdog limit that is not a positive number, a
    budget outside (0, 1), an unknown fallback (or `teleop`, which needs a person at a Meshcat),
    non-positive counts, negative seeds, test seeds among the calibration's, or a random gate its
    budget cannot hold (`SharedControlConfig.validate`)."""
    from ditch_drake.learning.uncertainty import DISAGREEMENT_SIGNALS, RISK_SIGNALS, UNCERTAINTY_SIGNALS

    study = config.studies.shared_control
    if study is None:
        return
    where = f"experiment file {path}: studies.shared_control"

    if study.signal not in (*UNCERTAINTY_SIGNALS, *RISK_SIGNALS):
        raise ConfigError(f"{where}.signal={study.signal!r}: expected one of {[*UNCERTAINTY_SIGNALS, *RISK_SIGNALS]} "
                          "(random handover runs beside it anyway)")
    if not _is_integer(study.ensemble) or study.ensemble < 1:
        raise ConfigError(f"{where}.ensemble={study.ensemble!r}: expected an integer >= 1 clones")
    if study.signal in DISAGREEMENT_SIGNALS and study.ensemble < 2:
        raise ConfigError(f"{where}.ensemble={study.ensemble}: the signal {study.signal!r} is the members' "
                          "disagreement; expected K >= 2")
    for key in ("demos", "calibration_rollouts", "calm_steps"):
        if not _is_integer(getattr(study, key)) or getattr(study, key) < 1:
            raise ConfigError(f"{where}.{key}={getattr(study, key)!r}: expected an integer >= 1")
    for key in ("seed", "calibration_seed"):
        if not _is_integer(getattr(study, key)) or getattr(study, key) < 0:
            raise ConfigError(f"{where}.{key}={getattr(study, key)!r}: expected an integer >= 0")
    calibration = range(study.calibration_seed, study.calibration_seed + study.calibration_rollouts)
    tests = range(study.seed, study.seed + config.rollouts)
    if calibration.start < tests.stop and tests.start < calibration.stop:
        raise ConfigError(f"{where}.seed={study.seed}: its seeds {study.seed}-{tests.stop - 1} overlap the "
                          f"calibration's {calibration.start}-{calibration.stop - 1} (calibration_seed, "
                          "calibration_rollouts); expected test seeds that the thresholds never saw")
    if study.aggregation:
        _check_aggregation(study, where, tests, calibration)
    _check_watchdogs(study, where)
    _check_gates(study, where, study.budgets, study.fallbacks)
    if study.split:
        _check_split_gating(study, f"{where}.split")


def _check_watchdogs(study: SharedControlStudy, where: str) -> None:
    """Refuses a watchdog limit that a gate would refuse (`SharedControlConfig.validate`), naming
    the study's key."""
    from ditch_drake.systems.shared_control import WATCHDOGS, SharedControlConfig

    for key in WATCHDOGS.values():
        limit = getattr(study, key)
        if limit is None:
            continue
        try:  # The study's signal is checked before, so only the limit can be refused here.
            SharedControlConfig(signal=study.signal, budget=0.5, calibration="calibration.npz",
                                **{key: limit}).validate()
        except ConfigError as error:
            raise ConfigError(f"{where}.{key}={limit!r}: {error}") from error


def _check_gates(study: SharedControlStudy, where: str, budgets: list[float], fallbacks: list[str],
                 signal: str = "") -> None:
    """Refuses budgets outside (0, 1), unknown fallbacks (or none), and random handover at a
    budget that the study's hysteresis cannot hold (`SharedControlConfig.validate`)."""
    bad = [b for b in budgets if not _is_share(b)]
    if bad or not budgets:
        raise ConfigError(f"{where}.budgets={budgets!r}: expected shares of control steps in (0, 1)")
    bad = [fallback for fallback in fallbacks if fallback not in STUDY_FALLBACKS]
    if bad or not fallbacks:
        raise ConfigError(f"{where}.fallbacks={fallbacks!r}: expected some of {list(STUDY_FALLBACKS)}")
    for gate in study_gates(study, "calibration.npz", budgets, fallbacks, signal):
        try:
            gate.validate()
        except ConfigError as error:
            raise ConfigError(f"{where}: random handover at budget {gate.budget} with random_lower_threshold "
                              f"{study.random_lower_threshold} and calm_steps {study.calm_steps}: {error}") from error


def _check_split_gating(study: SharedControlStudy, where: str) -> None:
    """Refuses a split part whose calibration split is held out (a gate's thresholds are a
    choice), an unknown split or signal, a policy that does not load (or a single clone for a
    disagreement signal), geometries out of range, a bad seed, or bad gates (`_check_gates`)."""
    from ditch_drake.benchmark.splits import check_split, split_seeds
    from ditch_drake.common.seeds import check_seed
    from ditch_drake.evaluation.batch import check_checkpoint
    from ditch_drake.learning.inference import is_ensemble
    from ditch_drake.learning.uncertainty import DISAGREEMENT_SIGNALS, RISK_SIGNALS, UNCERTAINTY_SIGNALS
    from ditch_drake.world.ditch_splits import CHOICE_SPLITS

    part = study.split
    signal = part.gate_signal(study)
    if signal not in (*UNCERTAINTY_SIGNALS, *RISK_SIGNALS):
        raise ConfigError(f"{where}.signal={part.signal!r}: expected one of {[*UNCERTAINTY_SIGNALS, *RISK_SIGNALS]} "
                          "(random handover runs beside it anyway), or '' for the study's")
    if part.calibration_split not in CHOICE_SPLITS:
        raise ConfigError(f"{where}.calibration_split={part.calibration_split!r}: the gate's thresholds are a choice; "
                          f"expected one of {list(CHOICE_SPLITS)}")
    try:
        check_split(part.split)
        for split, geometries in ((part.calibration_split, part.calibration_geometries),
                                  (part.split, part.geometries)):
            split_seeds(split, geometries)
        if not _is_integer(part.seed):
            raise ConfigError(f"seed {part.seed!r}: expected an integer >= 0")
        check_seed(part.seed, 1)
        check_checkpoint(part.checkpoint)
    except ConfigError as error:
        raise ConfigError(f"{where}: {error}") from error
    if signal in DISAGREEMENT_SIGNALS and not is_ensemble(part.checkpoint):
        raise ConfigError(f"{where}.checkpoint={part.checkpoint!r}: a single clone, and the signal {signal!r} is "
                          "the members' disagreement; expected an ensemble")
    _check_gates(study, where, part.budgets, part.fallbacks, signal)


def _check_aggregation(study: SharedControlStudy, where: str, tests: range, calibration: range) -> None:
    """Refuses an aggregation round naming a signal one clone cannot give (a disagreement
    signal), a bad budget, fallback or count, weights that are not positive numbers, or
    episode seeds among the calibration's or the test seeds."""
    from ditch_drake.demos.collect import SHARED_LABELS
    from ditch_drake.learning.uncertainty import DISAGREEMENT_SIGNALS, RISK_SIGNALS, UNCERTAINTY_SIGNALS

    round_ = study.aggregation
    where = f"{where}.aggregation"
    signals = [name for name in (*UNCERTAINTY_SIGNALS, *RISK_SIGNALS) if name not in DISAGREEMENT_SIGNALS]
    if round_.signal not in signals:
        raise ConfigError(f"{where}.signal={round_.signal!r}: expected one a single clone gives, one of {signals}")
    if round_.fallback not in STUDY_FALLBACKS:
        raise ConfigError(f"{where}.fallback={round_.fallback!r}: expected one of {list(STUDY_FALLBACKS)}")
    if not _is_share(round_.budget):
        raise ConfigError(f"{where}.budget={round_.budget!r}: expected a share of control steps in (0, 1)")
    for key, least in (("rollouts", 1), ("seed", 0)):
        value = getattr(round_, key)
        if not _is_integer(value) or value < least:
            raise ConfigError(f"{where}.{key}={value!r}: expected an integer >= {least}")
    weights = round_.intervention_weights
    if not weights or any(isinstance(w, bool) or not isinstance(w, (int, float)) or not 0 < w < math.inf
                          for w in weights):
        raise ConfigError(f"{where}.intervention_weights={weights!r}: expected positive finite loss weights (1: "
                          "uniform aggregation)")
    if not round_.labels or any(labels not in SHARED_LABELS for labels in round_.labels):
        raise ConfigError(f"{where}.labels={round_.labels!r}: expected some of {list(SHARED_LABELS)}")
    if not round_.shared_steps or any(steps not in SHARED_STEPS for steps in round_.shared_steps):
        raise ConfigError(f"{where}.shared_steps={round_.shared_steps!r}: expected some of {list(SHARED_STEPS)}")
    if "expert" in round_.labels and round_.fallback != "expert":
        raise ConfigError(f"{where}.labels={round_.labels!r} with fallback {round_.fallback!r}: the expert's labels "
                          "come from the expert fallback; expected fallback 'expert'")
    episodes = range(round_.seed, round_.seed + round_.rollouts)
    for seeds, what in ((tests, "the study's test seeds"), (calibration, "the calibration's")):
        if episodes.start < seeds.stop and seeds.start < episodes.stop:
            raise ConfigError(f"{where}.seed={round_.seed}: its seeds {episodes.start}-{episodes.stop - 1} overlap "
                              f"{what} {seeds.start}-{seeds.stop - 1}; expected training seeds of their own")


def _study_environments(config: ExperimentConfig):
    """(key, environment) for every environment a study names."""
    studies = config.studies
    for key in ("scalability", "generalization", "baseline", "shared_control"):
        study = getattr(studies, key)
        yield from ((f"studies.{key}.environments", env) for env in (study.environments if study else []))
    if studies.amalgam:
        yield from (("studies.amalgam.train", env) for env in studies.amalgam.train)
        yield from (("studies.amalgam.evaluate", env) for env in studies.amalgam.evaluate)
    if studies.must_cross:
        yield from (("studies.must_cross.environments", env) for env in studies.must_cross.environments)
        yield from (("studies.must_cross.open_environments", env) for env in studies.must_cross.open_environments)


def study_gates(study: SharedControlStudy, calibration: str, budgets: list[float] | None = None,
                fallbacks: list[str] | None = None, signal: str = "") -> list:
    """The gates of a shared-control study (`SharedControlConfig`s), for each budget and each
    fallback (the study's, or `budgets` and `fallbacks`): the gate on `study.signal` (or
    `signal`) with thresholds from the budget on `calibration` (a signals file), then random
    handover at the same budget; both with the study's watchdogs, where it sets them."""
    from ditch_drake.systems.shared_control import RANDOM_SIGNAL, WATCHDOGS, SharedControlConfig

    watchdogs = {key: getattr(study, key) for key in WATCHDOGS.values()}
    gates = []
    for budget in study.budgets if budgets is None else budgets:
        for fallback in study.fallbacks if fallbacks is None else fallbacks:
            gates += [SharedControlConfig(signal=signal or study.signal, budget=budget, calibration=calibration,
                                          calm_steps=study.calm_steps, fallback=fallback, **watchdogs),
                      SharedControlConfig(signal=RANDOM_SIGNAL, budget=budget, calm_steps=study.calm_steps,
                                          lower_threshold=study.random_lower_threshold, fallback=fallback,
                                          **watchdogs)]
    return gates


def base_environment(config: ExperimentConfig, environment: str) -> str:
    """The open environment a walled `environment` is made from (`Environment.based_on`), else
    `environment` itself.

    Raises:
        ConfigError: an unknown environment.
    """
    found = get_environment(environment, config.environments_file or None)
    return found.based_on or environment


@dataclass(frozen=True)
class Evaluation:
    """One study's rollouts of one controller in one environment.

    `controller` is a registered controller's name; `model` the learned controller's
    checkpoint to train and use (None: a classical controller, or for "learned" the
    environment's shipped model, `checkpoint.environment_model`). `config`: the controller's
    config, which names its checkpoint (None: `controller`'s defaults with `model`'s).
    `seed`: the first rollout's seed (None: the experiment's).
    """

    study: str
    controller: str
    model: ModelSpec | None
    environment: str
    config: typing.Any = field(default=None, hash=False)
    seed: int | None = None


def study_names() -> list[str]:
    """The studies an experiment file may hold, in pipeline order."""
    return [f.name for f in fields(Studies)]


def plan(config: ExperimentConfig, only: list[str] | None = None,
         only_studies: list[str] | None = None) -> tuple[list[ModelSpec], list[Evaluation]]:
    """The models to train and the evaluations to run, restricted to `only`'s environments and
    to the studies `only_studies` names (None: all).

    An evaluation is kept when its environment, the open environment that one is based on, or
    one of its model's environments is in `only`; a model when a kept evaluation uses it.

    Raises:
        ConfigError: a study names an unknown environment (`load_experiment` refuses those).
    """
    studies = config.studies
    evaluations: list[Evaluation] = []
    if studies.scalability:
        for env in studies.scalability.environments:
            for demos in studies.scalability.demos:
                evaluations.append(Evaluation("scalability", "learned", ModelSpec((env,), demos), env))
    if studies.generalization:
        environments = studies.generalization.environments
        for trained in environments:
            for env in environments:
                if env != trained:
                    model = ModelSpec((trained,), studies.generalization.demos)
                    evaluations.append(Evaluation("generalization", "learned", model, env))
    if studies.baseline:
        for env in studies.baseline.environments:
            evaluations.append(Evaluation("baseline", "dwa", None, env))
    if studies.amalgam:
        model = ModelSpec(tuple(studies.amalgam.train), studies.amalgam.demos)
        for env in studies.amalgam.evaluate:
            evaluations.append(Evaluation("amalgam", "learned", model, env))
    if studies.must_cross:
        study = studies.must_cross
        for env in study.environments:
            evaluations += [Evaluation("must_cross", controller, None, env) for controller in study.controllers]
            if study.shipped_models:
                evaluations.append(Evaluation("must_cross", "learned", None, env))
            if study.demos:
                model = ModelSpec((base_environment(config, env),), study.demos)
                evaluations.append(Evaluation("must_cross", "learned", model, env))
        for env in study.open_environments:
            evaluations += [Evaluation("must_cross", controller, None, env) for controller in study.open_controllers]
    if studies.shared_control:
        evaluations += _shared_control_evaluations(config, studies.shared_control)

    if only_studies is not None:
        evaluations = [e for e in evaluations if e.study in only_studies]
    if only is not None:
        bases = {env: base_environment(config, env) for env in {e.environment for e in evaluations}}
        evaluations = [e for e in evaluations if any(
            env in only for env in (e.environment, bases[e.environment], *(e.model.environments if e.model else ())))]
    models = list(dict.fromkeys(e.model for e in evaluations if e.model is not None))
    return models, evaluations


def _shared_control_evaluations(config: ExperimentConfig, study: SharedControlStudy) -> list[Evaluation]:
    """Per environment: its ensemble alone, then `study_gates` around it, on the study's seeds."""
    from ditch_drake.diagrams.rollout import LearnedPolicyConfig
    from ditch_drake.diagrams.shared_controller import SharedControlControllerConfig

    evaluations = []
    for env in study.environments:
        model = ModelSpec((env,), study.demos, study.ensemble)
        policy = LearnedPolicyConfig(checkpoint=str(model_path(config, model)))
        evaluations.append(Evaluation("shared_control", "learned", model, env, policy, study.seed))
        evaluations += [Evaluation("shared_control", "shared", model, env,
                                   SharedControlControllerConfig(policy=policy, gate=gate), study.seed)
                        for gate in study_gates(study, str(gate_signals_path(config, model)))]
        if study.aggregation:  # The clone before the round (unless it is the model above) and after it.
            clone = ModelSpec((env,), study.demos)
            retrained = [replace(clone, intervention_weight=float(w), round_labels=labels, round_steps=steps)
                         for labels in study.aggregation.labels for steps in study.aggregation.shared_steps
                         for w in study.aggregation.intervention_weights]
            evaluations += [Evaluation("shared_control", "learned", m, env,
                                       LearnedPolicyConfig(checkpoint=str(model_path(config, m))), study.seed)
                            for m in ([clone] if clone != model else []) + retrained]
    return evaluations


def model_path(config: ExperimentConfig, model: ModelSpec) -> Path:
    return Path(config.models_dir) / f"{model.name}.pt"


def _signals_file(config: ExperimentConfig, stem: str, signal: str) -> Path:
    """`<results_dir>/gate/<stem>.npz`, the recording a gate on `signal` is calibrated on; for a
    risk signal `<stem>_risk.npz`, recorded with the tip-risk signals beside the others."""
    from ditch_drake.learning.uncertainty import RISK_SIGNALS

    return Path(config.results_dir) / "gate" / f"{stem}{'_risk' if signal in RISK_SIGNALS else ''}.npz"


def gate_signals_path(config: ExperimentConfig, model: ModelSpec) -> Path:
    """The signals file of `model`'s own validation rollouts, which its gates are calibrated on
    (`_signals_file` of the study's signal)."""
    return _signals_file(config, model.name, config.studies.shared_control.signal)


def round_signals_path(config: ExperimentConfig, clone: ModelSpec) -> Path:
    """The signals file the aggregation round's gate on `clone` is calibrated on: the clone's
    own validation rollouts (`<clone>.npz`) for an uncertainty signal, with the tip-risk
    signals beside the others (`<clone>_risk.npz`) for a risk signal. Where the clone is the
    study's model and its gates read the same kind, it is their file (`gate_signals_path`)."""
    return _signals_file(config, clone.name, config.studies.shared_control.aggregation.signal)


def handovers_folder(config: ExperimentConfig, clone: ModelSpec, labels: str = "executed") -> Path:
    """The dataset folder of the aggregation round's gated episodes of `clone`, their steps
    labelled as `labels` says."""
    return Path(config.demos_dir) / "handovers" / (clone.name if labels == "executed" else f"{clone.name}_{labels}")


def _calibration(evaluation: Evaluation) -> str:
    """The signals file an evaluation's gate reads ("" for none, or a gate on a random draw)."""
    return getattr(getattr(evaluation.config, "gate", None), "calibration", "")


def evaluation_specs(config: ExperimentConfig, evaluation: Evaluation) -> list[RolloutSpec]:
    from ditch_drake.evaluation.batch import make_specs

    checkpoint = str(model_path(config, evaluation.model)) if evaluation.model else ""
    if evaluation.model and not Path(checkpoint).exists():
        return []  # Not trained (yet): `_evaluate` says so. No model: a shipped one, or a classical controller.
    if _calibration(evaluation) and not Path(_calibration(evaluation)).exists():
        return []  # Not recorded (yet): `_evaluate` records it first, or says why it could not.
    baseline = config.studies.baseline
    controller = baseline.controller if evaluation.study == "baseline" and baseline.controller else evaluation.controller
    if evaluation.config is not None:  # It names its checkpoint.
        controller, checkpoint = evaluation.config, ""
    seed = config.seed if evaluation.seed is None else evaluation.seed
    return make_specs(controller, checkpoint, evaluation.environment, config.tasks or None, config.rollouts,
                      seed, config.time_limit_s, config.environments_file)


def run_experiment(config: ExperimentConfig, only: list[str] | None = None, stages: tuple[str, ...] = (
        "collect", "train", "evaluate", "report"), progress: bool = True, command: str = "",
        only_studies: list[str] | None = None) -> dict:
    """Runs the stages of the experiment (see the module docstring) for the models and
    evaluations of `plan(config, only, only_studies)`; returns each stage's wall time (s).

    Each finished stage's time goes into the results folder's RUNS_FILE at once (with
    `command`, `only` and the CPU), so an interrupted run keeps the times of what it
    finished and the results page can say how long the protocol took.
    """
    models, evaluations = plan(config, only, only_studies)
    shared_control = config.studies.shared_control
    split_part = (shared_control and shared_control.split if only is None and (
        only_studies is None or "shared_control" in only_studies) else None)
    run = {"started_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
           "command": command, "only": list(only or []), "cpu": cpu_name(), "code": code_revision()}

    def report() -> None:
        from ditch_drake.evaluation.report import write_report

        page = Path(config.report or Path(config.results_dir) / "report.md")
        figures = Path(config.figures_dir or figures_beside(page))
        write_report([config.results_dir], page, figures, title=config.name, command=command)

    runners = {
        "collect": lambda: _collect(config, models, progress),
        "train": lambda: [_train(config, model, progress) for model in models],
        "evaluate": lambda: _evaluate(config, evaluations, progress, split_part),
        "report": report,
    }
    timings: dict[str, float] = {}
    for stage, run_stage in runners.items():  # In pipeline order, whatever order `stages` names them in.
        if stage in stages:
            start = time.perf_counter()
            if stage == "report":
                record_run(config.results_dir, {**run, **timings})  # The page shows this run's times so far.
            run_stage()
            timings[f"{stage}_s"] = time.perf_counter() - start
            record_run(config.results_dir, {**run, **timings})
    return timings


def cpu_name() -> str:
    """The CPU's model name (Linux's /proc/cpuinfo; else `platform.processor()`) and core count."""
    name = platform.processor()
    try:
        name = next(line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                    if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return f"{name or 'unknown CPU'}, {os.cpu_count()} cores"


def code_revision() -> str:
    """The package's git commit ("+changes" when its checkout has uncommitted edits to
    tracked files), or its version when it is not a git checkout."""
    import subprocess

    import ditch_drake

    folder = Path(ditch_drake.__file__).resolve().parent
    try:
        commit = subprocess.run(["git", "-C", str(folder), "rev-parse", "--short=12", "HEAD"],
                                capture_output=True, text=True, check=True, timeout=10).stdout.strip()
        changes = subprocess.run(["git", "-C", str(folder), "status", "--porcelain", "--untracked-files=no"],
                                 capture_output=True, text=True, check=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return f"ditch_drake {ditch_drake.__version__}"
    return commit + ("+changes" if changes else "")


def _collect(config: ExperimentConfig, models: list[ModelSpec], progress: bool) -> None:
    from ditch_drake.demos.collect import CollectConfig

    needed: dict[str, int] = {}
    for model in models:
        for env in model.environments:
            needed[env] = max(needed.get(env, 0), model.demos)
    for env, demos in needed.items():
        collect_demonstrations(CollectConfig(environment=env, demos=demos, seed=config.seed,
                                             out=str(Path(config.demos_dir) / env), workers=config.workers),
                               env, progress)


def _train(config: ExperimentConfig, model: ModelSpec, progress: bool) -> None:
    from ditch_drake.demos.training_set import load_training_set
    from ditch_drake.learning.config import TrainConfig

    directories = [Path(config.demos_dir) / env for env in model.environments]

    def samples():  # A dataset folder's images stay on disk, read batch by batch.
        return load_training_set(directories, max_demos=model.demos)

    settings = config.training
    defaults = TrainConfig()
    device = training_device("auto")
    train_config = TrainConfig(epochs=settings.epochs, patience=settings.patience, seed=config.seed,
                               device=device, precision=training_precision(device, settings.precision),
                               max_batches_per_epoch=settings.batches_per_epoch, balancing=settings.balancing,
                               smote=replace(defaults.smote, max_synthetic_fraction=settings.synthetic_fraction))
    if model.intervention_weight is not None:
        _train_after_the_round(config, model, replace(train_config, intervention_weight=model.intervention_weight,
                                                      shared_steps=model.round_steps), progress)
        return
    if model.ensemble > 1:
        train_ensemble_or_resume(model_path(config, model), model.name, directories, model.demos, train_config,
                                 model.ensemble, progress)
    else:
        train_or_resume(model_path(config, model), model.name, samples, train_config, progress)


def _train_after_the_round(config: ExperimentConfig, model: ModelSpec, train_config, progress: bool) -> None:
    """Trains `model` (a clone retrained after the aggregation round) on its clone's first
    demonstrations and the round's gated episodes, running the round first where it is
    unfinished."""
    from ditch_drake.demos.interventions import episode_interventions, kept_steps
    from ditch_drake.demos.training_set import dataset_episodes, training_set

    clone, labels = model.before_the_round, model.round_labels
    if not model_path(config, model).exists() and not _aggregation_round(config, clone, labels, progress):
        return

    @functools.cache  # Read once for the samples and their intervention flags.
    def episodes():  # The clone's demonstrations, then the round's episodes, as `train --data D --data H`.
        demonstrations = Path(config.demos_dir) / clone.environments[0]
        return [*dataset_episodes(demonstrations, clone.demos),
                *dataset_episodes(handovers_folder(config, clone, labels))]

    @functools.cache  # Read once for the samples and their flags.
    def steps():  # As `train --shared-steps`.
        return kept_steps(episodes(), train_config.shared_steps)

    weighted = train_config.intervention_weight != 1.0  # As `train`: W = 1 reads no flags.
    train_or_resume(model_path(config, model), model.name, lambda: training_set(episodes(), steps=steps()),
                    train_config, progress,
                    interventions=(lambda: episode_interventions(episodes(), steps())) if weighted else None)


def _aggregation_round(config: ExperimentConfig, clone: ModelSpec, labels: str, progress: bool) -> bool:
    """The shared-control study's aggregation round on `clone` (`AggregationRound`), each step
    skipped where an earlier run finished it: the clone trained, its signals file recorded,
    its gated episodes collected with their steps labelled as `labels` says (`handovers_folder`).
    False (logged): the clone could not be trained, as with no demonstrations."""
    from ditch_drake.demos.collect import CollectConfig, with_labelling_expert
    from ditch_drake.diagrams.rollout import LearnedPolicyConfig
    from ditch_drake.diagrams.shared_controller import SharedControlControllerConfig
    from ditch_drake.learning.uncertainty import RISK_SIGNALS
    from ditch_drake.systems.shared_control import SharedControlConfig

    study = config.studies.shared_control
    round_ = study.aggregation
    checkpoint = model_path(config, clone)
    if not checkpoint.exists():
        _train(config, clone, progress)
    if not checkpoint.exists():
        log_progress(progress, f"aggregation round on {clone.name}: no checkpoint {checkpoint}; skipped")
        return False
    env = clone.environments[0]
    signals = round_signals_path(config, clone)
    tasks = config.tasks or range(len(get_environment(env, config.environments_file or None).tasks))
    record_signals_or_resume(signals, str(checkpoint), [(env, task) for task in tasks], study.calibration_rollouts,
                             study.calibration_seed, config.time_limit_s, config.environments_file, progress,
                             risk=round_.signal in RISK_SIGNALS, workers=config.workers)
    gate = SharedControlConfig(signal=round_.signal, budget=round_.budget, calibration=str(signals),
                               calm_steps=study.calm_steps, fallback=round_.fallback)
    shared = with_labelling_expert(SharedControlControllerConfig(
        policy=LearnedPolicyConfig(checkpoint=str(checkpoint)), gate=gate))
    collect_demonstrations(CollectConfig(environment=env, demos=round_.rollouts, seed=round_.seed,
                                         out=str(handovers_folder(config, clone, labels)),
                                         workers=config.workers, environments_file=config.environments_file,
                                         shared=shared, shared_labels=labels),
                           f"{env} (gated {clone.name}, {labels} labels)", progress)
    return True


def _calibrate(config: ExperimentConfig, evaluations: list[Evaluation], progress: bool) -> None:
    """Records the signals file of each gated evaluation's model where it is missing (the
    model's ungated rollouts in its environment, on the shared-control study's calibration
    seeds), before any rollout reads it."""
    from ditch_drake.learning.uncertainty import RISK_SIGNALS
    from ditch_drake.world.environments import get_environment

    study = config.studies.shared_control
    needed = {_calibration(e): e for e in evaluations if _calibration(e)}
    for path, evaluation in needed.items():
        checkpoint = model_path(config, evaluation.model)
        if not checkpoint.exists():
            log_progress(progress, f"calibrate {evaluation.model.name}: no checkpoint {checkpoint}; skipped")
            continue
        env = evaluation.environment
        tasks = config.tasks or range(len(get_environment(env, config.environments_file or None).tasks))
        record_signals_or_resume(path, str(checkpoint), [(env, task) for task in tasks], study.calibration_rollouts,
                                 study.calibration_seed, config.time_limit_s, config.environments_file, progress,
                                 risk=study.signal in RISK_SIGNALS, workers=config.workers)


def split_gating_paths(config: ExperimentConfig, part: SplitGating) -> tuple[Path, Path]:
    """The split part's signals file (with the tip-risk signals for a risk signal) and results file."""
    stem = f"{Path(part.checkpoint).stem}_{part.calibration_split}"
    return (_signals_file(config, stem, part.gate_signal(config.studies.shared_control)),
            Path(config.results_dir) / f"shared_control_{part.split}.jsonl")


def split_gating_specs(config: ExperimentConfig, part: SplitGating) -> list[RolloutSpec]:
    """The split part's rollouts (the policy alone, then each gate of `study_gates`), on
    `part.split`'s ditches, written (added) to its results file's ditches file first."""
    from ditch_drake.benchmark.splits import ditches_file, split_ditches, write_ditches
    from ditch_drake.diagrams.rollout import LearnedPolicyConfig
    from ditch_drake.diagrams.shared_controller import SharedControlControllerConfig
    from ditch_drake.evaluation.batch import make_specs

    signals, results = split_gating_paths(config, part)
    ditches = split_ditches(part.split, part.geometries)
    environments_file = str(write_ditches(ditches_file(results), ditches))
    policy = LearnedPolicyConfig(checkpoint=part.checkpoint)
    study = config.studies.shared_control
    controllers = [policy] + [SharedControlControllerConfig(policy=policy, gate=gate) for gate in study_gates(
        study, str(signals), part.budgets, part.fallbacks, part.gate_signal(study))]
    return [spec for controller in controllers for ditch in ditches
            for spec in make_specs(controller, "", ditch.name, None, 1, part.seed, config.time_limit_s,
                                   environments_file)]


def _run_split_gating(config: ExperimentConfig, part: SplitGating, progress: bool) -> None:
    """The split part of the shared-control study: its signals file on the calibration split
    (resumable, as `gate-signals --split`), then its rollouts (finished ones skipped)."""
    from ditch_drake.benchmark.splits import ditches_file, split_ditches, write_ditches
    from ditch_drake.evaluation.batch import evaluate
    from ditch_drake.learning.uncertainty import RISK_SIGNALS

    signals, results = split_gating_paths(config, part)
    ditches = split_ditches(part.calibration_split, part.calibration_geometries)
    environments_file = str(write_ditches(ditches_file(signals), ditches))
    runs = [(ditch.name, task) for ditch in ditches for task in range(len(ditch.environment.tasks))]
    record_signals_or_resume(signals, part.checkpoint, runs, 1, part.seed, config.time_limit_s, environments_file,
                             progress, risk=part.gate_signal(config.studies.shared_control) in RISK_SIGNALS,
                             workers=config.workers)
    report = evaluate(split_gating_specs(config, part), results, workers=config.workers, progress=progress)
    log_progress(progress, f"evaluate shared_control on {part.split}: " + json.dumps(
        {"recorded": report.recorded, "skipped": report.skipped, "wall_s": round(report.wall_s, 1)}))
    if report.interrupted:
        pass_on_stop(report.exit_code)


def _evaluate(config: ExperimentConfig, evaluations: list[Evaluation], progress: bool,
              split_part: SplitGating | None = None) -> None:
    from ditch_drake.evaluation.batch import evaluate

    _calibrate(config, evaluations, progress)
    by_study: dict[str, list[RolloutSpec]] = {}
    for evaluation in evaluations:
        specs = evaluation_specs(config, evaluation)
        if not specs and evaluation.model:
            checkpoint = model_path(config, evaluation.model)
            missing = f"signals file {_calibration(evaluation)}" if checkpoint.exists() else f"checkpoint {checkpoint}"
            log_progress(progress, f"evaluate {evaluation.study}: no {missing}; skipped")
        by_study.setdefault(evaluation.study, []).extend(specs)
    for study, specs in by_study.items():
        report = evaluate(specs, Path(config.results_dir) / f"{study}.jsonl", workers=config.workers,
                          progress=progress)
        log_progress(progress, f"evaluate {study}: " + json.dumps(
            {"recorded": report.recorded, "skipped": report.skipped, "wall_s": round(report.wall_s, 1)}))
        if report.interrupted:
            pass_on_stop(report.exit_code)
    if split_part is not None:
        _run_split_gating(config, split_part, progress)
