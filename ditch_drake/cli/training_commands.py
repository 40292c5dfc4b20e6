"""Commands of data and training: collect, train, checkpoint-info, train-generalist, gate-signals,
gate-thresholds."""

import json
import os
import sys

from ditch_drake.cli.options import (
    Commands,
    ConfigDefault,
    add_backend,
    add_env,
    add_environments_file,
    add_out,
    add_workers,
    check_task,
    print_table,
)
from ditch_drake.cli.shared_options import add_gate_options, shared_config_from_options
from ditch_drake.common.errors import ConfigError
from ditch_drake.common.parallel import check_workers, interrupt_exit_code
from ditch_drake.common.seeds import check_seed

COLLECT = "ditch_drake.demos.collect:CollectConfig"
TRAIN = "ditch_drake.learning.config:TrainConfig"
GENERALIST = "ditch_drake.pipelines.generalist:GeneralistConfig"
ENSEMBLE = "ditch_drake.learning.ensemble_training:train_ensemble"


def add_collect(commands: Commands) -> None:
    collect = commands.add("collect", "record expert demonstrations (resumable; Ctrl-C keeps what finished)")
    add_env(collect, default=ConfigDefault(COLLECT, "environment"))
    add_environments_file(collect)
    collect.add_argument("--demos", type=int, default=ConfigDefault(COLLECT, "demos"),
                         help="successful demonstrations, spread over the tasks")
    collect.add_argument("--seed", type=int, default=ConfigDefault(COLLECT, "seed"),
                         help="demonstration i's first attempt uses seed + i")
    add_out(collect, "dataset folder (made if missing); demonstration i is its episode i")
    add_workers(collect, "demonstrations", default=ConfigDefault(COLLECT, "workers"))
    collect.add_argument("--learner", default=ConfigDefault(COLLECT, "learner"), metavar="CHECKPOINT",
                         help="DAgger: this policy drives, the expert labels; every rollout is kept "
                              "(--demos rollouts, one per seed)")
    collect.add_argument("--labeller", choices=["latched", "replanning"], default="latched",
                         help="with --learner: the expert keeps the plan it chose before the wall (latched) "
                              "or decides it afresh from the current pose every step (replanning)")
    collect.add_argument("--lead-in", action="store_true",
                         help="the expert first makes room along the ditch when the crossing would not fit "
                              "before the ditch's end (EdgeAngleDriverConfig.lead_in)")
    collect.add_argument("--shared", action="store_true",
                         help="the learned policy (--checkpoint) drives, gated by its tip risk or uncertainty, and --fallback "
                              "takes over where the gate hands over; every rollout is kept (--demos rollouts, one per "
                              "seed), each step flagged as an intervention where the fallback drove")
    collect.add_argument("--checkpoint", default=None,
                         help="with --shared: the gated policy, a shipped name, a .pt file or an ensemble file "
                              "(default: the shipped generalist ensemble, generalist_k5)")
    collect.add_argument("--shared-labels", choices=["executed", "expert"], default=ConfigDefault(COLLECT,
                                                                                                  "shared_labels"),
                         help="with --shared: the label stored for each step: the executed one (the policy's or "
                              "the fallback's) or the expert fallback's at every step (DAgger's labels) "
                              "(default %(default)s)")
    add_gate_options(collect, ["expert", "mppi"])
    add_backend(collect, COLLECT)
    collect.set_defaults(run=cmd_collect)


def cmd_collect(args) -> int:
    check_workers(args.workers, "--workers")
    check_seed(args.seed, args.demos if args.demos > 0 else 1)
    if args.learner is None and args.labeller != "latched":
        raise ConfigError(f"--labeller {args.labeller}: a labeller needs --learner (a DAgger round)")
    if args.shared and args.learner is not None:
        raise ConfigError(f"--learner {args.learner} with --shared: the gated policy is --checkpoint; expected one "
                          "of --learner (DAgger) and --shared")
    if not args.shared and args.checkpoint is not None:
        raise ConfigError(f"--checkpoint {args.checkpoint}: a gated policy drives only with --shared")
    from dataclasses import replace

    from ditch_drake.demos.collect import LABELLER_VARIATION, CollectConfig, collect, with_labelling_expert

    config = CollectConfig(environment=args.env, demos=args.demos, seed=args.seed, out=args.out, workers=args.workers,
                           environments_file=args.environments or "", backend=args.backend, address=args.address)
    config = replace(config, variation=replace(config.variation, lead_in=args.lead_in))
    if args.learner is not None:
        config = replace(config, learner=args.learner, variation=replace(
            LABELLER_VARIATION, replan_each_step=args.labeller == "replanning", lead_in=args.lead_in))
    if args.shared:
        shared = with_labelling_expert(shared_config_from_options(args, args.checkpoint), args.lead_in)
        config = replace(config, shared=shared, shared_labels=args.shared_labels)
    report = collect(config)
    print(json.dumps(report, indent=2))
    if report["interrupted"]:
        print(f"interrupted: {report['recorded']} demonstrations recorded by this run, "
              f"{report['kept_before'] + report['recorded']} of {args.demos} in {args.out}; "
              "run the same command again to continue", file=sys.stderr)
        return report["exit_code"]
    return 0 if not report["unfilled_slots"] else 1


def add_checkpoint_info(commands: Commands) -> None:
    info = commands.add("checkpoint-info", "training data and validation metrics of checkpoints")
    info.add_argument("checkpoints", nargs="+",
                      help="shipped model names, .pt files or ensemble files (a row per member)")
    info.add_argument("--confusion", action="store_true", help="also the validation confusion matrices")
    info.set_defaults(run=cmd_checkpoint_info)


def cmd_checkpoint_info(args) -> int:
    """What each checkpoint was trained on and how it validated."""
    from ditch_drake.learning.checkpoint import load_checkpoint, resolve_checkpoint_path
    from ditch_drake.learning.ensemble import is_ensemble_checkpoint, load_ensemble

    checkpoints = {}
    for name in args.checkpoints:
        path = resolve_checkpoint_path(name)
        if is_ensemble_checkpoint(path):  # One row per member, named "<file>[k]".
            members = load_ensemble(path).members
            checkpoints.update({f"{name}[{k}]": member for k, member in enumerate(members)})
        else:
            checkpoints[name] = load_checkpoint(path, allow_untrained=True)
    rows = [{"checkpoint": name, **checkpoint.summary()} for name, checkpoint in checkpoints.items()]
    print_table(rows, list(rows[0]))
    if args.confusion:
        for name, checkpoint in checkpoints.items():
            matrix = checkpoint.metrics.get("val_confusion_matrix") or []
            print(f"\n{name}: validation confusion matrix (row: demonstrated label, column: predicted)")
            print_table([{"label": str(label), **{str(j): str(v) for j, v in enumerate(row)}}
                         for label, row in enumerate(matrix)], ["label", *map(str, range(len(matrix)))])
    return 0


def add_train(commands: Commands) -> None:
    training = commands.add("train", "behavioural cloning from demonstrations (Ctrl-C keeps the best finished epoch)")
    training.add_argument("--data", action="append", required=True, metavar="DIR",
                          help="demonstration directory (repeat for an amalgam of environments)")
    add_out(training, "checkpoint path (.pt)")
    training.add_argument("--seed", type=int, default=ConfigDefault(TRAIN, "seed"),
                          help="seeds the split, SMOTE, initialization, shuffling and dropout")
    training.add_argument("--max-demos", type=int, default=None,
                          help="use the first N demonstrations of each directory (default None: all)")
    training.add_argument("--epochs", type=int, default=ConfigDefault(TRAIN, "epochs"), help="most epochs to run")
    training.add_argument("--patience", type=int, default=ConfigDefault(TRAIN, "patience"),
                          help="epochs without a better validation accuracy before stopping")
    training.add_argument("--batch-size", type=int, default=ConfigDefault(TRAIN, "batch_size"),
                          help="samples per optimizer step")
    training.add_argument("--batches-per-epoch", type=int, default=ConfigDefault(TRAIN, "max_batches_per_epoch"),
                          help="batches drawn (without replacement) from the shuffled training set per epoch")
    training.add_argument("--synthetic-fraction", type=float,
                          default=ConfigDefault(TRAIN, "smote.max_synthetic_fraction"),
                          help="at most this many added samples (SMOTE's or oversampling's) per real training sample")
    training.add_argument("--threads", type=int, default=ConfigDefault(TRAIN, "num_threads"),
                          help="torch threads (default %(default)s: all cores)")
    # "auto" is the command line's own choice; TrainConfig takes the device and precision it picks.
    training.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                          help="auto: CUDA when torch sees a GPU, else the CPU (a CUDA run is not bitwise "
                               "reproducible on the CPU)")
    training.add_argument("--precision", choices=["auto", "fp32", "bf16"], default="auto",
                          help="bf16: training steps under bfloat16 autocast; auto: bf16 on a CPU with native "
                               "bf16 (AVX512-BF16 or AMX), else fp32")
    from ditch_drake.learning.config import BALANCING_METHODS, SHARED_STEPS  # No torch: `--help` stays fast.

    training.add_argument("--balancing", choices=BALANCING_METHODS, default=ConfigDefault(TRAIN, "balancing"),
                          help="class balancing of the training split (ditch_drake/learning/balance.py)")
    training.add_argument("--loader-workers", type=int, default=ConfigDefault(TRAIN, "num_workers"),
                          help="processes reading the batches (default 0: read in the training process)")
    training.add_argument("--intervention-weight", type=float, default=ConfigDefault(TRAIN, "intervention_weight"),
                          help="loss weight of the steps a supervisor took over (the dataset's intervention flag: "
                               "collect --shared, teleop --shared), relative to 1 for the others (Sirius); "
                               "1: uniform (default %(default)s)")
    training.add_argument("--shared-steps", choices=list(SHARED_STEPS), default=ConfigDefault(TRAIN, "shared_steps"),
                          help="which steps of a shared episode (collect --shared, teleop --shared) to learn: all "
                               "(the policy's own and the supervisor's, as Sirius) or interventions (the "
                               "supervisor's only, as HG-DAgger and ThriftyDAgger); other episodes are used whole "
                               "(default %(default)s)")
    training.add_argument("--resume", action="store_true",
                          help="continue an interrupted run from its .resume file beside --out")
    training.add_argument("--ensemble", type=int, nargs="?", const=ConfigDefault(ENSEMBLE, "members"), default=None,
                          metavar="K", help="train K clones (default K %(const)s), each on a bootstrap resample of the "
                                            "demonstrations with seed --seed + k, into one ensemble file at --out; "
                                            "a rerun keeps the finished members and continues the interrupted one")
    training.set_defaults(run=cmd_train)


def cmd_train(args) -> int:
    from dataclasses import replace

    from ditch_drake.learning.config import TrainConfig

    # Every setting is checked here, before minutes of loading: a bad value fails at once.
    config = TrainConfig.from_options(
        epochs=args.epochs, seed=args.seed, patience=args.patience, batch_size=args.batch_size,
        max_batches_per_epoch=args.batches_per_epoch, synthetic_fraction=args.synthetic_fraction,
        num_threads=args.threads, balancing=args.balancing, num_workers=args.loader_workers,
        intervention_weight=args.intervention_weight, shared_steps=args.shared_steps)
    if args.max_demos is not None and args.max_demos < 1:
        raise ConfigError(f"--max-demos {args.max_demos}: expected >= 1 demonstrations per directory")
    from ditch_drake.demos.interventions import episode_interventions, kept_steps
    from ditch_drake.demos.training_set import dataset_episodes, training_set
    from ditch_drake.learning.train import train
    from ditch_drake.pipelines.stages import training_device, training_precision

    device = training_device(args.device)
    precision = training_precision(device, args.precision)
    config = replace(config, device=device, precision=precision)
    if args.ensemble is not None:
        return _train_ensemble(args, config)
    # Several directories train the amalgam model; a dataset folder's images stay on disk.
    episodes = [episode for directory in args.data for episode in dataset_episodes(directory, args.max_demos)]
    steps = kept_steps(episodes, config.shared_steps)
    intervention = episode_interventions(episodes, steps) if config.intervention_weight != 1.0 else None
    result = train(training_set(episodes, steps=steps), config, output_path=args.out, resume=args.resume,
                   intervention=intervention)
    best = next((record for record in result.history if record["epoch"] == result.best_epoch), {})
    print(json.dumps({"out": str(result.output_path) if result.output_path else None,
                      "resume_file": str(result.resume_file) if result.resume_file else None,
                      "best_epoch": result.best_epoch, "stopped_early": result.stopped_early,
                      "interrupted": result.interrupted, "best": best}, default=float))
    if result.interrupted:
        print("interrupted: " + (f"the best finished epoch is in {result.output_path}" if result.output_path
                                 else "no epoch had finished, so no checkpoint was written")
              + (f"; --resume continues from {result.resume_file}" if result.resume_file else ""), file=sys.stderr)
        return result.exit_code
    return 0


def _train_ensemble(args, config) -> int:
    """`train --ensemble K`: K clones on bootstrap resamples of the demonstrations, one file."""
    from ditch_drake.demos.interventions import episode_interventions, kept_steps
    from ditch_drake.demos.training_set import named_dataset_episodes, training_set
    from ditch_drake.learning.bootstrap import check_member_count
    from ditch_drake.learning.ensemble_training import train_ensemble

    members = check_member_count(args.ensemble)
    episodes, names = named_dataset_episodes(args.data, args.max_demos)
    steps = kept_steps(episodes, config.shared_steps)

    def chosen(indices):  # A member's resample: its episodes, and the steps kept of each.
        return [episodes[i] for i in indices], None if steps is None else [steps[i] for i in indices]

    def member_samples(indices):
        resample, kept = chosen(indices)
        return training_set(resample, steps=kept)

    weighted = config.intervention_weight != 1.0
    result = train_ensemble(member_samples, names, args.out, config, members,
                            interventions_of=(lambda indices: episode_interventions(*chosen(indices)))
                            if weighted else None)
    print(json.dumps({"out": str(result.output_path) if result.output_path else None,
                      "members_folder": str(result.members_folder), "trained": result.trained,
                      "skipped": result.skipped, "interrupted": result.interrupted,
                      "best": {str(member): best for member, best in result.best.items()}}, default=float))
    if result.interrupted:
        print(f"interrupted: the finished members are kept in {result.members_folder}; run the same command again "
              "to continue", file=sys.stderr)
        return result.exit_code
    return 0


def add_train_generalist(commands: Commands) -> None:
    generalist = commands.add("train-generalist", "the generalist policy: expert demonstrations and DAgger over the "
                                                  "train split's ditches, the best round on the val split (resumable)")
    add_out(generalist, "the chosen checkpoint (default: <work dir>/generalist.pt)",
            default=ConfigDefault(GENERALIST, "out"))
    generalist.add_argument("--work-dir", default=ConfigDefault(GENERALIST, "work_dir"),
                            help="demonstrations, each round's checkpoint and the val results")
    generalist.add_argument("--train-geometries", type=int, default=ConfigDefault(GENERALIST, "train_geometries"),
                            help="the train split's first N ditches")
    generalist.add_argument("--demos-per-task", type=int, default=ConfigDefault(GENERALIST, "demos_per_task"),
                            help="expert demonstrations per task")
    generalist.add_argument("--dagger-rounds", type=int, default=ConfigDefault(GENERALIST, "dagger_rounds"),
                            help="DAgger rounds after the first clone")
    generalist.add_argument("--val-geometries", type=int, default=ConfigDefault(GENERALIST, "val_geometries"),
                            help="the val split's first N ditches")
    generalist.add_argument("--dagger-stride", type=int, default=ConfigDefault(GENERALIST, "dagger_stride"),
                            help="train on every k-th control step of the DAgger rollouts (memory)")
    generalist.add_argument("--epochs", type=int, default=ConfigDefault(GENERALIST, "epochs"),
                            help="most epochs per training")
    from ditch_drake.learning.config import BALANCING_METHODS  # No torch: `--help` stays fast.

    generalist.add_argument("--balancing", choices=BALANCING_METHODS, default=ConfigDefault(GENERALIST, "balancing"),
                            help="class balancing of every round's training (ditch_drake/learning/balance.py)")
    generalist.add_argument("--mirror", action="store_true",
                            help="also train on the left-right reflection of each rollout whose crossing turns "
                                 "clearly to one side (ditch_drake/pipelines/generalist.py)")
    generalist.add_argument("--canonical-side", action="store_true",
                            help="reflect every step that crosses turned left along the edge, and tell the clone "
                                 "the side to cross on (found in the lidar's rays when it drives: "
                                 "systems/perceived_crossing_side.py)")
    generalist.add_argument("--seed", type=int, default=ConfigDefault(GENERALIST, "seed"),
                            help="seeds demonstrations, training and val rollouts")
    generalist.add_argument("--ensemble", type=int, default=ConfigDefault(GENERALIST, "ensemble"), metavar="K",
                            help="then K clones of the chosen round's data, each on a bootstrap resample of its "
                                 "rollouts, into <work dir>/ensemble.pt (the shared controller's gated policy); "
                                 "0: none (default %(default)s)")
    generalist.add_argument("--ranges", default=ConfigDefault(GENERALIST, "ranges"),
                            help="the val split's ranges YAML file (default: the benchmark's)")
    generalist.add_argument("--train-ranges", default=ConfigDefault(GENERALIST, "train_ranges"),
                            help="the train ditches' ranges YAML file (default: the packaged "
                                 "generalist_train_ranges.yaml)")
    add_workers(generalist, "demonstrations and val rollouts", default=ConfigDefault(GENERALIST, "workers"))
    add_backend(generalist, GENERALIST)
    generalist.set_defaults(run=cmd_train_generalist)


def cmd_train_generalist(args) -> int:
    """The generalist: demonstrations and DAgger over the train split, the best round on val."""
    check_workers(args.workers, "--workers")
    check_seed(args.seed)
    from ditch_drake.benchmark.splits import split_seeds
    from ditch_drake.pipelines.generalist import GeneralistConfig, train_generalist

    split_seeds("train", args.train_geometries)
    split_seeds("val", args.val_geometries)
    config = GeneralistConfig(out=args.out, work_dir=args.work_dir, train_geometries=args.train_geometries,
                              demos_per_task=args.demos_per_task, dagger_rounds=args.dagger_rounds,
                              val_geometries=args.val_geometries, dagger_stride=args.dagger_stride,
                              epochs=args.epochs, balancing=args.balancing, seed=args.seed, mirror=args.mirror,
                              ensemble=args.ensemble,
                              canonical_side=args.canonical_side, workers=args.workers,
                              ranges=args.ranges or "", train_ranges=args.train_ranges or "",
                              backend=args.backend, address=args.address)
    try:
        summary = train_generalist(config)
    except KeyboardInterrupt as error:
        print("interrupted; finished stages are kept, run the same command again to continue", file=sys.stderr)
        return interrupt_exit_code(error)
    print(json.dumps(summary))
    return 0


GATE_SIGNALS = "ditch_drake.evaluation.gate_signals:record_gate_signals"
AUC = "ditch_drake.learning.gate_calibration:auc_report"
GATE = "ditch_drake.systems.shared_control:SharedControlConfig"
TIP_RISK = "ditch_drake.systems.tip_risk:TipRiskConfig"
# The budgets `gate-thresholds` prints by default: the shared-control study's.
STUDY_BUDGETS = (0.01, 0.02, 0.05, 0.1, 0.2)
# gate-thresholds --figure: seconds before each rollover drawn, twice the AUC's failure horizon, so that
# the steps the AUC counts as coming failures show beside those before them.
FIGURE_WINDOW_S = 4.0


def add_gate_signals(commands: Commands) -> None:
    signals = commands.add("gate-signals", "the learned policy's uncertainty signals at every control step of its own "
                                           "validation rollouts, and how well each foresees a rollover (ROC AUC)")
    signals.add_argument("--checkpoint", required=True,
                         help="the policy, a shipped name, a .pt file or an ensemble file (an ensemble records the "
                              "disagreement signals too)")
    add_env(signals, many=True)
    add_environments_file(signals)
    signals.add_argument("--split", default=None,
                         help="record on a benchmark split's ditches instead of --env/--environments: one the "
                              "gate's thresholds may be chosen on (train, val, search_val; test, stress and search "
                              "are held out), written beside --out as <out stem>.ditches.yaml (default: none)")
    signals.add_argument("--geometries", type=int, default=None,
                         help="with --split: the split's first N ditches (default: all of them)")
    signals.add_argument("--ranges", default=None, metavar="FILE",
                         help="with --split: a ranges YAML file (default: the split's packaged one)")
    signals.add_argument("--task", type=int, action="append", default=None,
                         help="task index (repeatable; default None: every task of each environment)")
    signals.add_argument("--rollouts", type=int, default=ConfigDefault(GATE_SIGNALS, "rollouts"),
                         help="seeded rollouts per task")
    signals.add_argument("--seed", type=int, default=ConfigDefault(GATE_SIGNALS, "seed"),
                         help="first seed; rollout i of each task uses seed + i (validation seeds: keep the test "
                              "seeds out)")
    signals.add_argument("--time-limit", type=float, default=ConfigDefault(GATE_SIGNALS, "time_limit_s"),
                         help="episode timeout in s")
    signals.add_argument("--horizon", type=float, default=ConfigDefault(AUC, "horizon_s"),
                         help="a step is labelled a coming failure where its episode rolls over within this many "
                              "seconds after it")
    signals.add_argument("--risk", action="store_true",
                         help="also record the tip-risk signals: minus the tip margin of the chassis now "
                              "(tip_risk_now) and the least one predicted along the commanded arc on the perceived "
                              "elevation map (tip_risk_ahead), in deg")
    signals.add_argument("--risk-horizon", type=float, default=ConfigDefault(TIP_RISK, "horizon_s"),
                         help="with --risk: how long the commanded arc is held for tip_risk_ahead (s; a gate on "
                              "this file's tip risk needs the same policy.tip_risk.horizon_s)")
    add_workers(signals, "episodes (an (environment, task) pair per item; the signals equal one process's)")
    add_out(signals, "the signals file (.npz), written when every episode has finished, with the AUC table "
                     "beside it as <out>.auc.json; until then the finished episodes are kept in <out>.parts/, and "
                     "the same command again continues (Ctrl-C keeps them); a finished file is refused")
    signals.set_defaults(run=cmd_gate_signals)


def _check_risk_horizon(args) -> None:
    """Raises ConfigError for a --risk-horizon shorter than a control period (or not a number),
    or one set without --risk."""
    from ditch_drake.spec import robot
    from ditch_drake.systems.tip_risk import TipRiskConfig

    horizon = args.risk_horizon
    try:
        TipRiskConfig(horizon_s=horizon).validate()  # The block's own bound, named by the option here.
    except ConfigError:
        raise ConfigError(f"--risk-horizon {horizon!r}: expected at least one control period, "
                          f"{robot.CONTROL_PERIOD_S} s") from None
    if not args.risk and horizon != TipRiskConfig.horizon_s:
        raise ConfigError(f"--risk-horizon {horizon:g} without --risk: it sets the tip-risk signals' arc; expected "
                          "--risk too")


def cmd_gate_signals(args) -> int:
    """Records the signals on the policy's own rollouts, then each signal's AUC of a rollover within --horizon s.

    Each episode is kept in <out>.parts/ as it finishes: interrupted, the same command
    continues; with other settings it is refused (exit 2). The signals file and its report are
    written once all have finished, and the folder is then removed: a finished --out is refused.
    """
    from ditch_drake.common.checks import check_count, check_finite_positive
    from ditch_drake.common.files import exclusive_use, prepare_output
    from ditch_drake.common.parallel import worker_count
    from ditch_drake.evaluation.gate_signals import EpisodeParts, parts_folder

    out = prepare_output(args.out, "--out")
    report_path = out.with_suffix(".auc.json")
    folder = parts_folder(out)

    def refuse_finished() -> None:
        # With a recording in progress the files may be there from a stop while they were written.
        for path in (out, report_path) if not EpisodeParts.begun(folder) else ():
            if path.exists():
                raise ConfigError(f"--out {args.out}: {path} exists (a finished recording); expected a new path "
                                  "(delete it to record again)")

    refuse_finished()
    check_count(args.rollouts, "--rollouts")
    check_seed(args.seed, args.rollouts, "--seed")
    check_finite_positive(args.time_limit, "--time-limit")
    check_finite_positive(args.horizon, "--horizon")
    _check_risk_horizon(args)
    check_workers(args.workers, "--workers")
    from ditch_drake.world.environments import environment_names, get_environment, load_environments

    environments_file = args.environments or ""
    if args.split:
        environments_file = _write_split_ditches(args, out)
    elif args.geometries is not None or args.ranges is not None:
        raise ConfigError(f"{'--geometries' if args.geometries is not None else '--ranges'} without --split: it "
                          "says which of a split's ditches to record on; expected --split too")
    environments = args.env or (list(load_environments(environments_file)) if environments_file
                                else environment_names())
    runs = []
    for environment in environments:
        tasks = len(get_environment(environment, environments_file or None).tasks)
        for task in args.task if args.task is not None else range(tasks):
            check_task(environment, task, environments_file)
            runs.append((environment, task))
    import torch

    from ditch_drake.evaluation.batch import check_checkpoint
    from ditch_drake.evaluation.gate_signals import write_signals_file

    digest = check_checkpoint(args.checkpoint)
    torch.set_num_threads(1)  # One forward pass of one sample: as each evaluation worker runs it.
    # Two runs on one --out would each run the episodes the other has not kept yet.
    with exclusive_use(out, "--out"):
        refuse_finished()  # Again: another run may have finished it meanwhile.
        try:
            _, report = write_signals_file(out, args.checkpoint, digest, runs, args.rollouts, args.seed,
                                           args.time_limit, environments_file, args.horizon, risk=args.risk,
                                           workers=worker_count(args.workers), risk_horizon_s=args.risk_horizon)
        except KeyboardInterrupt as error:
            print(f"interrupted: the finished episodes are kept in {folder}; run the same command again to continue",
                  file=sys.stderr)
            return interrupt_exit_code(error)

    _print_auc_rows(report["rows"])
    print(f"signals: {out}\nAUC of a rollover within {args.horizon} s: {report_path}")
    return 0


def _print_auc_rows(rows: list[dict], first: tuple[str, ...] = ()) -> None:
    """The AUC table of `signal_aucs` rows, the columns `first` before the signal's."""
    import math

    def number(value: float) -> str:
        return "-" if math.isnan(value) else f"{value:.3f}"

    print_table([{**row, "auc": number(row["auc"]), "95% interval": f"[{number(row['ci_low'])}, "
                  f"{number(row['ci_high'])}]"} for row in rows],
                [*first, "signal", "auc", "95% interval", "positive_steps", "steps", "rolled_over_episodes", "episodes"])


def add_gate_auc(commands: Commands) -> None:
    auc = commands.add("gate-auc", "how far ahead each signal of a signals file foresees a rollover: the AUC of "
                                   "\"a rollover within H s\" for each horizon H, from the file as recorded")
    auc.add_argument("signals", help="a signals file of ditch-drake gate-signals")
    auc.add_argument("--horizon", type=float, nargs="+", default=ConfigDefault(AUC, "horizon_s"),
                     help="seconds: a step is labelled a coming failure where its episode rolls over within this "
                          "long after it (one table row per signal and horizon)")
    auc.add_argument("--seed", type=int, default=ConfigDefault(AUC, "seed"),
                     help="seed of the bootstrap over the episodes that gives each interval")
    auc.set_defaults(run=cmd_gate_auc)


def cmd_gate_auc(args) -> int:
    """Prints `signal_aucs` of the file at each --horizon: what `gate-signals` reports at its one
    horizon, without recording the rollouts again."""
    from ditch_drake.common.checks import check_finite_positive
    from ditch_drake.learning.gate_calibration import load_signals, signal_aucs

    given = args.horizon if isinstance(args.horizon, list) else [args.horizon]  # The default is one number.
    horizons = [check_finite_positive(horizon, "--horizon") for horizon in given]
    check_seed(args.seed, where="--seed")
    signals = load_signals(args.signals)
    rows = []
    for done, horizon in enumerate(horizons, start=1):  # Each horizon bootstraps every signal: seconds apiece.
        rows += [{"horizon_s": f"{horizon:g}", **row} for row in signal_aucs(signals, horizon, args.seed)]
        print(f"gate-auc: {done}/{len(horizons)} horizons", file=sys.stderr, flush=True)
    _print_auc_rows(rows, ("horizon_s",))
    print(f"{args.signals}: {len(signals['episode_status'])} episodes, checkpoint {signals['checkpoint']}; 95% "
          "intervals from resampling the episodes")
    return 0


def add_gate_peaks(commands: Commands) -> None:
    peaks = commands.add("gate-peaks", "each signal's largest value per episode of a signals file, by how the "
                                       "episodes ended: where a fixed threshold (a watchdog's) would separate them")
    peaks.add_argument("signals", help="a signals file of ditch-drake gate-signals")
    peaks.add_argument("--signal", nargs="+", default=None,
                       help="the signals to show (default: every one the file recorded)")
    peaks.add_argument("--warmup-steps", type=int, default=ConfigDefault(GATE, "warmup_steps"),
                       help="control steps at each episode's start left out, as the gate ignores them")
    peaks.set_defaults(run=cmd_gate_peaks)


def cmd_gate_peaks(args) -> int:
    """Prints `episode_peaks` for each signal: per outcome, how many episodes, and the least,
    median and largest of their peaks."""
    from ditch_drake.common.checks import check_count
    from ditch_drake.learning.gate_calibration import episode_peaks, load_signals

    signals = load_signals(args.signals)
    names = args.signal or signals["signals"]
    unknown = [name for name in names if name not in signals["signals"]]
    if unknown:
        raise ConfigError(f"--signal {unknown[0]}: {args.signals} did not record it; expected one of "
                          f"{signals['signals']}")
    check_count(args.warmup_steps, "--warmup-steps", lowest=0)
    rows = [{**row, **{key: f"{row[key]:.4g}" for key in ("least_peak", "median_peak", "largest_peak")}}
            for name in names for row in episode_peaks(signals, name, args.warmup_steps)]
    print_table(rows, list(rows[0]))
    print(f"{args.signals}: {len(signals['episode_status'])} episodes, checkpoint {signals['checkpoint']}; each "
          f"episode's largest value after its first {args.warmup_steps} steps")
    return 0


def _write_split_ditches(args, out) -> str:
    """The environments file of `--split`'s ditches (its first `--geometries`, drawn from
    `--ranges`), written as `<out stem>.ditches.yaml`; refuses --environments beside it."""
    from ditch_drake.benchmark.splits import ditches_file, split_ditches, split_ranges, write_ditches
    from ditch_drake.world.ditch_splits import CHOICE_SPLITS, SEED_SPLITS

    if args.split not in CHOICE_SPLITS:
        why = ("held out for reporting, and a gate's thresholds are a choice" if args.split in SEED_SPLITS
               else "no generated split")
        raise ConfigError(f"--split {args.split!r}: {why}; expected one of {list(CHOICE_SPLITS)}")
    if args.environments:
        raise ConfigError(f"--split {args.split} with --environments {args.environments}: both say where to drive; "
                          "expected one of them")
    ditches = split_ditches(args.split, args.geometries, split_ranges(args.split, args.ranges))
    return str(write_ditches(ditches_file(out), ditches))


def add_gate_thresholds(commands: Commands) -> None:
    thresholds = commands.add("gate-thresholds", "the thresholds a budget sets on a signals file (gate.budget with "
                                                 "gate.calibration), and the share of steps they hand over there")
    thresholds.add_argument("signals", help="a signals file of ditch-drake gate-signals")
    thresholds.add_argument("--signal", default=ConfigDefault(GATE, "signal"),
                            help="the uncertainty signal the gate reads (one the file recorded)")
    thresholds.add_argument("--budget", type=float, nargs="+", default=list(STUDY_BUDGETS),
                            help="shares of control steps the fallback may drive, each in (0, 1)")
    thresholds.add_argument("--calm-steps", type=int, default=ConfigDefault(GATE, "calm_steps"),
                            help="the gate's hysteresis: calm control steps before it hands back")
    thresholds.add_argument("--warmup-steps", type=int, default=ConfigDefault(GATE, "warmup_steps"),
                            help="control steps at each episode's start whose signal the gate ignores")
    thresholds.add_argument("--figure", metavar="PNG",
                            help="also draw the signal before each rollover of the file, with each budget's upper "
                                 "threshold, into this PNG")
    thresholds.add_argument("--window", type=float, metavar="S",
                            help=f"with --figure: the seconds before each rollover it draws (default "
                                 f"{FIGURE_WINDOW_S:g})")
    thresholds.set_defaults(run=cmd_gate_thresholds)


def cmd_gate_thresholds(args) -> int:
    """Prints, for each budget, the thresholds `SharedControlConfig.resolved` would set, the
    quantile share s they sit at, and the share of the file's steps the gate hands over replayed
    over its episodes, beside what the quantiles at the budget itself (no hysteresis counted) would."""
    import numpy as np

    from ditch_drake.common.checks import check_finite_positive
    from ditch_drake.common.files import prepare_output
    from ditch_drake.learning.gate_calibration import (
        calibration_values,
        load_signals,
        quantile_thresholds,
        replay_fallback_share,
        rollover_warnings,
        signal_before_rollovers,
    )
    from ditch_drake.systems.shared_control import SharedControlConfig

    if args.window is not None and not args.figure:
        raise ConfigError(f"--window {args.window:g} without --figure: it sets the figure's span; expected --figure PNG "
                          "beside it")
    window = check_finite_positive(FIGURE_WINDOW_S if args.window is None else args.window, "--window")
    if args.figure:
        prepare_output(args.figure, "--figure")
    gates = [SharedControlConfig(signal=args.signal, budget=budget, calibration=args.signals, calm_steps=args.calm_steps,
                                 warmup_steps=args.warmup_steps).resolved() for budget in args.budget]
    episodes = calibration_values(args.signals, args.signal)
    signals = load_signals(args.signals)
    values = np.concatenate([episode[args.warmup_steps:] for episode in episodes])
    rows = []
    for gate in gates:
        upper, lower = gate.upper_threshold, gate.lower_threshold
        replay = (gate.calm_steps, gate.warmup_steps)
        quantile_rule = replay_fallback_share(episodes, *quantile_thresholds(values, gate.budget), *replay)
        rows.append({"budget": f"{gate.budget:g}", "upper_threshold": f"{upper:.4g}", "lower_threshold": f"{lower:.4g}",
                     "quantile_share": f"{np.mean(values > upper):.4f}",
                     "replayed_share": f"{replay_fallback_share(episodes, upper, lower, *replay):.4f}",
                     "replayed_share_quantile_rule": f"{quantile_rule:.4f}",
                     **_warning_columns(rollover_warnings(signals, args.signal, upper, lower, *replay))})
    print_table(rows, list(rows[0]))
    print(f"{args.signal} over {values.size} steps of {len(episodes)} episodes in {args.signals} (the first "
          f"{args.warmup_steps} of each ignored); calm_steps {args.calm_steps}. quantile_share: the share of the steps above the upper threshold; replayed_share: "
          "the fallback's share with the gate replayed over each episode; replayed_share_quantile_rule: the same "
          "with the quantiles at the budget itself (ThriftyDAgger's rule, the hysteresis not counted); "
          "rollovers_warned: of the episodes that rolled over, those whose last step the replayed gate handed the "
          "fallback; median_warning_s, least_warning_s: the median and the least time from that handover to the "
          "rollover, over those (on the policy's own path: a real handover changes what follows).")
    if args.figure:
        from ditch_drake.evaluation.gate_figure import rollover_signal_figure

        traces = signal_before_rollovers(signals, args.signal, window)
        rollover_signal_figure(traces, args.signal, [(g.budget, g.upper_threshold) for g in gates], args.figure,
                               f"{args.signal} before the {len(traces)} rollovers of {os.path.basename(args.signals)}")
        print(f"figure: {args.figure}")
    return 0


def _warning_columns(warnings) -> dict:
    """`gate-thresholds`' columns of `rollover_warnings`: how many were warned, and how early."""
    import numpy as np

    warned = warnings[np.isfinite(warnings)]
    return {"rollovers_warned": f"{warned.size}/{warnings.size}",
            "median_warning_s": f"{np.median(warned):.1f}" if warned.size else "-",
            "least_warning_s": f"{warned.min():.1f}" if warned.size else "-"}
